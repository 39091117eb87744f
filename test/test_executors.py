"""
The executor the nodes spin on (``sphere_servo.ros.executors``, issue 17).

rclpy's EventsExecutor by default, the classic SingleThreadedExecutor on request
(``SPHERE_SERVO_EXECUTOR=single_threaded``), a refused value named; and over ROS, a node
started either way answers its inputs and exits 0 on Ctrl-C.
"""
from __future__ import annotations

from conftest import wait_for
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from sphere_servo.ros.executors import executor_choice, make_executor, VARIABLE


def test_the_choice_comes_from_the_environment():
    assert executor_choice({}) == 'events' == executor_choice({VARIABLE: ''})
    assert executor_choice({VARIABLE: 'single_threaded'}) == 'single_threaded'
    with pytest.raises(ValueError, match=f'{VARIABLE}=.multi.'):
        executor_choice({VARIABLE: 'multi'})


def test_make_executor_gives_the_chosen_kind(monkeypatch):
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        monkeypatch.delenv(VARIABLE, raising=False)
        events = make_executor(ctx)
        assert type(events).__name__ == 'EventsExecutor'
        monkeypatch.setenv(VARIABLE, 'single_threaded')
        classic = make_executor(ctx)
        assert isinstance(classic, SingleThreadedExecutor)
        classic.shutdown()
        events.shutdown()
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.mark.parametrize('choice', ['events', 'single_threaded'])
def test_a_node_on_either_executor_answers_and_stops(choice, launch, test_node):
    from sphere_servo.ros.qos import observer, PIPELINE
    from sensor_msgs.msg import JointState
    node, spin = test_node
    got = []
    node.create_subscription(JointState, 'features/s_n', got.append, observer(PIPELINE))
    proc = launch('features', '--ros-args', '-p', 'desired_source:=pose',
                  env_extra={VARIABLE: choice})
    pub = node.create_publisher(JointState, 'detector/measurement', PIPELINE)
    from test_loop import _exact_measurement
    from sphere_servo.experiments.scenarios import CMO_DESIRED
    from sphere_servo.core.targets import special_sphere

    def answered():
        pub.publish(_exact_measurement(CMO_DESIRED, special_sphere(), 2.0))
        spin(0.1)
        return bool(got)
    wait_for(answered, 30.0, what=f'features on the {choice} executor to answer')
    assert got[-1].header.stamp.sec == 2 and len(got[-1].position) == 6, proc.log()
    assert proc.stop() == 0, proc.log()
    assert 'EventsExecutor' not in proc.log()  # no fall-back warning: this rclpy has it


def test_a_callback_that_reads_its_message_info_gets_it(monkeypatch):
    """
    A node whose callback takes (msg, info) spins where info is passed, and gets it.

    rclpy's EventsExecutor calls callbacks with the message only: arm_sim's one-driver rule
    (the publication sequence number) failed on every command on it. A process whose nodes
    have such a callback (arm_sim's command, and only it) gets an executor that passes it.
    """
    from sphere_servo.bringup.single import NODE_CLASSES, node_classes
    from sphere_servo.ros.executors import wants_message_info
    from std_msgs.msg import String
    monkeypatch.delenv(VARIABLE, raising=False)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=0)
    nodes = []
    try:
        nodes = [cls(context=ctx) for cls in node_classes(NODE_CLASSES)]
        assert {n.get_name(): wants_message_info([n]) for n in nodes} == {
            'servo': False, 'features': False, 'detector': False, 'arm_sim': True}
        probe = rclpy.create_node('info_probe', context=ctx)
        nodes.append(probe)
        got = []
        probe.create_subscription(String, 'info_probe', lambda m: None, 10)
        assert not wants_message_info([probe])
        probe.create_subscription(String, 'info_probe', lambda m, i: got.append(i), 10)
        assert wants_message_info([probe])
        pub = probe.create_publisher(String, 'info_probe', 10)
        executor = make_executor(ctx, message_info=True)
        executor.add_node(probe)
        wait_for(lambda: pub.publish(String(data='x')) or executor.spin_once(0.05) or got,
                 10.0, what='the probe to receive with its info')
        assert got[0]['publication_sequence_number'] >= 1
        executor.shutdown()
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown(context=ctx)
