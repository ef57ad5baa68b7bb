"""launch/bevo.launch.py and rviz/bevo.rviz: the launch file compiles, and every executable,
parameter, argument and file it names exists.

There is no `launch` / `launch_ros` wheel here, so the launch API is replaced by recorders that
keep what the file builds (the actions and their arguments); the checks then run on that.
"""
from __future__ import annotations

import ast
import importlib.util
import py_compile
import sys
import types
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "bevo.launch.py"
RVIZ = REPO / "rviz" / "bevo.rviz"


class Recorded:
    """Stands for any launch class: keeps its arguments."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.args}, {self.kwargs})"


def _fake_launch_api(monkeypatch, share: Path) -> None:
    classes = {
        "launch": ["LaunchDescription"],
        "launch.actions": ["DeclareLaunchArgument", "ExecuteProcess", "IncludeLaunchDescription", "GroupAction"],
        "launch.conditions": ["IfCondition", "UnlessCondition"],
        "launch.substitutions": ["LaunchConfiguration", "PythonExpression", "PathJoinSubstitution", "TextSubstitution"],
        "launch_ros": [],
        "launch_ros.actions": ["Node", "PushRosNamespace"],
        "launch_ros.parameter_descriptions": ["ParameterValue"],
        "launch_ros.substitutions": ["ExecutableInPackage", "FindPackageShare"],
    }
    for mod, names in classes.items():
        m = types.ModuleType(mod)
        for n in names:
            setattr(m, n, type(n, (Recorded,), {}))
        monkeypatch.setitem(sys.modules, mod, m)
    import ament_index_python.packages as ament

    monkeypatch.setattr(ament, "get_package_share_directory",
                        lambda pkg: str(share) if pkg == "bevo_ros" else f"/opt/ros/jazzy/share/{pkg}")


def _walk(obj):
    """Every Recorded object reachable from ``obj`` (through args, kwargs, lists, dicts)."""
    if isinstance(obj, Recorded):
        yield obj
        for v in list(obj.args) + list(obj.kwargs.values()):
            yield from _walk(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            yield from _walk(v)
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from _walk(v)


def _setup_py_executables() -> set[str]:
    """console_scripts of setup.py: bevo_node plus the EXECUTABLES tuple (read from its AST, not run)."""
    tree = ast.parse((REPO / "setup.py").read_text())
    tools = next(ast.literal_eval(n.value) for n in ast.walk(tree) if isinstance(n, ast.Assign)
                 and any(isinstance(t, ast.Name) and t.id == "EXECUTABLES" for t in n.targets))
    text = (REPO / "setup.py").read_text()
    assert '"bevo_node = bevo_ros.node:main"' in text
    assert '"bevo_localizer = bevo_ros.localizer_node:main"' in text
    assert 'f"{name} = bevo_ros.cli:{name}" for name in EXECUTABLES' in text
    return {"bevo_node", "bevo_localizer", *tools}


@pytest.fixture
def description(monkeypatch):
    py_compile.compile(str(LAUNCH), doraise=True)
    _fake_launch_api(monkeypatch, REPO)  # the source tree has the share layout (params/, rviz/, launch/)
    spec = importlib.util.spec_from_file_location("bevo_launch_under_test", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def test_launch_file_names_only_what_exists(description):
    from bevo_ros import cli
    from bevo_ros.commands import play
    from bevo_ros.ros.settings import NodeSettings
    from bevo_ros.config import BevoConfig

    objs = list(_walk(description))
    kinds = lambda name: [o for o in objs if type(o).__name__ == name]  # noqa: E731
    declared = {d.args[0]: d.kwargs for d in kinds("DeclareLaunchArgument")}
    used = {c.args[0] for c in kinds("LaunchConfiguration")}
    assert used <= set(declared), f"undeclared launch arguments {used - set(declared)}"
    assert {"params_file", "use_sim_time", "namespace", "bag", "rate", "rviz"} <= set(declared)

    # the default params file is the installed kitti.yaml (here: the share layout of the checkout)
    assert Path(declared["params_file"]["default_value"]) == REPO / "params" / "kitti.yaml"

    executables = _setup_py_executables()
    assert set(cli.EXECUTABLES) <= executables
    nodes = kinds("Node")
    ours = [n for n in nodes if n.kwargs["package"] == "bevo_ros"]
    assert [n.kwargs["executable"] for n in ours] == ["bevo_node", "bevo_node", "bevo_localizer"]
    assert all(n.kwargs["executable"] in executables for n in ours)
    others = {(n.kwargs["package"], n.kwargs["executable"]) for n in nodes if n not in ours}
    assert others <= {("rviz2", "rviz2")}, others

    # bevo_node: live (the params file alone) unless a bag is given; with a bag, replay.yaml on top
    live, replay = ours[0], ours[1]
    assert [type(n.kwargs["condition"]).__name__ for n in (live, replay)] == ["UnlessCondition", "IfCondition"]
    assert live.kwargs["condition"].args == replay.kwargs["condition"].args  # the same has_bag expression
    assert Path(replay.kwargs["parameters"][1]) == REPO / "params" / "replay.yaml"
    overlay = yaml.safe_load((REPO / "params" / "replay.yaml").read_text())["/**"]["ros__parameters"]
    assert overlay["input_qos"] == "reliable" and overlay["image_qos_depth"] >= 10

    # every parameter given to bevo_node is one it declares (or rclpy's use_sim_time)
    known = {f.name for f in __import__("dataclasses").fields(NodeSettings)} | set(BevoConfig().to_flat()) | {
        "use_sim_time"}
    assert set(overlay) <= known, set(overlay) - known
    for node in (live, replay):
        for entry in node.kwargs["parameters"]:
            if isinstance(entry, dict):
                assert set(entry) <= known, set(entry) - known
            elif isinstance(entry, str):
                assert entry == str(REPO / "params" / "replay.yaml")
            else:
                assert isinstance(entry, Recorded) and entry.args == ("params_file",)

    # bevo_localizer (launch option localizer:=true): its parameters file and overrides are its own
    from bevo_ros.localizer_node import LocalizerSettings

    loc = ours[2]
    assert type(loc.kwargs["condition"]).__name__ == "IfCondition"
    assert Path(loc.kwargs["parameters"][0]) == REPO / "params" / "bevo_localizer.yaml"
    assert set(loc.kwargs["parameters"][1]) <= {f.name for f in __import__("dataclasses").fields(LocalizerSettings)} | {
        "use_sim_time"}

    # the bag replay runs the project's player with arguments its parser accepts
    exe = kinds("ExecutableInPackage")
    assert [(e.kwargs["package"], e.kwargs["executable"]) for e in exe] == [("bevo_ros", "play_bag")]
    cmd = kinds("ExecuteProcess")[0].kwargs["cmd"]
    flags = [c for c in cmd if isinstance(c, str)]
    parser = play.build_parser()
    args = []
    for c in cmd[1:]:
        args.append(c if isinstance(c, str) else {"bag": "some_bag", "rate": "1.0", "namespace": "car1",
                                                   "params_file": "car.yaml"}[c.args[0]])
    parsed = parser.parse_args(args)
    assert parsed.bag == "some_bag" and parsed.namespace == "car1" and "--wait-for-subscribers" in flags
    assert parsed.wait_params == "car.yaml" and parsed.wait_topics is None  # the node's inputs, from its file
    defaults = NodeSettings()  # the node's own inputs (root-namespace bag names)
    assert play.node_input_topics(str(REPO / "params" / "kitti.yaml")) == [
        defaults.imu_topic, defaults.image_topic, defaults.camera_info_topic]

    # RViz gets the installed config, in the namespace, each topic it shows remapped to the namespace's
    rviz = [n for n in nodes if n.kwargs["package"] == "rviz2"][0]
    assert Path(rviz.kwargs["arguments"][1]) == RVIZ
    assert rviz.kwargs["namespace"].args == ("namespace",)
    manager = yaml.safe_load(RVIZ.read_text())["Visualization Manager"]
    shown = {d["Topic"]["Value"] for d in manager["Displays"] + manager["Tools"] if "Topic" in d}
    assert "/initialpose" in shown  # "2D Pose Estimate", for bevo_localizer
    assert dict(rviz.kwargs["remappings"]) == {t: t.lstrip("/") for t in shown}


def test_launch_argument_defaults_read_only_arguments_declared_before_them(description):
    """launch evaluates a DeclareLaunchArgument's default where it is declared: a default that reads
    an argument declared later fails (SubstitutionFailure) whenever that argument is not given."""
    declared: set[str] = set()
    for action in description.args[0]:
        if type(action).__name__ != "DeclareLaunchArgument":
            continue
        reads = {c.args[0] for c in _walk(action.kwargs.get("default_value")) if type(c).__name__ == "LaunchConfiguration"}
        assert reads <= declared, f"{action.args[0]}'s default reads {reads - declared}, declared after it"
        declared.add(action.args[0])
    assert {"bag", "use_sim_time"} <= declared


def test_rviz_config_shows_the_node_outputs():
    doc = yaml.safe_load(RVIZ.read_text())
    manager = doc["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == "odom"
    displays = {d["Class"]: d for d in manager["Displays"]}
    topics = {d["Topic"]["Value"] for d in manager["Displays"] if "Topic" in d}
    assert {"/bevo/odometry", "/bevo/path", "/bevo/bev_image"} <= topics
    assert {"rviz_default_plugins/TF", "rviz_default_plugins/Odometry", "rviz_default_plugins/Path",
            "rviz_default_plugins/Image"} <= set(displays)


def test_setup_installs_launch_rviz_params_executables_and_license():
    from bevo_ros.cli import COMMANDS, EXECUTABLES

    text = (REPO / "setup.py").read_text()
    for pattern in ('glob("params/*.yaml")', 'glob("launch/*.launch.py")', 'glob("rviz/*.rviz")', '["LICENSE"]'):
        assert pattern in text, pattern
    assert "tools/" not in text  # tools/ holds benchmarks and build helpers, nothing installed
    assert _setup_py_executables() - {"bevo_node", "bevo_localizer"} == set(EXECUTABLES)
    for name, command in EXECUTABLES.items():  # each runs a bevo command's module
        assert command in COMMANDS and (REPO / "bevo_ros" / "commands" / f"{command}.py").is_file(), name


# import name -> rosdep key (ROS packages are their own key); pip-only ones have none
ROSDEP_KEYS = {"numpy": "python3-numpy", "yaml": "python3-yaml", "cv2": "python3-opencv",
               "torch": "python3-pytorch-pip", "tqdm": "python3-tqdm", "matplotlib": "python3-matplotlib",
               "tf2_ros": "tf2_ros_py", "scipy": "python3-scipy"}
PIP_ONLY = {"rosbags"}


def test_license_and_every_runtime_import_is_declared():
    import xml.etree.ElementTree as ET

    root = ET.parse(REPO / "package.xml").getroot()
    assert root.findtext("license") == "BSD-3-Clause"
    assert (REPO / "LICENSE").read_text().startswith("BSD 3-Clause License")
    deps = {e.text for e in root.findall("exec_depend")}
    files = [*(REPO / "bevo_ros").rglob("*.py"), LAUNCH]
    imported: set[str] = set()
    for f in files:
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                imported |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                imported.add(node.module.split(".")[0])
    third_party = {m for m in imported if m not in sys.stdlib_module_names and m not in ("bevo_ros", "__future__")}
    missing = {m for m in third_party - PIP_ONLY if ROSDEP_KEYS.get(m, m) not in deps}
    assert not missing, f"imported but not an exec_depend of package.xml: {sorted(missing)}"


def test_parameter_choices_match_the_engine():
    from bevo_ros.core.compiled import KERNEL_MODES
    from bevo_ros.core.odometry import MODES
    from bevo_ros.ros.camera import UNDISTORT_MODES
    from bevo_ros.ros.parameters import CHOICES

    assert CHOICES["odometry.mode"] == MODES and CHOICES["undistort"] == UNDISTORT_MODES
    assert CHOICES["kernels"] == KERNEL_MODES
