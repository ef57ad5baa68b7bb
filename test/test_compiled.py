"""core.compiled: the engine's optional torch.compile kernels agree with the eager functions, fall
back to eager on a compiler failure (one warning, never a crash), and the ``kernels`` setting."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from bevo_ros.config import BevoConfig, ConfigError, build_odometry
from bevo_ros.core import compiled as compiled_module
from bevo_ros.core.compiled import EngineKernels, compiler_available
from bevo_ros.core.phase_correlation import InvalidBevError
from bevo_ros.datasets.synthetic import make_drive
from bevo_ros.io.learned_params import LearnedParams

from helpers.env import in_ci

needs_compiler = pytest.mark.skipif(not compiler_available() and not in_ci(),  # CI: README's setup has one
                                    reason="no C++ compiler (g++/c++/clang++): torch.compile's CPU backend cannot build")


def _engines(drive, *modes):
    out = []
    for mode in modes:
        config = BevoConfig()
        config.kernels = mode
        out.append(build_odometry(config, LearnedParams(), camera=drive.camera))
    return out


def _run(odo, drive, frames):
    steps, i = [], 0
    for f, stamp in enumerate(drive.frame_stamps[:frames]):
        while i < len(drive.imu_stamps) and drive.imu_stamps[i] <= stamp:
            steps += odo.add_imu(float(drive.imu_stamps[i]), drive.gyro[i], drive.accel[i])
            i += 1
        steps += odo.add_image(float(stamp), np.asarray(drive.image(f)))
    return steps + odo.flush()


@pytest.mark.slow  # ~13 s: three kernels compile (less with inductor's cache warm)
@needs_compiler
def test_compiled_kernels_agree_with_eager():
    """The same inputs through each compiled kernel and its eager function: float32 rounding apart;
    then a short synthetic drive through an eager and a compiled engine."""
    drive = make_drive(seed=5, duration=2.0, render="lazy")
    eager_odo, odo = _engines(drive, "eager", "compiled")
    k, dpc, spec, cam = odo.kernels, odo.dpc, odo.spec, odo.camera
    assert k.compiled and not eager_odo.kernels.compiled
    with torch.inference_mode():
        prepared, bevs = [], []
        for f, (pitch, roll) in enumerate([(0.02, -0.01), (0.025, -0.008), (0.018, -0.012)]):
            image = torch.as_tensor(np.asarray(drive.image(f)))[None, None]
            p, r = torch.tensor([pitch]), torch.tensor([roll])
            bev, mask = k.project_to_bev(image, cam, p, r, spec)  # the first call of each kernel is eager
            bev, mask = k.project_to_bev(image, cam, p, r, spec)
            bev0, mask0 = eager_odo.kernels.project_to_bev(image, cam, p, r, spec)
            assert torch.equal(mask, mask0)
            torch.testing.assert_close(bev, bev0, rtol=0, atol=1e-4)
            for _ in range(2):
                weight = k.mask_weight(mask0, dpc, bev0.dtype)
            weight0 = eager_odo.kernels.mask_weight(mask0, dpc, bev0.dtype)
            torch.testing.assert_close(weight.weight, weight0.weight, rtol=0, atol=1e-5)
            prepared.append(k.prepare(bev0, mask0, dpc, weight0))
            bevs.append(bev0)
        # As the fused engine calls it (the gyro's angle, the cached envelope): one compiled graph,
        # which the drive below reuses (each other argument pattern is a compilation of its own).
        for prev, curr, angle in ((prepared[0], prepared[1], 0.01), (prepared[1], prepared[2], -0.004)):
            kw = dict(angle=torch.tensor([angle]), angle_std=torch.tensor([0.002]),
                      envelope=k.overlap_envelope(prev.weight_spectrum, curr.weight_spectrum),
                      forward_range=torch.tensor([[-1.0, float("inf")]]))  # the direction of travel
            reg = k.register_prepared(prev, curr, dpc, **kw)
            reg = k.register_prepared(prev, curr, dpc, **kw)
            reg0 = eager_odo.kernels.register_prepared(prev, curr, dpc, **kw)
            # The whitening divides by each bin's magnitude: a weak bin's rounding counts more
            # (measured: shift 1e-4 px, quality 1.3e-3 of 0.63 on a pair derotated 0.002 rad off).
            torch.testing.assert_close(reg.angle, reg0.angle, rtol=0, atol=1e-5)
            torch.testing.assert_close(reg.shift, reg0.shift, rtol=0, atol=2e-3)
            torch.testing.assert_close(reg.quality, reg0.quality, rtol=0, atol=5e-3)
            torch.testing.assert_close(reg.shift_cov, reg0.shift_cov, rtol=1e-2, atol=1e-6)
            torch.testing.assert_close(reg.angle_std, reg0.angle_std, rtol=1e-2, atol=1e-7)
            for _ in range(2):
                motion = k.vehicle_motion_from_registration(reg0.angle, reg0.shift, spec)
                cov = k.motion_covariance_from_registration(reg0, spec)
            torch.testing.assert_close(motion, eager_odo.kernels.vehicle_motion_from_registration(
                reg0.angle, reg0.shift, spec), rtol=0, atol=1e-6)
            torch.testing.assert_close(cov, eager_odo.kernels.motion_covariance_from_registration(reg0, spec),
                                       rtol=1e-5, atol=1e-10)
        # The function's own errors come through the compiled kernel as they are, no fallback.
        with pytest.raises(InvalidBevError):
            k.mask_weight(torch.zeros_like(bevs[0]), dpc, bevs[0].dtype)
    assert k.fallbacks == {}
    eager_steps, steps = _run(eager_odo, drive, 15), _run(odo, drive, 15)
    assert len(steps) == len(eager_steps) == 15
    for a, b in zip(eager_steps, steps):
        np.testing.assert_allclose(b.position, a.position, rtol=0, atol=2e-3)
        np.testing.assert_allclose(b.motion, a.motion, rtol=0, atol=1e-3)
    assert odo.kernels.fallbacks == {}


def test_compiler_failure_falls_back_to_eager_with_one_warning(monkeypatch):
    """A compiler that fails (here every compiled call raises inductor's own error, as without a
    C++ compiler) costs one warning; the engine's numbers are then exactly the eager ones."""
    def broken_compile(fn, **kwargs):
        def call(*args, **kw):
            raise torch._inductor.exc.InductorError(RuntimeError("no C++ compiler"), None)
        return call

    monkeypatch.setattr(compiled_module.torch, "compile", broken_compile)
    drive = make_drive(seed=5, duration=1.0, render="lazy")
    eager_odo, odo = _engines(drive, "eager", "compiled")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        steps = _run(odo, drive, 6)
    fallbacks = [w for w in caught if "torch.compile of" in str(w.message)]
    assert set(odo.kernels.fallbacks) >= {"project_to_bev", "register_prepared", "vehicle_motion_from_registration",
                                          "motion_covariance_from_registration"}
    assert len(fallbacks) == 1, [str(w.message) for w in fallbacks]
    assert "InductorError" in str(fallbacks[0].message) and fallbacks[0].category is RuntimeWarning
    for a, b in zip(_run(eager_odo, drive, 6), steps, strict=True):
        np.testing.assert_array_equal(b.position, a.position)


def test_kernels_setting():
    assert BevoConfig().kernels == "eager"
    assert BevoConfig.from_flat({"kernels": "compiled"}).kernels == "compiled"
    config = BevoConfig()
    config.kernels = "fast"
    with pytest.raises(ConfigError, match="kernels must be one of eager, compiled, auto"):
        build_odometry(config, LearnedParams())
    with pytest.raises(ValueError, match="kernels must be one of"):
        EngineKernels("on")
    assert EngineKernels("auto").compiled == compiler_available()
    assert not EngineKernels().compiled
