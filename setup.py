"""ament_python / pip build of shape_detector (colcon on ROS 2 Jazzy, or pip into a venv)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "shape_detector"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["shape_detector", "shape_detector.*", "msg_conversion", "msg_conversion.*"]),
    package_data={PACKAGE: ["weights/*.pt", "weights/*.onnx", "weights/*.json", "config/*.xml", "training/recipes/*.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("shape_detector/config/*.xml")),
    ],
    python_requires=">=3.10",
    # ROS packages (rclpy, *_msgs) come from apt on a ROS install or from the
    # requirements-ros.txt wheels in a venv; torch must be pinned before this install.
    install_requires=["numpy>=1.24", "opencv-python-headless>=4.8", "rosbags>=0.10", "mcap>=1.1", "torch>=2.1",
                      "onnxruntime>=1.17", "scipy>=1.10", "trimesh>=4.0", "numba>=0.59"],
    zip_safe=True,
    maintainer="shape_detector maintainers",
    maintainer_email="maintainers@shape-detector.invalid",
    description="RGB-D furniture detection with cuboid shape primitives for ROS 2",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "detector_node = shape_detector.node:main",
            "shape-detector = shape_detector.cli:main",
        ],
    },
)
