"""
The ``arm_sim`` process with what only the node sees: header stamps and a publisher restart.

Lockstep, driven from a test rclpy node (the probe of ``test_arm_sim_node``). Nothing here
asserts on wall-clock time.
"""
import numpy as np
import pytest

pytest.importorskip('rclpy')
from builtin_interfaces.msg import Time  # noqa: E402, I100
from geometry_msgs.msg import TwistStamped  # noqa: E402
from test_arm_sim_node import DT, lockstep, Probe  # noqa: E402

V = [0.0, 0.0, 0.02, 0.0, 0.0, 0.05]


@pytest.fixture
def probe(test_node):
    return Probe(*test_node)


def _moved(probe) -> bool:
    return bool(np.any(np.abs(probe.joints[-1].velocity) > 1e-6))


def test_a_command_s_stamp_is_not_judged_a_limit(launch, probe):
    """
    Limit (pinned): arm_sim judges a command by its arrival, never by its header stamp.

    Zero (the servo's watchdog twists), negative, far past and far future stamps are all
    executed; the watchdog (``cmd_timeout`` after the arrival) is what bounds a stale one.
    """
    proc = lockstep(launch)
    probe.wait_first_image()
    for sec, nanosec in ((0, 0), (-5, 0), (-2**31, 0), (1, 999_999_999), (2**31 - 1, 0)):
        msg = probe.twist(V)
        msg.header.stamp = Time(sec=sec, nanosec=nanosec)
        n = len(probe.images)
        probe.pub.publish(msg)
        assert probe.spin(20.0, until=lambda: len(probe.images) > n and probe.joints)
        probe.spin(0.2)
        assert _moved(probe), (sec, nanosec)
    assert proc.stop() == 0


def test_a_restarted_publisher_drives_again_within_the_documented_periods(launch, probe):
    """
    A driver that restarts numbers its commands from 1 again.

    It is refused (a second publisher, as far as the numbers tell) for at most
    ⌊cmd_timeout/dt⌋ = 6 periods, or none once the node's graph shows one publisher; then
    it drives. Every refused period holds the arm still and says why.
    """
    proc = lockstep(launch)
    probe.wait_first_image()
    for _ in range(10):
        probe.step(V)
    assert _moved(probe)
    probe.node.destroy_publisher(probe.pub)
    probe.pub = probe.node.create_publisher(TwistStamped, 'camera/cmd_vel', 10)
    probe.wait_first_image()                   # the new publisher matched
    refused = 0
    for _ in range(int(0.2 / DT) + 2):
        probe.step(V)
        if _moved(probe):
            break
        values = {kv.key: kv.value for kv in probe.status[-1].values}
        assert 'out of sequence' in values['command_error'], values
        refused += 1
    assert _moved(probe) and refused <= 6, refused
    if refused:
        assert 'out of sequence' in proc.log()
    assert proc.stop() == 0
