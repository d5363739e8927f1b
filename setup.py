import runpy
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

package_name = "lq_ros"
HERE = Path(__file__).resolve().parent
# The shipped top-level folders (msg_schemas/, config/robots/, config/dds/): lq_ros.core.shipped names them.
_shipped = runpy.run_path(str(HERE / "lq_ros" / "core" / "shipped.py"))
SHIPPED, SHIPPED_DIR_NAME = _shipped["SHIPPED"], _shipped["SHIPPED_DIR"].name


class BuildPyWithShipped(build_py):
    """Also copy the shipped top-level folders into the built package (lq_ros/_shipped/<path>), where an installed
    lq_ros finds them (lq_ros.core.shipped.shipped_path). An editable install reads them in the source tree."""

    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):
            return
        for folder, pattern in SHIPPED.items():
            dest = Path(self.build_lib) / package_name / SHIPPED_DIR_NAME / folder
            self.mkpath(str(dest))
            for src in sorted((HERE / folder).glob(pattern)):
                self.copy_file(str(src), str(dest / src.name))


setup(
    name=package_name,
    version="0.1.0",
    # The node programs live in nodes/ (the design's layout) but install under a name that is ours:
    # a top-level package called "nodes" in site-packages would collide with anyone else's.
    packages=[*find_packages(include=["lq_ros", "lq_ros.*"]), "lq_ros_nodes"],
    package_dir={"lq_ros_nodes": "nodes"},
    # Shipped learned-policy weights (LIBERO-Spatial), loaded by default by `oft` and `flow`.
    package_data={"lq_ros.policies": ["weights/*.pt", "weights/*.json", "learned/motion_model.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", ["config/demo.yaml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="LIBERO-LQ developers",
    maintainer_email="lq-ros@example.com",
    description="LIBERO-LQ on ROS 2: latency-aware evaluation of VLA policies",
    license="Apache-2.0",
    cmdclass={"build_py": BuildPyWithShipped},
    # Every node program (nodes/*.py) under its module's name, as `ros2 run lq_ros <name>` would start it.
    entry_points={
        "console_scripts": [
            "lq = lq_ros.cli:entry",
            "sim_node = lq_ros_nodes.sim_node:main",
            "policy_node = lq_ros_nodes.policy_node:main",
            "executor_node = lq_ros_nodes.executor_node:main",
            "metrics_node = lq_ros_nodes.metrics_node:main",
            "manager_node = lq_ros_nodes.manager_node:main",
            "bridge_node = lq_ros_nodes.bridge_node:main",
            "robot_standin = lq_ros_nodes.robot_standin:main",
        ],
    },
)
