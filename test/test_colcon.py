"""colcon builds the package, and the executable is found and started the way `ros2 run` does.

`ros2 run bevo_ros bevo_node` = ament index ``get_package_prefix('bevo_ros')`` (AMENT_PREFIX_PATH),
then the one executable named ``bevo_node`` under ``<prefix>/lib/bevo_ros``, run with the
arguments. The source is copied first so colcon writes nothing into the repository.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent
from helpers.env import skip_outside_ci  # noqa: E402
from helpers.ros import domain_id_for  # noqa: E402

DOMAIN_ID = str(domain_id_for(13))
pytestmark = [pytest.mark.ros, pytest.mark.timeout(240)]

COPY_IGNORE = shutil.ignore_patterns(".venv", ".git", "__pycache__", "*.egg-info", ".pytest_cache", "build",
                                     "install", "log", "out", "tmp", ".whl", ".gl")


def _find_executable(prefix: Path, package: str, name: str) -> Path:
    """ros2run's rule: exactly one executable file called ``name`` below ``<prefix>/lib/<package>``."""
    base = prefix / "lib" / package
    found = [Path(d) / f for d, _, files in os.walk(base) for f in files
             if f == name and os.access(Path(d) / f, os.X_OK)]
    assert len(found) == 1, f"expected one executable '{name}' under {base}, found {found}"
    return found[0]


def test_colcon_build_and_ros2_run_style_start(tmp_path, monkeypatch):
    colcon = VENV_BIN / "colcon"
    if not colcon.exists():
        skip_outside_ci("colcon is not installed in the venv (requirements.txt: make setup)")
    src = tmp_path / "src" / "bevo_ros"
    shutil.copytree(REPO, src, ignore=COPY_IGNORE)
    build = subprocess.run(
        [str(colcon), "--log-base", str(tmp_path / "log"), "build", "--base-paths", str(tmp_path / "src"),
         "--build-base", str(tmp_path / "build"), "--install-base", str(tmp_path / "install"),
         "--event-handlers", "console_direct-"],
        cwd=tmp_path, capture_output=True, text=True, timeout=180)
    assert build.returncode == 0, f"colcon build failed:\n{build.stdout[-3000:]}\n{build.stderr[-3000:]}"
    pkg_install = tmp_path / "install" / "bevo_ros"

    # What `source install/setup.bash` does for this package (its colcon hooks).
    site = pkg_install / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    assert (site / "bevo_ros" / "node.py").is_file()
    monkeypatch.setenv("AMENT_PREFIX_PATH", os.pathsep.join(
        [str(pkg_install)] + [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]))
    from ament_index_python.packages import get_package_prefix, get_package_share_directory

    prefix = Path(get_package_prefix("bevo_ros"))
    assert prefix == pkg_install
    exe = _find_executable(prefix, "bevo_ros", "bevo_node")
    share = Path(get_package_share_directory("bevo_ros"))
    params = share / "params" / "kitti.yaml"
    assert params.is_file() and (params.parent / "learned_default.yaml").is_file()
    # issue 11: launch, RViz and the license are installed; every command is a package module (issue 10: no
    # tools/ scripts in share), each executable is found
    from bevo_ros.cli import COMMANDS, EXECUTABLES

    for f in ("launch/bevo.launch.py", "rviz/bevo.rviz", "LICENSE", "package.xml"):
        assert (share / f).is_file(), f"{f} not installed in {share}"
    assert not (share / "tools").exists()
    for command in COMMANDS:
        assert (site / "bevo_ros" / "commands" / f"{command}.py").is_file(), command
    tool_exes = {t: _find_executable(prefix, "bevo_ros", t) for t in EXECUTABLES}
    bevo = _find_executable(prefix, "bevo_ros", "bevo")  # `ros2 run bevo_ros bevo run BAG --out OUT`

    env = dict(os.environ, ROS_DOMAIN_ID=DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=os.pathsep.join([str(site)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]),
               PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0")
    for name, tool_exe in tool_exes.items():  # the installed executables run the installed commands
        help_run = subprocess.run([str(tool_exe), "--help"], cwd=tmp_path, env=env, capture_output=True, text=True,
                                  timeout=120)
        assert help_run.returncode == 0 and "usage:" in help_run.stdout, f"{name}: {help_run.stderr[-2000:]}"
    for command in ("demo", "ablation", "run"):  # the installed `bevo` runs the installed commands
        help_run = subprocess.run([str(bevo), command, "--help"], cwd=tmp_path, env=env, capture_output=True,
                                  text=True, timeout=120)
        assert help_run.returncode == 0 and f"usage: bevo {command}" in help_run.stdout, help_run.stderr[-2000:]
    # past the parsing: an installed command's default params file is the installed one (share/), not
    # one beside the Python package (site-packages has no params/)
    calib = subprocess.run([str(bevo), "calibrate", str(tmp_path / "no_bag")], cwd=tmp_path, env=env,
                           capture_output=True, text=True, timeout=120)
    assert calib.returncode == 2 and "parameters file not found" not in calib.stderr, calib.stderr[-2000:]
    assert "no_bag" in calib.stderr, calib.stderr[-2000:]
    proc = subprocess.Popen([str(exe), "--ros-args", "--params-file", str(params)], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = []
    try:
        deadline = time.monotonic() + 90
        ready = False
        os.set_blocking(proc.stdout.fileno(), False)
        while time.monotonic() < deadline and proc.poll() is None:
            line = proc.stdout.readline()
            if not line:
                time.sleep(0.05)
                continue
            out.append(line)
            if "ready:" in line:
                ready = True
                break
        assert ready, f"bevo_node did not log 'ready' (exit {proc.poll()}):\n{''.join(out)}"
        assert str(params.parent / "learned_default.yaml") in "".join(out), "".join(out)
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    os.set_blocking(proc.stdout.fileno(), True)
    rest = proc.stdout.read()
    text = "".join(out) + rest
    assert rc == 0, f"bevo_node exited with {rc} on SIGINT:\n{text}"
    assert "Traceback" not in text, text
