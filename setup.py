"""Python package of em_exploration_ros: the ROS-free core, the ROS 2 nodes and the tools."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE_NAME = "em_exploration_ros"

# Console scripts: one per node and per tool (name -> module:function).
CONSOLE_SCRIPTS = {
    "em-sim": "em_exploration_ros.tools.sim_cli:main",
    "em-bench": "em_exploration_ros.tools.bench:main",
    "em-world": "em_exploration_ros.nodes.world_node:main",
    "em-robot": "em_exploration_ros.nodes.robot_node:main",
    "em-evaluator": "em_exploration_ros.nodes.evaluator_node:main",
    "em-record": "em_exploration_ros.tools.record:main",
    "em-replay": "em_exploration_ros.tools.replay:main",
    "em-bag": "em_exploration_ros.tools.bag:main",
    "em-foxglove": "em_exploration_ros.tools.foxglove_bridge:main",
    "em-fuzz": "em_exploration_ros.tools.fuzz:main",
}

# Planners, found by name in this entry-point group (core/planner_registry.py): a plugin
# package registers its own the same way (docs/plugins.md).
PLANNERS = {
    "EM_2": "em_exploration_ros.core.planning.planners:em2_planner",
    "EM_3": "em_exploration_ros.core.planning.planners:em3_planner",
    "CE": "em_exploration_ros.core.planning.planners:ce_planner",
    "BSP": "em_exploration_ros.core.planning.planners:bsp_planner",
    "NEAREST": "em_exploration_ros.core.planning.planners:nearest_planner",
}

setup(
    name=PACKAGE_NAME,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE_NAME, f"{PACKAGE_NAME}.*"]),
    # The ament_python layout for colcon; in the venv, setup_env.sh lays it out with
    # em_exploration_ros/tools/ament_install.py (an editable pip install skips data_files).
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE_NAME}"]),
        (f"share/{PACKAGE_NAME}", ["package.xml"]),
        (f"share/{PACKAGE_NAME}/config", sorted(glob("config/*.*"))),
        (f"share/{PACKAGE_NAME}/config/worlds", sorted(glob("config/worlds/*.yaml"))),
    ],
    # foxglove-sdk: the WebSocket server of em-foxglove (tools/foxglove_bridge.py), the live view;
    # no node imports it. google-re2 (module re2): the topic expressions of em-record,
    # em-replay and em-foxglove, matched in time linear in the topic name
    # (bag_format/topic_selection.py).
    install_requires=["numpy", "gtsam", "mcap", "mcap-ros2-support", "PyYAML", "matplotlib",
                      "foxglove-sdk", "google-re2"],
    python_requires=">=3.11",
    zip_safe=False,
    maintainer="em_exploration_ros maintainers",
    maintainer_email="maintainers@em-exploration.example.org",
    description="Multi-robot exploration under localization uncertainty with EM, on ROS 2 Jazzy",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [f"{name} = {target}" for name, target in CONSOLE_SCRIPTS.items()],
        "em_exploration_ros.planners": [f"{name} = {target}" for name, target in
                                        PLANNERS.items()],
    },
)
