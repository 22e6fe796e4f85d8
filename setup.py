"""ament_python package set-up for memgs_ros.

The ROS 2 Python wheels are an optional extra (``[ros]``): on a Jetson rclpy
comes from apt, and everything that is not a node imports without it.
"""
import runpy
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "memgs_ros"

# The node list lives in memgs_ros/nodes/registry.py (literals: read without importing the package).
_REGISTRY = runpy.run_path(str(Path(__file__).resolve().parent / "memgs_ros/nodes/registry.py"))
NODES = {name: f"{module}:main" for name, (module, _) in _REGISTRY["NODES"].items()}
NODES.update({name: f"{module}:main" for name, module in _REGISTRY["COMPOSED"].items()})

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks"]),
    # The ORB vocabulary of loop closure and relocalisation (memgs_ros/core/tracking/features/vocabulary.py).
    package_data={"memgs_ros.data": ["*.npz"]},
    include_package_data=True,
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        # `ros2 launch memgs_ros memgs.launch.py` finds launch files in the package's share folder.
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/rviz", glob("rviz/*.rviz")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "opencv-python-headless>=4.8",
        # Pinned range that the CPU wheel on these machines satisfies; users with CUDA
        # install their own torch first and pip keeps it.
        "torch>=2.1",
        # The compiled CPU compositor and binning (rasterize's default on CPU); the package
        # still works without it (pure torch compositor).
        "numba>=0.60",
        "rosbags>=0.10",
        "mcap>=1.1",
        "tqdm>=4.60",
        "matplotlib>=3.6",
        "PyYAML>=5.4",
    ],
    extras_require={
        "ros": [
            "ros-jazzy-rclpy",
            "ros-jazzy-common-interfaces",
            "ros-jazzy-rmw-fastrtps-cpp",
        ],
        # CUDA users: the rasterizer's gsplat backend (same signature, used when importable on CUDA).
        "gsplat": ["gsplat>=1.0"],
        # The Rerun view (memgs run --rerun, memgs view, the rerun_bridge node): 0.36 is the first
        # rerun-sdk with the GaussianSplats3D archetype.
        "viz": ["rerun-sdk>=0.36"],
        # rerun-sdk >= 0.41: the tests read recordings back with rerun.chunk.RrdReader.
        # ruff and mypy pinned: test/unit/test_lint.py holds the code to exactly these versions' rules.
        "test": ["pytest>=7", "pytest-xdist>=3", "hypothesis>=6", "colcon-core", "colcon-ros", "colcon-python-setup-py",
                 "rerun-sdk>=0.41", "ruff==0.17.6", "mypy==2.4.1"],
    },
    zip_safe=True,
    maintainer="memgs_ros maintainers",
    description="MemGS Gaussian-splatting SLAM as ROS 2 nodes",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [f"{name}={target}" for name, target in NODES.items()]
        + ["memgs=memgs_ros.cli:main"],
    },
)
