"""The engine's vision kernels, optionally through ``torch.compile`` (inference only).

:class:`BevoOdometry` calls the BEV projection, the mask weight and the registration through one
:class:`EngineKernels`. With ``compile="off"`` (the default) they are the plain functions, so the
engine's numbers are the pinned ones. With ``"compiled"`` (or ``"auto"``: compiled when a C++
compiler is found) the three are compiled by TorchInductor on their first call (seconds), which fuses the
~250 small tensor operations of these stages into a few loops. The FFT preparation stays eager:
inductor's FFT and complex-magnitude path measured slower than eager on the CPU.

Compiled results equal the eager ones to float32 rounding (~1e-5 on the BEV, test_compiled.py),
not bit for bit: the fused motion filter's gates can then decide a borderline frame differently,
so a long compiled run drifts apart from an eager one by what such a decision moves.

Never a crash: a compilation or compiled-call failure of the compiler's own (no compiler, an
unsupported operation) logs one warning and that kernel runs eagerly from then on; errors of the
functions themselves (e.g. ``InvalidBevError``) propagate as they do eagerly. Gradients are not
supported through compiled kernels: training calls the functions directly, never these.
"""
from __future__ import annotations

import shutil
import warnings
from typing import Callable

import torch

from .bev import project_to_bev
from .phase_correlation import mask_weight, overlap_envelope, prepare, register_prepared

KERNEL_MODES = ("eager", "compiled", "auto")
KERNELS = ("project_to_bev", "mask_weight", "register_prepared")  # compiled with "compiled"
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
    failure (one warning).

    The eager first call fills the constant caches (:func:`~bevo_ros.core.device.constant_cache`):
    traced with them filled, the graph takes the cached tensors as inputs instead of rebuilding them,
    and no cache changes under it later (which would recompile it)."""

    def __init__(self, fn: Callable, log: Callable[[str], None] | None) -> None:
        self.fn = fn
        self.name = fn.__name__
        self._log = log
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
            self.failed = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
            msg = f"torch.compile of {self.name} failed ({self.failed[:300]}): running it eagerly"
            warnings.warn(msg, RuntimeWarning, stacklevel=2)
            if self._log is not None:
                self._log(msg)
            return self.fn(*args, **kwargs)


class EngineKernels:
    """The vision functions the engine calls, eager or compiled (see the module docstring).

    Args:
        mode: ``"eager"``, ``"compiled"`` or ``"auto"`` (compiled when :func:`compiler_available`).
        log: called with the one warning of a fallback (e.g. a ROS logger's ``warning``).
    """

    def __init__(self, mode: str = "eager", log: Callable[[str], None] | None = None) -> None:
        if mode not in KERNEL_MODES:
            raise ValueError(f"kernels must be one of {KERNEL_MODES}, got {mode!r}")
        self.mode = mode
        self.compiled = mode == "compiled" or (mode == "auto" and compiler_available())
        self.prepare = prepare
        self.overlap_envelope = overlap_envelope
        for name, fn in (("project_to_bev", project_to_bev), ("mask_weight", mask_weight),
                         ("register_prepared", register_prepared)):
            setattr(self, name, _CompiledKernel(fn, log) if self.compiled else fn)

    @property
    def fallbacks(self) -> dict[str, str]:
        """The kernels that fell back to eager, with why."""
        return {name: k.failed for name in KERNELS if isinstance(k := getattr(self, name), _CompiledKernel)
                and k.failed is not None}


__all__ = ["KERNEL_MODES", "EngineKernels", "compiler_available"]
