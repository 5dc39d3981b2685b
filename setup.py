"""ament_python package orchard_mapping (also pip-installable for the offline CLI)."""

from glob import glob

from setuptools import find_packages, setup

package_name = "orchard_mapping"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=["orchard_mapping", "orchard_mapping.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.xml")),
        ("share/" + package_name + "/config/scenarios", glob("config/scenarios/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.py")),
        # the shipped trunk detector and its card: trunks.model resolves here in an installed package
        ("share/" + package_name + "/models", glob("models/*.onnx") + glob("models/*.json") + ["models/README.md"]),
    ],
    python_requires=">=3.10",
    install_requires=["numpy", "scipy", "pyyaml", "pydantic>=2", "typer", "rich", "rosbags", "opencv-python-headless"],
    zip_safe=False,
    maintainer="orchard_mapping developers",
    maintainer_email="orchard-mapping@example.org",
    description="Semantic mapping of orchard rows from two-side reconstructions",
    license="BSD-3-Clause",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "orchard-map = orchard_mapping.cli.main:app",
            # the nodes, for `ros2 run` / `ros2 launch` on a full ROS install (orchard-map launch runs them
            # with python -m)
            "rgbd_odometry = orchard_mapping.ros.rgbd_odometry:main",
            "trunk_detector = orchard_mapping.ros.trunk_detector:main",
            "local_ground_fitter = orchard_mapping.ros.local_ground_fitter:main",
            "bag_player = orchard_mapping.ros.player:main",
            "recorder = orchard_mapping.ros.recorder:main",
            "side_merger = orchard_mapping.ros.side_merger:main",
            "trait_reporter = orchard_mapping.ros.trait_reporter:main",
        ],
    },
)
