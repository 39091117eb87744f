"""
Start the sphere_servo nodes of a scenario with ``ros2 launch`` (full ROS 2 Jazzy install).

    ros2 launch sphere_servo sphere_servo.launch.py [scenario:=special_sphere]

Reads the scenario file ``share/sphere_servo/config/scenarios/<scenario>.yaml`` (or a path)
with the launcher's own reader and starts each of its nodes with each of its params files,
in order: the same nodes with the same parameter files as ``launcher --config <scenario>``,
and, as it does, the shipped Fast DDS profile (``config/fastdds.xml``: images through shared
memory) unless the environment names a profile or another rmw
(:func:`~sphere_servo.pipeline.middleware.middleware_additions`).
What the launcher refuses before it starts anything and a node would not refuse itself
(no node, a node named twice, a params section that names no node: ``check_scenario``) is
refused here too, with the launcher's line.

It does not run the teach sequence, wait for the recorder or watch for convergence: that
is the Python launcher's job. With a teach scenario (the servo starts disabled) do it by
hand::

    ros2 service call /arm_sim/go_desired std_srvs/srv/Trigger
    ros2 service call /features/teach std_srvs/srv/Trigger
    ros2 service call /arm_sim/go_start std_srvs/srv/Trigger
    ros2 service call /servo/enable std_srvs/srv/SetBool "{data: true}"
"""
import os

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from sphere_servo.bringup.launcher import check_scenario
from sphere_servo.pipeline.config import ConfigError, scenario
from sphere_servo.pipeline.middleware import middleware_additions

DEFAULT_SCENARIO = 'special_sphere'


def _nodes(context):
    sc = scenario(LaunchConfiguration('scenario').perform(context))
    refused = check_scenario(sc)
    if refused:
        raise ConfigError(f'scenario error ({sc.path}), nothing started: {refused}')
    env = middleware_additions(os.environ)
    return [Node(package='sphere_servo', executable=name, name=name, output='screen',
                 parameters=[str(path) for path in sc.params_files], additional_env=env)
            for name in sc.nodes]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('scenario', default_value=DEFAULT_SCENARIO,
                              description='scenario name (config/scenarios) or path'),
        OpaqueFunction(function=_nodes),
    ])
