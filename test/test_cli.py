"""The `bevo` command (bevo_ros.cli): every subcommand's help, dump-config round trip, one error
convention (message on stderr, exit 2)."""
from __future__ import annotations

import subprocess
import sys

import pytest
import yaml

from bevo_ros import cli
from bevo_ros.config import BevoConfig, REPO_ROOT, dump_params_yaml, load_config, load_params_file

ALL = [*cli.COMMANDS, cli.DUMP_CONFIG]


def test_the_command_is_registered_as_a_console_script():
    assert "bevo = bevo_ros.cli:main" in (REPO_ROOT / "setup.py").read_text()
    assert "bevo demo" in (REPO_ROOT / "Makefile").read_text()


@pytest.mark.parametrize("command", ALL)
def test_help_of_each_subcommand(command, capsys):
    assert cli.main([command, "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: bevo {command}"), out[:200]  # the command's own options, under its bevo name
    assert "--help" in out


def test_top_level_help_lists_every_command(capsys):
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    for command in ALL:
        assert f"  {command} " in out


@pytest.mark.parametrize("argv, message", [
    ([], "usage: bevo"),
    (["no-such-command"], "invalid choice"),
    (["run", "bag", "--out", "o", "--no-such-option"], "unrecognized arguments"),
    (["run"], "the following arguments are required"),
    (["evaluate", "--gt", "/nonexistent/gt.txt", "--est", "/nonexistent/est.txt", "--out", "/tmp/x"], "error"),
    (["dump-config", "--bogus"], "unrecognized arguments"),
])
def test_errors_exit_2_with_a_message(argv, message, capsys):
    assert cli.main(argv) == 2
    captured = capsys.readouterr()
    assert message in captured.err + captured.out


def test_an_uncaught_bad_input_is_reported_not_raised(tmp_path, capsys, monkeypatch):
    """A ValueError escaping a command is the same convention: `bevo CMD: error: ...`, exit 2."""
    def boom(name, argv):
        raise ValueError("bad value in the input")

    monkeypatch.setattr(cli, "run_command", boom)
    assert cli.main(["run", "x"]) == 2
    assert "bevo run: error: bad value in the input" in capsys.readouterr().err


def test_dump_config_round_trips_through_load_config(tmp_path, capsys):
    assert cli.main([cli.DUMP_CONFIG]) == 0
    text = capsys.readouterr().out
    path = tmp_path / "all.yaml"
    path.write_text(text)
    config, flat = load_config(path)
    default = BevoConfig()
    expected = default.to_flat()
    assert set(expected) <= set(flat)  # every engine field is in the file
    got = config.to_flat()
    assert got.pop("learned_params_file") == str(REPO_ROOT / "params" / "learned_default.yaml")
    expected.pop("learned_params_file")
    assert got == expected
    for name, value in expected.items():  # also typed as the dataclass has it (1e-05 must not read as text)
        assert type(flat[name]) is type(value), name
    from bevo_ros.ros.settings import NodeSettings

    for field in NodeSettings.__dataclass_fields__:  # and the node's own settings
        assert field in flat
    assert "# camera centre height above the road (m)" in text  # documented


def test_dump_config_of_a_changed_config_reads_back_equal(tmp_path):
    config = BevoConfig()
    config.filter.max_imu_gap = 1e-5  # repr "1e-05": YAML 1.1 needs a dot
    config.odometry.mode = "paper"
    config.camera.base_T_camera = [float(i) for i in range(16)]
    config.bev.size = 64
    config.learned_params_file = str(REPO_ROOT / "params" / "learned_paper.yaml")
    path = tmp_path / "changed.yaml"
    cli_text = dump_params_yaml(config)
    path.write_text(cli_text)
    assert load_config(path)[0] == config
    assert isinstance(yaml.safe_load(cli_text)["/**"]["ros__parameters"]["filter.max_imu_gap"], float)
    assert load_params_file(path)["bev.size"] == 64


def test_a_warning_is_one_line_naming_the_command(tmp_path, capsys):
    """A parameters file with a typo: the warning reads as the errors do (``bevo run: warning: ...``),
    not as Python's (file, line number, ``UserWarning``, the source line)."""
    params = tmp_path / "typo.yaml"
    params.write_text((REPO_ROOT / "params" / "kitti.yaml").read_text().replace("    odometry.mode:", "    odometry.mod:"))
    # as a user runs it (in the test process pytest records warnings instead of printing them)
    r = subprocess.run([sys.executable, "-m", "bevo_ros.cli", "run", str(tmp_path / "no_bag"), "--out",
                        str(tmp_path / "out"), "--params", str(params)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    err = r.stderr
    lines = [line for line in err.splitlines() if "odometry.mod" in line]
    assert len(lines) == 1 and lines[0].startswith("bevo run: warning: ") and "did you mean odometry.mode?" in lines[0], err
    assert "UserWarning" not in err and "load_config(" not in err and "bevo run: error:" in err, err


def test_dump_config_from_a_params_file_keeps_its_rig(tmp_path, capsys):
    """``--params FILE``: every setting, FILE's where it sets one (the KITTI rig's mounting, its node
    wiring), the defaults elsewhere; the dump reads back as FILE does. Without it the defaults' mounting
    is 0 (a KITTI bag run with them drifted ~37 %), hence the option; a missing file is a clear error."""
    rig = tmp_path / "rig"
    rig.mkdir()
    kitti = rig / "kitti.yaml"  # the KITTI rig with a node setting of its own and its learned file beside it
    text = (REPO_ROOT / "params" / "kitti.yaml").read_text()
    assert "    imu_topic: imu/data " in text and "    learned_params_file: params/learned_default.yaml" in text
    kitti.write_text(text.replace("    imu_topic: imu/data ", "    imu_topic: x/imu ").replace(
        "    learned_params_file: params/learned_default.yaml", "    learned_params_file: mine.yaml"))
    (rig / "mine.yaml").write_text((REPO_ROOT / "params" / "learned_default.yaml").read_text())
    for out in (rig / "k.yaml", tmp_path / "elsewhere" / "k.yaml"):
        out.parent.mkdir(exist_ok=True)
        assert cli.main([cli.DUMP_CONFIG, "--params", str(kitti), "-o", str(out)]) == 0
        dumped, flat = load_config(out)
        original, original_flat = load_config(kitti)
        assert dumped == original and dumped.filter.mounting_pitch != BevoConfig().filter.mounting_pitch
        assert set(BevoConfig().to_flat()) <= set(flat)  # complete
        assert flat["imu_topic"] == "x/imu" and original_flat["imu_topic"] == "x/imu"  # the node's settings too
        # the learned file as written where that still names it (beside the dump), else its absolute path
        written = "mine.yaml" if out.parent == rig else str(rig / "mine.yaml")
        assert f'learned_params_file: "{written}"' in out.read_text()
    assert cli.main([cli.DUMP_CONFIG, "--params", str(tmp_path / "none.yaml")]) == 2
    assert "bevo dump-config: error: parameters file not found" in capsys.readouterr().err


def test_dump_config_to_a_file_and_run_as_a_module(tmp_path):
    out = tmp_path / "p.yaml"
    r = subprocess.run([sys.executable, "-m", "bevo_ros.cli", "dump-config", "--engine-only", "-o", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert load_config(out)[0].bev == BevoConfig().bev
    assert "imu_topic" not in out.read_text()  # --engine-only


def test_calibrate_prints_the_params_lines_with_their_reference(tmp_path, capsys):
    """``bevo calibrate`` on a level synthetic drive (no mounting tilt, no road tilt): the pitch
    comes back ~0, and the lines say the mounting was fitted through camera.base_T_camera
    (``filter.mounting_reference: camera``) and that it is not to be measured again at the engine's start
    (``filter.tilt_from_images: 0``); the lines paste into a params file as YAML."""
    from bevo_ros.datasets.rosbag import write_drive_bag
    from bevo_ros.datasets.synthetic import make_drive

    drive = make_drive(seed=3, duration=2.0, bumps=0.0, road_tilt=False, render="lazy")
    bag_path = write_drive_bag(drive, tmp_path / "bag")
    assert cli.main(["calibrate", str(bag_path), "--params", str(REPO_ROOT / "params" / "synthetic.yaml"),
                     "--frames", "0:11"]) == 0
    lines = [ln.strip() for ln in capsys.readouterr().out.splitlines() if ln.strip().startswith("filter.")]
    params = yaml.safe_load("\n".join(lines))
    assert set(params) == {"filter.mounting_pitch", "filter.mounting_roll", "filter.mounting_reference",
                           "filter.tilt_from_images"}
    assert params["filter.mounting_reference"] == "camera"
    assert params["filter.tilt_from_images"] == 0  # the fitted pitch as is, not the engine start's measurement
    assert abs(params["filter.mounting_pitch"]) < 0.001  # rad: the drive's rig sits level on the road


def test_an_empty_folder_and_a_bare_on_are_named_for_what_they_are(tmp_path, capsys):
    """Two slips a user makes: an empty folder given as the bag (rosbags named the folder as the
    metadata file) and ``undistort: on`` unquoted (YAML reads a bool where the setting is text)."""
    from bevo_ros.config import ConfigError, coerce_setting

    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli.main(["run", str(empty), "--out", str(tmp_path / "out")]) == 2
    assert f"bevo run: error: {empty}: not a rosbag2 folder (it has no metadata.yaml)" in capsys.readouterr().err
    with pytest.raises(ConfigError, match=r"'undistort' = True is not a valid str \(YAML reads a bare on as "
                                          r"true/false: quote it, 'on'\)"):
        coerce_setting(True, "auto", "undistort")
    assert coerce_setting("on", "auto", "undistort") == "on"
