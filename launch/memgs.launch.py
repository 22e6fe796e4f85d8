"""The MemGS graph (tracker, keyframe_sampler, mapper, merger) on a live RGB-D camera.

    ros2 launch realsense2_camera rs_launch.py align_depth.enable:=true
    ros2 launch memgs_ros memgs.launch.py [namespace:=/uav1] [params_file:=my.yaml] [map:=~/.ros/memgs/.../maps]

Arguments (``ros2 launch memgs_ros memgs.launch.py --show-args``):

- ``namespace``: pushed onto all four nodes, so their ``memgs/*`` topics and services become
  ``<namespace>/memgs/*`` (default: none).
- ``params_file``: the nodes' parameters (default: the installed ``config/realsense_d435i.yaml``).
- ``color_topic``, ``depth_topic``, ``camera_info_topic``: the camera's topics, given to the
  tracker as its parameters of the same names when given (then they win over the params file).
  Not given: a ``params_file`` of yours keeps its topics; with the default params file, the
  absolute topics of realsense2_camera 4.x with ``align_depth.enable:=true`` and its default
  ``camera_namespace``/``camera_name`` (``camera``/``camera``), so they do not move with
  ``namespace``.
- ``run_dir``: this launch's folder, new for every launch and never reused (default
  ``$ROS_HOME/memgs/<date>-<time>``, ``~/.ros`` without ROS_HOME): the merger's ``map.ply`` and the
  mapper's checkpoint (``mapper_checkpoint.npz``, every ``checkpoint_period_s``: a node killed or
  restarted resumes from it) go there.
- ``map_path``: where the merger writes the map PLY instead (on ``memgs/save_map``, every
  ``save_period_s`` and at shutdown; wins over the params file).
- ``map``: a saved map bundle to start from (a bundle folder, or a folder holding ``latest``):
  the tracker gives no pose until a frame relocalises in it, then maps on in its world frame
  (default: none, a new map).
- ``map_mode``: with ``map``, ``mapping`` (continue it) or ``localize`` (track in it, render it,
  add nothing: repeat flights, a second robot).
- ``bundle_dir``: where ``memgs/save_map`` saves map bundles (default ``<run_dir>/maps``, with a
  ``latest`` link); each save is a new folder.
- ``use_sim_time``: true when a ``/clock`` publisher (a replayed bag) drives time.
- ``autostart``: false leaves the four (managed) nodes unconfigured until a lifecycle manager or
  ``ros2 lifecycle set <ns>/tracker configure`` ... ``activate`` drives them (warm up on the
  ground, map from take-off, ``deactivate`` to pause; ros/lifecycle.py).
- ``composed``: true runs the four nodes as components of one process (the ``composed``
  executable: one executor, the libraries loaded once; on a Jetson, whose CPU and GPU share one
  memory, 828 MB where four processes took 1290 MB on the fr1/rpy head). Each node keeps its name
  and reads its own section of the params file; the launch's own parameters reach the node they
  belong to (``--param tracker:color_topic:=...``).

First run after installing: the nodes compile their kernels before they take frames (a minute on
2 cores; a live camera's frames meanwhile are counted as ``skipped.warming``). ``memgs doctor
--warm`` compiles them ahead, once, into the per-user kernel cache.

Fast DDS: unless FASTRTPS_DEFAULT_PROFILES_FILE is already set, the nodes get the package's
``config/fastdds.xml`` (a 50 ms heartbeat that repairs large reliable messages quickly).
"""
import os
import time

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from launch import LaunchDescription
from memgs_ros.nodes.registry import COMPOSED, GRAPH

PACKAGE = "memgs_ros"
NODES = GRAPH  # memgs_ros/nodes/registry.py
(COMPOSED_EXECUTABLE,) = COMPOSED  # the graph's nodes in one process
# seconds from SIGTERM to SIGKILL: the mapper's shutdown budget (checkpoint 15 s, then its session's
# close 30 s: nodes/mapper/node.py) and a margin
SIGTERM_TIMEOUT_S = "50"

# Tracker parameter -> default topic: realsense2_camera with align_depth.enable:=true.
CAMERA_TOPICS = {
    "color_topic": "/camera/camera/color/image_raw",
    "depth_topic": "/camera/camera/aligned_depth_to_color/image_raw",
    "camera_info_topic": "/camera/camera/color/camera_info",
}


def new_run_dir() -> str:
    """A folder no earlier launch used: ``$ROS_HOME/memgs/<date>-<time>[-n]`` (made by the first save)."""
    root = os.path.join(os.environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros"), "memgs")
    base = os.path.join(root, time.strftime("%Y%m%d-%H%M%S"))
    path, n = base, 1
    while os.path.exists(path):
        path, n = f"{base}-{n}", n + 1
    return path


def generate_launch_description():
    share = get_package_share_directory(PACKAGE)
    run_dir = new_run_dir()
    default_params = os.path.join(share, "config", "realsense_d435i.yaml")
    arguments = [
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of the four nodes (e.g. /uav1)"),
        DeclareLaunchArgument("params_file",
                              default_value=default_params,
                              description="ROS parameter file of the nodes"),
        DeclareLaunchArgument("run_dir", default_value=run_dir,
                              description="this launch's folder: the map PLY and the mapper's checkpoint"),
        DeclareLaunchArgument("map_path", default_value=os.path.join(run_dir, "map.ply"),
                              description="map PLY written by the merger (default: in run_dir)"),
        DeclareLaunchArgument("map", default_value="",
                              description="a saved map bundle to start from (empty: a new map)"),
        DeclareLaunchArgument("map_mode", default_value="mapping", choices=["mapping", "localize"],
                              description="with map: mapping continues it, localize only tracks in it"),
        DeclareLaunchArgument("bundle_dir", default_value="",
                              description="where memgs/save_map saves map bundles (empty: run_dir/maps)"),
        DeclareLaunchArgument("use_sim_time", default_value="false", choices=["true", "false"],
                              description="take time from /clock"),
        DeclareLaunchArgument("autostart", default_value="true", choices=["true", "false"],
                              description="configure and activate the nodes at start; false: wait for "
                                          "lifecycle transitions (ros2 lifecycle set, a lifecycle manager)"),
        DeclareLaunchArgument("composed", default_value="false", choices=["true", "false"],
                              description="the four nodes as components of one process (libraries loaded once)"),
    ]
    arguments += [
        DeclareLaunchArgument(name, default_value="",
                              description=f"tracker input ({name}); empty: the params file's ({topic} "
                                          "with the default params file)")
        for name, topic in CAMERA_TOPICS.items()
    ]
    # The nodes are made once the arguments are known: a camera topic goes to the tracker only
    # when given (or with the default params file), so a params file's own topics are not overridden.
    return LaunchDescription(arguments + [OpaqueFunction(function=_nodes, args=[share, default_params])])


def _nodes(context, share: str, default_params: str) -> list:
    params_file = LaunchConfiguration("params_file")
    default_file = params_file.perform(context) == default_params
    topics = {name: LaunchConfiguration(name).perform(context) or (topic if default_file else "")
              for name, topic in CAMERA_TOPICS.items()}
    common = {"use_sim_time": ParameterValue(LaunchConfiguration("use_sim_time"), value_type=bool),
              "autostart": ParameterValue(LaunchConfiguration("autostart"), value_type=bool)}
    # node -> parameter -> its value (substitutions, joined): string parameters the launch sets
    given_dir = LaunchConfiguration("bundle_dir").perform(context)
    bundles = {"bundle_dir": ([LaunchConfiguration("bundle_dir")] if given_dir
                              else [LaunchConfiguration("run_dir"), "/maps"])}
    if LaunchConfiguration("map").perform(context):  # a map to start from: given to tracker and mapper
        bundles.update(map_bundle=[LaunchConfiguration("map")], map_mode=[LaunchConfiguration("map_mode")])
    own_text = {
        "tracker": {**{name: [topic] for name, topic in topics.items() if topic}, **bundles},
        "merger": {"map_path": [LaunchConfiguration("map_path")], "bundle_dir": bundles["bundle_dir"]},
        "mapper": {"checkpoint_path": [LaunchConfiguration("run_dir"), "/mapper_checkpoint.npz"], **bundles},
    }
    own = {node: {param: ParameterValue(value, value_type=str) for param, value in values.items()}
           for node, values in own_text.items()}
    env = {}
    if "FASTRTPS_DEFAULT_PROFILES_FILE" not in os.environ:
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = os.path.join(share, "config", "fastdds.xml")

    composed = LaunchConfiguration("composed")
    # Ctrl-C: launch sends SIGTERM, then SIGKILL after sigterm_timeout (5 s by default): the mapper
    # writes its checkpoint and the merger its PLY on the way out, so wait for them.
    shared = {"package": PACKAGE, "namespace": LaunchConfiguration("namespace"), "additional_env": env,
              "output": "screen", "emulate_tty": True, "sigterm_timeout": SIGTERM_TIMEOUT_S}
    nodes = [
        Node(executable=name, name=name, parameters=[params_file, {**common, **own.get(name, {})}],
             condition=UnlessCondition(composed), **shared)
        for name in NODES
    ]
    # One process: no node name (a __node remap would rename all four); a parameter of one node goes
    # to that node alone (--param, memgs_ros/nodes/composed.py), since every node refuses a
    # parameter it does not declare.
    nodes.append(Node(
        executable=COMPOSED_EXECUTABLE, parameters=[params_file, common],
        arguments=[arg for node, values in own_text.items() for param, value in values.items()
                   for arg in ("--param", [f"{node}:{param}:=", *value])],
        condition=IfCondition(composed), **shared))
    return nodes
