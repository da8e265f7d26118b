"""genreg: GenReg point cloud registration as a ROS 2 (ament_python) package plus a pure-Python core.

`pip install -e .` gives the core and the console scripts; `colcon build` installs the ROS 2 package
(executables under lib/genreg_ros, see setup.cfg).
"""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "genreg_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["genreg_core", "genreg_core.*", "genreg_bench", "genreg_bench.*", "genreg_ros", "genreg_ros.*"]),
    package_data={"genreg_core": ["weights/*.pt", "weights/*.confidence.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=[
        "setuptools", "numpy", "scipy", "numba", "torch", "open3d", "small_gicp", "rosbags", "pyyaml", "tqdm", "pillow",
        "matplotlib",
    ],
    zip_safe=False,
    maintainer="genreg developers",
    maintainer_email="genreg@example.com",
    description="GenReg (CVPR 2022) deep generative point cloud registration as a ROS 2 node",
    license="MIT",
    entry_points={
        "console_scripts": [
            "register_node = genreg_ros.node:main",
            "genreg-train = genreg_core.training.cli:main",
            "genreg-bench = genreg_bench.cli:main",
            "genreg-make-bag = genreg_ros.bag.make_bag:main",
            "genreg-replay = genreg_ros.replay:main",
        ],
    },
)
