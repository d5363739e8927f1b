from setuptools import find_packages, setup

package_name = "lq_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=["lq_ros", "lq_ros.*", "nodes"]),
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
            "sim_node = nodes.sim_node:main",
            "policy_node = nodes.policy_node:main",
            "executor_node = nodes.executor_node:main",
            "metrics_node = nodes.metrics_node:main",
        ],
    },
)
