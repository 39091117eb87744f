"""
The executor the nodes spin on (``sphere_servo.ros.executors``, issue 17).

rclpy's EventsExecutor by default, the classic SingleThreadedExecutor on request
(``SPHERE_SERVO_EXECUTOR=single_threaded``), a refused value named; and over ROS, a node
started either way answers its inputs and exits 0 on Ctrl-C; in one process, arm_sim (its
callback reads its MessageInfo) spins on a classic executor on a thread of its own beside
the EventsExecutor of the others (messages both ways; a failure there raised in the main
thread).
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


def test_a_callback_that_reads_its_message_info_gets_it(monkeypatch, ros_env):
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
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
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


def test_in_one_process_arm_sim_spins_apart(monkeypatch, ros_env):
    """
    The four nodes of ``--single-process``: arm_sim on an executor of its own, the rest shared.

    With the EventsExecutor the three nodes of the image → twist path share it (in order)
    and arm_sim, whose command callback reads its MessageInfo, gets the classic one; with
    ``single_threaded`` all four share one.
    """
    from sphere_servo.bringup.single import NODE_CLASSES, node_classes
    from sphere_servo.ros.executors import executor_groups, NodeExecutors
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    nodes = []
    try:
        nodes = [cls(context=ctx) for cls in node_classes(NODE_CLASSES)]
        monkeypatch.delenv(VARIABLE, raising=False)
        names = [(info, [n.get_name() for n in group]) for info, group in executor_groups(nodes)]
        assert names == [(False, ['servo', 'features', 'detector']), (True, ['arm_sim'])]
        both = NodeExecutors(nodes, ctx)
        assert [type(e).__name__ for e, _ in both.executors] == ['EventsExecutor',
                                                                 'SingleThreadedExecutor']
        assert [both.threaded(n) for n in nodes] == [False, False, False, True]
        monkeypatch.setenv(VARIABLE, 'single_threaded')
        assert [(info, len(g)) for info, g in executor_groups(nodes)] == [(True, 4)]
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_node_executors_carry_messages_both_ways_and_raise_a_thread_failure(
        monkeypatch, ros_env):
    """
    A plain node on the caller's thread and a MessageInfo node on its own, talking.

    ``ping`` (the caller's thread, EventsExecutor) publishes; ``pong`` (its thread, classic
    executor) gets each message with its info and answers; ``ping`` gets the answers. A
    callback of ``pong`` that raises ends its thread, and the caller's next ``spin_once``
    raises that exception: the process does not go on without the node.
    """
    import threading
    from sphere_servo.ros.executors import NodeExecutors
    from std_msgs.msg import String
    monkeypatch.delenv(VARIABLE, raising=False)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    ping = rclpy.create_node('ping', context=ctx)
    pong = rclpy.create_node('pong', context=ctx)
    executors = None
    try:
        answers, infos, threads = [], [], {}
        to_pong = ping.create_publisher(String, 'to_pong', 10)
        to_ping = pong.create_publisher(String, 'to_ping', 10)

        def on_pong(msg, info):
            threads['pong'] = threading.current_thread()
            if msg.data == 'fail':
                raise RuntimeError('pong failed')
            infos.append(info['publication_sequence_number'])
            to_ping.publish(String(data=msg.data.upper()))

        def on_ping(msg):
            threads['ping'] = threading.current_thread()
            answers.append(msg.data)
        pong.create_subscription(String, 'to_pong', on_pong, 10)
        ping.create_subscription(String, 'to_ping', on_ping, 10)
        executors = NodeExecutors([ping, pong], ctx)
        assert [executors.threaded(n) for n in (ping, pong)] == [False, True]
        executors.start()
        wait_for(lambda: to_pong.get_subscription_count() and to_ping.get_subscription_count(),
                 20.0, what='ping and pong to match')
        for word in ('a', 'b', 'c'):
            to_pong.publish(String(data=word))
        wait_for(lambda: executors.spin_once(0.05) or len(answers) == 3, 20.0,
                 what='the three answers')
        assert answers == ['A', 'B', 'C'] and infos == sorted(infos) and infos[0] >= 1
        assert threads['ping'] is threading.main_thread()
        assert threads['pong'] is not threading.main_thread()
        to_pong.publish(String(data='fail'))
        with pytest.raises(RuntimeError, match='pong failed'):
            wait_for(lambda: executors.spin_once(0.05), 20.0, what='the failure to surface')
    finally:
        if executors is not None:
            executors.stop_threads()
        ping.destroy_node()
        pong.destroy_node()
        rclpy.try_shutdown(context=ctx)
