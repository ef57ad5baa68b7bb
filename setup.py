from glob import glob

from setuptools import find_packages, setup

package_name = "bevo_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "tools"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/params", glob("params/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="BEVO ROS maintainers",
    maintainer_email="bevo-maintainers@bevo-ros.org",
    description="BEVO: BEV-based visual-inertial odometry with a differentiable UKF and phase correlation.",
    license="BSD-3-Clause",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "bevo_node = bevo_ros.node:main",
            "bevo_localizer = bevo_ros.localizer_node:main",
        ],
    },
)
