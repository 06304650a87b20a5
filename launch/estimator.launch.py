"""Launch the transplanter_ident estimator with its default parameters and an optional tuned file.

    ros2 launch transplanter_ident estimator.launch.py
    ros2 launch transplanter_ident estimator.launch.py tuned_params:=/path/to/tuned.yaml
    ros2 launch transplanter_ident estimator.launch.py use_sim_time:=true   # with `ros2 bag play --clock`
    ros2 launch transplanter_ident estimator.launch.py executor:=single     # rclpy's default executor

The defaults come from share/transplanter_ident/config/estimator.yaml; a tuned file written by
`tuner` is layered over them (later files override earlier ones key by key), as on the command
line: `estimator --ros-args --params-file config/estimator.yaml --params-file tuned.yaml`.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def _estimator(context, *args, **kwargs):
    """The estimator node, with the parameter files resolved at launch time."""
    share = get_package_share_directory("transplanter_ident")
    parameters = [os.path.join(share, "config", "estimator.yaml")]
    tuned = LaunchConfiguration("tuned_params").perform(context).strip()
    if tuned:
        tuned = os.path.abspath(os.path.expanduser(tuned))
        if not os.path.isfile(tuned):
            raise RuntimeError(f"tuned_params: no such file: {tuned}")
        parameters.append(tuned)
    use_sim_time = LaunchConfiguration("use_sim_time").perform(context).strip().lower() in ("true", "1", "yes")
    parameters.append({"use_sim_time": use_sim_time})
    executor = LaunchConfiguration("executor").perform(context).strip()
    if executor not in ("events", "single"):
        raise RuntimeError(f"executor: must be events or single, got {executor!r}")
    return [
        Node(
            package="transplanter_ident",
            executable="estimator",
            name="estimator",
            arguments=["--executor", executor],
            parameters=parameters,
            output="screen",
            emulate_tty=True,
        )
    ]


def generate_launch_description():
    """Arguments: tuned_params (a params YAML from `tuner`, optional), use_sim_time, executor."""
    return LaunchDescription([
        DeclareLaunchArgument(
            "tuned_params",
            default_value="",
            description="params YAML written by `tuner`, layered over config/estimator.yaml (empty: none)",
        ),
        DeclareLaunchArgument(
            "use_sim_time",
            default_value="false",
            description="use the /clock of a replayed bag (ros2 bag play --clock)",
        ),
        DeclareLaunchArgument(
            "executor",
            default_value="events",
            description="events (rclpy's EventsExecutor, the lighter one) or single (SingleThreadedExecutor)",
        ),
        OpaqueFunction(function=_estimator),
    ])
