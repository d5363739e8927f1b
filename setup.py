from setuptools import find_packages, setup

package_name = "lq_ros"

setup(
    name=package_name,
    version="0.1.0",
    # The node programs live in nodes/ (the design's layout) but install under a name that is ours:
    # a top-level package called "nodes" in site-packages would collide with anyone else's.
    packages=[*find_packages(include=["lq_ros", "lq_ros.*"]), "lq_ros_nodes"],
    package_dir={"lq_ros_nodes": "nodes"},
    # Shipped learned-policy weights (LIBERO-Spatial), loaded by default by `oft` and `flow`.
    package_data={"lq_ros.policies": ["weights/*.pt", "weights/*.json"]},
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
    entry_points={
        "console_scripts": [
            "lq = lq_ros.cli:main",
            "sim_node = lq_ros_nodes.sim_node:main",
            "policy_node = lq_ros_nodes.policy_node:main",
            "executor_node = lq_ros_nodes.executor_node:main",
            "metrics_node = lq_ros_nodes.metrics_node:main",
        ],
    },
)
