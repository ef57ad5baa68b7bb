"""The engine's vision kernels, optionally through ``torch.compile`` (inference only).

:class:`~bevo_ros.core.odometry.BevoOdometry` calls the BEV projection, the mask weight, the
registration and the registration's motion and covariance through one :class:`EngineKernels`.
With ``mode="eager"`` (the default) they are the plain functions, so the engine's numbers are the
pinned ones. With ``"compiled"`` (or ``"auto"``: compiled when a C++ compiler is found) each is
compiled by TorchInductor on its second call (seconds, once per process; inductor's on-disk cache
makes later starts faster), which fuses their ~250 small tensor operations per frame into a few
loops. The FFT preparation stays eager: inductor's FFT and complex-magnitude path measured slower
than eager on the CPU.

Compiled results equal the eager ones to float32 rounding (~1e-6 on the BEV and the correlation;
the whitening makes a weak frequency's rounding count, test_compiled.py), not bit for bit, so the
fused motion filter's gates can decide a borderline frame differently: a long compiled run drifts
apart from an eager one by what such a decision moves (10 s synthetic drive: 0.1 m of 72 m).

Never a crash: a failure of the compiler's own (no compiler, an unsupported operation) costs one
``RuntimeWarning`` (one per distinct reason) and the failing kernels run eagerly from then on; errors of the functions themselves (e.g.
``InvalidBevError``) propagate as they do eagerly. No gradients through compiled kernels: training
calls the functions directly, never these.
"""
from __future__ import annotations

import shutil
import warnings
from typing import Callable

import torch

from .bev import project_to_bev
from .motion import motion_covariance_from_registration, vehicle_motion_from_registration
from .phase_correlation import mask_weight, overlap_envelope, prepare, register_prepared

KERNEL_MODES = ("eager", "compiled", "auto")
KERNELS = ("project_to_bev", "mask_weight", "register_prepared", "vehicle_motion_from_registration",
           "motion_covariance_from_registration")  # compiled with "compiled"
EAGER_KERNELS = ("prepare", "overlap_envelope")  # always eager (measured slower compiled)


def compiler_available() -> bool:
    """A C++ compiler that TorchInductor's CPU backend can use (``$CXX``, ``g++``, ``c++``, ``clang++``)."""
    import os

    cxx = os.environ.get("CXX")
    return any(shutil.which(c) for c in ([cxx] if cxx else []) + ["g++", "c++", "clang++"])


def _is_compiler_error(exc: BaseException) -> bool:
    """An error of torch.compile's machinery (dynamo, inductor, the C++ build), not of the function."""
    mod = type(exc).__module__ or ""
    return mod.startswith(("torch._dynamo", "torch._inductor", "torch.fx", "torch._subclasses")) or isinstance(
        exc, (OSError, ImportError))


class _CompiledKernel:
    """``fn`` eager on its first call, compiled from the second on; eager for good after a compiler
    failure (``warn(name, reason)``).

    The eager first call fills the constant caches (:func:`~bevo_ros.core.device.constant_cache`):
    traced with them filled, the graph takes the cached tensors as inputs instead of rebuilding them,
    and no cache changes under it later (which would recompile it)."""

    def __init__(self, fn: Callable, warn: Callable[[str, str], None]) -> None:
        self.fn = fn
        self.name = fn.__name__
        self._warn = warn
        self._compiled = torch.compile(fn, dynamic=False)
        self._calls = 0
        self.failed: str | None = None

    def __call__(self, *args, **kwargs):
        self._calls += 1
        if self.failed is not None or self._calls == 1:
            return self.fn(*args, **kwargs)
        try:
            return self._compiled(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - sorted below: the compiler's or the function's
            if not _is_compiler_error(exc):
                raise
            self.failed = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"[:300]
            self._warn(self.name, self.failed)
            return self.fn(*args, **kwargs)


class EngineKernels:
    """The vision functions the engine calls, eager or compiled (see the module docstring).

    Args:
        mode: ``"eager"``, ``"compiled"`` or ``"auto"`` (compiled when :func:`compiler_available`).
        log: also called with each fallback warning (e.g. a ROS logger's ``warning``).

    A compiler failure is warned once per reason (``RuntimeWarning``): without a compiler every
    kernel fails the same way, and that is one warning.
    """

    def __init__(self, mode: str = "eager", log: Callable[[str], None] | None = None) -> None:
        if mode not in KERNEL_MODES:
            raise ValueError(f"kernels must be one of {KERNEL_MODES}, got {mode!r}")
        self.mode = mode
        self.compiled = mode == "compiled" or (mode == "auto" and compiler_available())
        self._log = log
        self._warned: set[str] = set()
        self.prepare = prepare
        self.overlap_envelope = overlap_envelope
        functions = dict(project_to_bev=project_to_bev, mask_weight=mask_weight, register_prepared=register_prepared,
                         vehicle_motion_from_registration=vehicle_motion_from_registration,
                         motion_covariance_from_registration=motion_covariance_from_registration)
        for name in KERNELS:
            setattr(self, name, _CompiledKernel(functions[name], self._fallback) if self.compiled else functions[name])

    def _fallback(self, name: str, reason: str) -> None:
        if reason in self._warned:
            return
        self._warned.add(reason)
        msg = f"torch.compile of the engine's kernels failed ({reason}; first in {name}): running them eagerly"
        warnings.warn(msg, RuntimeWarning, stacklevel=3)
        if self._log is not None:
            self._log(msg)

    @property
    def fallbacks(self) -> dict[str, str]:
        """The kernels that fell back to eager, with why."""
        return {name: k.failed for name in KERNELS if isinstance(k := getattr(self, name), _CompiledKernel)
                and k.failed is not None}


__all__ = ["KERNEL_MODES", "EngineKernels", "compiler_available"]
