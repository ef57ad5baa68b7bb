"""Training O and Q end to end (bevo_ros.training.trainer, bevo train).

Evidence that learning works, on a synthetic bumpy drive with known noise (strong suspension
bumps and accelerometer vibration, half-resolution KITTI-like camera to keep rendering cheap):
the gradient reaches O and Q, the windowed, accumulated gradient equals plain autograd through
one run_sequence graph, and a few epochs from a deliberately bad start (O large = the filter follows the
vibrating accelerometer) lower both the validation loss and the relative pose error.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from helpers.drives import make_bumpy_bag

from bevo_ros.commands import train as train_command
from bevo_ros.config import REPO_ROOT, load_config
from bevo_ros.io.learned_params import load_learned_params
from bevo_ros.core.loss import registration_kl_loss
from bevo_ros.core.sequence import registration_targets, run_sequence
from bevo_ros.datasets.rosbag import load_sequence
from bevo_ros.training import trainer as training
from bevo_ros.training.trainer import TrainOptions, load_checkpoint, make_dukf, sequence_pass, train

SYNTH_PARAMS = REPO_ROOT / "params" / "synthetic.yaml"
BAD_INIT = (1.0, 1.0, 1e-2, 1e-2)  # O 1 rad^2/s at 100 Hz: per-step variance = Q -> follows the accelerometer


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    path = make_bumpy_bag(tmp_path_factory.mktemp("train") / "bumpy_bag")
    config, _ = load_config(SYNTH_PARAMS)
    seq = load_sequence(path, config)
    print(f"\nsynthetic bumpy bag: {len(seq)} frames, {seq.imu_stamps.numel()} IMU samples "
          f"({time.perf_counter() - t0:.1f} s to render and write)")
    return path, config, seq


def test_gradient_reaches_o_and_q_and_equals_plain_autograd(synth):
    _, config, seq = synth
    part = seq.frames(0, 13)
    dukf = make_dukf(BAD_INIT[:2], BAD_INIT[2:], config.filter.motion_model)
    r = sequence_pass(dukf, part, config, backward=True, window=5)  # 3 windows: the accumulation path
    g_o, g_q = dukf.log_process_var.grad.clone(), dukf.log_measurement_var.grad.clone()
    print(f"\nloss {r.loss:.4f}; dL/dlog O {g_o.tolist()}, dL/dlog Q {g_q.tolist()}")
    assert math.isfinite(r.loss) and r.n_failed == 0
    for g in (g_o, g_q):
        assert bool(torch.isfinite(g).all()) and bool((g.abs() > 0).all())

    # The same loss through run_sequence in one graph (no window, no accumulation): same motion, loss and gradient.
    ref = make_dukf(BAD_INIT[:2], BAD_INIT[2:], config.filter.motion_model)
    spec = training.bev_spec(config)
    mounting = (config.filter.mounting_pitch, config.filter.mounting_roll)
    res = run_sequence(ref, part.camera, spec, training.loss_dpc(), part.imu_stamps, part.gyro, part.accel,
                       part.frame_stamps, part.images, config.filter.road_tilt_time_constant,
                       mounting_attitude=mounting)
    angle, shift = registration_targets(part.gt_motion(), spec)
    loss = registration_kl_loss(res.registration, angle, shift, training.SIGMA_ANGLE, training.SIGMA_SHIFT)
    loss.backward()
    assert torch.allclose(r.motion, res.motion.detach().double(), atol=1e-4)
    assert abs(float(loss.detach()) - r.loss) < 1e-4 * max(1.0, abs(r.loss))
    assert torch.allclose(ref.log_process_var.grad, g_o, rtol=1e-3, atol=1e-6)
    assert torch.allclose(ref.log_measurement_var.grad, g_q, rtol=1e-3, atol=1e-6)

    # The engine's options: a mounting tilt and the turn compensation (its first pass windowed too) give the
    # unwindowed motion.
    config.filter.mounting_pitch, config.filter.turn_compensation = 0.01, True
    try:
        with torch.no_grad():
            r2 = sequence_pass(ref, part, config, window=5)
            res2 = run_sequence(ref, part.camera, spec, training.loss_dpc(), part.imu_stamps, part.gyro, part.accel,
                                part.frame_stamps, part.images, config.filter.road_tilt_time_constant,
                                mounting_attitude=(0.01, config.filter.mounting_roll), turn_compensation=True)
    finally:
        config.filter.mounting_pitch, config.filter.turn_compensation = mounting[0], False
    assert torch.allclose(r2.motion, res2.motion.double(), atol=1e-4)
    assert torch.allclose(r2.pitch_roll_road, res2.pitch_roll_road.double(), atol=1e-9)
    assert not torch.allclose(r2.motion, r.motion, atol=1e-3)

    before = [p.detach().clone() for p in (dukf.log_process_var, dukf.log_measurement_var)]
    torch.optim.Adam([dukf.log_process_var, dukf.log_measurement_var], lr=0.1).step()
    after = [dukf.log_process_var.detach(), dukf.log_measurement_var.detach()]
    for b, a in zip(before, after):
        assert bool((a != b).all()), "one optimiser step must change every log-variance"


def test_a_frame_off_the_road_fails_its_two_pairs_across_windows(synth):
    """A BEV without a valid pixel (the camera tilted to the sky) cannot be registered: its two pairs
    get zero motion and the uniform distribution's loss, the other pairs are untouched."""
    _, config, seq = synth
    part = seq.frames(0, 8)
    level = torch.zeros(len(part), 2, dtype=torch.float64)
    tilted = level.clone()
    tilted[3, 0] = 1.3  # frame 3 ends window 0 and starts window 1 (window=3)
    base = sequence_pass(None, part, config, source="given", given_pitch_roll_road=level, window=3)
    r = sequence_pass(None, part, config, source="given", given_pitch_roll_road=tilted, window=3)
    assert base.n_failed == 0 and r.failed.tolist() == [False, False, True, True, False, False, False]
    assert torch.all(r.motion[2:4] == 0) and torch.equal(r.motion[[0, 1, 4, 5, 6]], base.motion[[0, 1, 4, 5, 6]])
    pairs_2_3 = sequence_pass(None, part.frames(2, 5), config, source="given", given_pitch_roll_road=level[2:5])
    angle, shift = registration_targets(part.gt_motion()[2:4], training.bev_spec(config))
    uniform = float(training._uniform_kl(angle, shift, training.loss_dpc(), training.bev_spec(config).size,
                                         training.SIGMA_ANGLE, training.SIGMA_SHIFT))
    assert r.loss * 7 == pytest.approx(base.loss * 7 - pairs_2_3.loss * 2 + uniform, rel=1e-6)


def test_training_lowers_validation_loss_and_pose_error(synth):
    _, config, seq = synth
    opts = TrainOptions(epochs=4, lr=0.5, steps_per_bag=4, patience=0, init=BAD_INIT, init_search=0)
    t0 = time.perf_counter()
    result = train([seq], config, opts, progress=False)
    b, a = result.before, result.after
    o, q = result.learned.process_noise_density, result.learned.measurement_noise_variance
    print(f"\nbefore (O {BAD_INIT[:2]}, Q {BAD_INIT[2:]}): val loss {b.loss:.4f}, RPE {b.trans_m:.4f} m, "
          f"{b.yaw_deg:.4f} deg per frame")
    print(f"after  (O [{o[0]:.3g}, {o[1]:.3g}], Q [{q[0]:.3g}, {q[1]:.3g}]): val loss {a.loss:.4f}, "
          f"RPE {a.trans_m:.4f} m, {a.yaw_deg:.4f} deg per frame; {result.seconds_per_epoch:.1f} s/epoch, "
          f"{time.perf_counter() - t0:.1f} s")
    assert result.status == "completed" and result.epochs_run == 4
    assert a.loss < b.loss - 0.5
    assert a.trans_m < 0.7 * b.trans_m
    assert a.yaw_deg < 0.7 * b.yaw_deg
    # The filter now trusts the gyro far more than the accelerometer (ratio O/Q down).
    assert o[0] / q[0] < 0.1 * BAD_INIT[0] / BAD_INIT[2]


def test_cli_writes_loadable_yaml_and_resumes(synth, tmp_path, capsys):
    bag_path, _, _ = synth
    tool = train_command
    out = tmp_path / "learned.yaml"
    common = [str(bag_path), "--out", str(out), "--params", str(SYNTH_PARAMS), "--lr", "0.5", "--steps-per-bag",
              "3", "-q"]
    assert tool.main(common + ["--epochs", "1", "--init", *map(str, BAD_INIT), "--suspension-evals", "0"]) == 0
    learned = load_learned_params(out)
    info = learned.info
    print(f"\nafter 1 epoch: O {learned.process_noise_density}, Q {learned.measurement_noise_variance}; "
          f"validation {info['validation_before']} -> {info['validation_after']}")
    assert info["training_bags"] == ["bumpy_bag"] and info["split"] == "3/4" and info["epochs_run"] == 1
    assert info["init"]["mode"].startswith("given")
    assert "date" in info and "code_version" in info and "validation_before" in info
    # what O/Q training does not learn is kept from the configuration's learned file
    base = load_learned_params(load_config(SYNTH_PARAMS)[0].learned_params_file)
    assert learned.suspension_gradients == base.suspension_gradients != (0.0, 0.0)
    ckpt_path = tmp_path / "learned.yaml.ckpt.yaml"
    text = ckpt_path.read_text()
    assert "!!python" not in text and "&id" not in text  # plain YAML
    ckpt = load_checkpoint(ckpt_path)
    assert ckpt["epoch"] == 1 and len(ckpt["history"]) == 1 and ckpt["adam"]["log_process_var"]["step"] == 3

    capsys.readouterr()
    assert tool.main(common + ["--epochs", "2", "--resume", str(ckpt_path), "--suspension-evals", "3"]) == 0
    said = capsys.readouterr().out
    assert "suspension (" in said and "engine runs" in said  # the fused params learn the suspension too
    ckpt2 = load_checkpoint(ckpt_path)
    assert ckpt2["epoch"] == 2 and [h["epoch"] for h in ckpt2["history"]] == [1, 2]
    assert ckpt2["adam"]["log_process_var"]["step"] == 6
    assert ckpt2["before"] == ckpt["before"]  # the same run, continued
    resumed = load_learned_params(out)
    assert resumed.info["epochs_run"] == 2
    # kept only when the validation frames say so, and then recorded
    fit = resumed.info.get("suspension_fit")
    if fit is None:
        assert resumed.suspension_gradients == base.suspension_gradients
    else:
        assert tuple(fit["from"]) == base.suspension_gradients
        assert fit["validation_rmse"][1] <= fit["validation_rmse"][0] and fit["engine_runs"] >= 3
    with pytest.raises(SystemExit) as refused:  # refused before training, as argparse refuses
        tool.main(common + ["--epochs", "1", "--suspension-evals", "2"])
    assert refused.value.code == 2


def test_divergence_stops_cleanly_keeping_the_last_good_values(synth, tmp_path, capsys):
    bag_path, config, seq = synth
    tool = train_command
    out = tmp_path / "learned.yaml"
    rc = tool.main([str(bag_path), "--out", str(out), "--params", str(SYNTH_PARAMS), "--epochs", "3", "--lr", "1e6",
                    "--init", *map(str, BAD_INIT), "--suspension-evals", "0", "-q"])
    err = capsys.readouterr().err
    print(err)
    assert rc == 3 and "diverged" in err
    learned = load_learned_params(out)  # valid file with the last good (= initial, the only validated) values
    assert np.allclose(learned.process_noise_density, BAD_INIT[:2]) and np.allclose(
        learned.measurement_noise_variance, BAD_INIT[2:])
    ckpt = load_checkpoint(tmp_path / "learned.yaml.ckpt.yaml")
    assert "diverged" in ckpt and np.allclose(ckpt["current"]["process_noise_density"], BAD_INIT[:2])

    # A NaN loss in the middle of epoch 2 (injected): epoch 1's parameters survive.
    calls = {"n": 0}
    real = training.registration_kl_loss

    def flaky(*args, **kwargs):
        calls["n"] += 1
        loss = real(*args, **kwargs)
        return loss * float("nan") if calls["n"] == 6 else loss

    training.registration_kl_loss = flaky
    try:
        opts = TrainOptions(epochs=3, lr=0.5, steps_per_bag=2, window=64, patience=0, init=BAD_INIT, init_search=0)
        result = train([seq], config, opts, progress=False, log=lambda m: None)
    finally:
        training.registration_kl_loss = real
    # calls: 1 initial validation, 2-3 epoch-1 steps, 4 validation, 5-6 epoch-2 steps: NaN at the 2nd step
    print(f"injected NaN: {result.message}")
    assert result.status == "diverged" and "loss is nan" in result.message
    assert result.epochs_run == 1 and result.best_epoch == 1
    e1 = result.history[0]
    assert np.allclose(result.last_good[0], e1["process_noise_density"])
    assert np.allclose(result.learned.process_noise_density, e1["process_noise_density"])
    assert all(math.isfinite(v) and v > 0 for v in (*result.learned.process_noise_density,
                                                     *result.learned.measurement_noise_variance))


def test_initialisation_units_device_fallback_and_bad_checkpoints(tmp_path):
    # Paper: uniform in [0, 1] per IMU step -> our density = draw / IMU period; Q as drawn.
    o, q, u = training.random_init(5, 0.01)
    assert np.allclose(o, (u[0] / 0.01, u[1] / 0.01)) and np.allclose(q, u[2:]) and all(0 < v <= 1 for v in u)
    assert training.random_init(5, 0.01) == (o, q, u)  # seeded: repeatable
    if not torch.cuda.is_available():
        with pytest.warns(RuntimeWarning, match="CUDA is not available"):
            assert training.resolve_device("cuda") == torch.device("cpu")
    with pytest.raises(ValueError):
        training.resolve_device("tpu")
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"format": training.CHECKPOINT_FORMAT, "epoch": 1,
                                   "current": {"process_noise_density": [1.0, float("nan")],
                                               "measurement_noise_variance": [1.0, 1.0]},
                                   "best": {"process_noise_density": [1.0, 1.0],
                                            "measurement_noise_variance": [1.0, 1.0]}}))
    with pytest.raises(ValueError, match="current.process_noise_density"):
        load_checkpoint(bad)
    with pytest.raises(ValueError, match="not a BEVO training checkpoint"):
        bad.write_text("format: something/1\n")
        load_checkpoint(bad)
    with pytest.raises(ValueError):
        TrainOptions(split="1/2").check()
    with pytest.raises(ValueError):
        TrainOptions(init=(1.0, 1.0, 0.0, 1.0)).check()
