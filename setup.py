from glob import glob

from setuptools import find_packages, setup

package_name = "bevo_ros"
# per-command executables in lib/bevo_ros, each running its bevo_ros.commands module (the launch file runs
# play_bag); bevo_ros.cli.EXECUTABLES, kept literal: setup.py must not import the package
EXECUTABLES = ("play_bag", "kitti_to_bag", "run_bag", "evaluate", "train_from_bag", "calibrate_mounting", "map_from_bag")

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "tools"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/params", glob("params/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
        ("share/" + package_name + "/rviz", glob("rviz/*.rviz")),
        ("share/" + package_name, ["LICENSE"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="BEVO ROS maintainers",
    maintainer_email="bevo-maintainers@bevo-ros.org",
    description="BEVO: BEV-based visual-inertial odometry with a differentiable UKF and phase correlation.",
    license="BSD-3-Clause",
    extras_require={"test": ["pytest"]},  # tests_require is gone from setuptools >= 72
    entry_points={
        "console_scripts": [
            "bevo = bevo_ros.cli:main",  # the one command: bevo convert|play|run|train|evaluate|... (bevo_ros.cli)
            "bevo_node = bevo_ros.node:main",
            "bevo_localizer = bevo_ros.localizer_node:main",
            *(f"{name} = bevo_ros.cli:{name}" for name in EXECUTABLES),
        ],
    },
)
