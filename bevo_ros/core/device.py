"""The torch device a run asks for, with the one CUDA fallback rule (engine, training, map localisation)."""
from __future__ import annotations

import functools
import warnings
from typing import Callable

import torch


def resolve_device(device: str | torch.device, log: Callable[[str], None] | None = None,
                   what: str = "running") -> torch.device:
    """``cpu`` / ``cuda[:n]`` -> ``torch.device``; CUDA asked for but absent falls back to the CPU
    with a ``RuntimeWarning`` (and ``log(message)`` when given, e.g. a ROS logger's ``warning``).
    Anything else raises ``ValueError``."""
    name = str(device)
    if name.startswith("cuda"):
        if torch.cuda.is_available():
            return torch.device(name)
        msg = f"device {name!r} asked for but CUDA is not available: {what} on the CPU"
        warnings.warn(msg, RuntimeWarning, stacklevel=2)
        if log is not None:
            log(msg)
        return torch.device("cpu")
    if name != "cpu":
        raise ValueError(f"device must be 'cpu' or 'cuda[:n]', got {name!r}")
    return torch.device("cpu")


def constant_cache(maxsize: int = 32):
    """A cache for tensors that depend only on settings (grids, windows, bands): built outside
    inference mode, so the engine (which runs in ``torch.inference_mode``) and training (autograd,
    which cannot save an inference tensor) share them whoever asks first. Positional, hashable
    arguments; the oldest entry goes beyond ``maxsize``.

    A plain dict rather than ``functools.lru_cache``: ``torch.compile`` (the engine's optional
    compiled kernels, :mod:`~bevo_ros.core.compiled`) traces through an ``lru_cache`` and would
    rebuild every constant in each call, while a dict hit is a graph input it reuses."""
    def decorate(fn):
        store: dict = {}

        @functools.wraps(fn)
        def get(*args):
            hit = store.get(args)
            if hit is None:
                with torch.inference_mode(False):
                    hit = fn(*args)
                if len(store) >= maxsize:
                    store.pop(next(iter(store)))
                store[args] = hit
            return hit
        get.cache_clear = store.clear
        return get
    return decorate
