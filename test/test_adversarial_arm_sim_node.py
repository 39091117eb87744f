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


def test_a_lockstep_command_is_judged_by_the_image_it_answers(launch, probe):
    """
    In lockstep a command steps only if it answers the image shown, or no image (stamp 0).

    Negative, far past, one period stale and far future stamps answer an image of another
    pose (e.g. one before a jump): each is refused and steps nothing, so the next command
    stamped with the image shown steps exactly one period, moving the arm once. Unstamped
    (the probe's, a teleoperator's) and current stamps move the arm and step.
    """
    proc = lockstep(launch)
    probe.wait_first_image()
    probe.step(V)
    for stamp in ((-5, 0), (-2**31, 0), (0, 1), (2**31 - 1, 0), 'stale'):
        shown = probe.images[-1].header.stamp
        q = np.array(probe.joints[-1].position)
        bad = probe.twist(V)
        if stamp == 'stale':  # the image before the one shown: one period stale
            t = shown.sec + shown.nanosec * 1e-9 - DT
            stamp = int(t), int(round((t - int(t)) * 1e9))
        sec, nanosec = stamp
        bad.header.stamp = Time(sec=sec, nanosec=nanosec)
        probe.pub.publish(bad)
        good = probe.twist(V)
        good.header.stamp = shown
        probe.pub.publish(good)
        assert probe.spin(20.0, until=lambda: probe.images[-1].header.stamp != shown
                          and probe.joints[-1].header.stamp != shown), (sec, nanosec)
        probe.spin(0.3)  # what the refused one would have stepped, had it stepped
        stamps = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in probe.images}
        after = [s for s in stamps if s > (shown.sec, shown.nanosec)]
        assert len(after) == 1, (sec, nanosec, after)  # one period, the good command's
        t_after = after[0][0] + after[0][1] * 1e-9
        assert t_after == pytest.approx(shown.sec + shown.nanosec * 1e-9 + DT, abs=1e-8)
        assert not np.array_equal(np.array(probe.joints[-1].position), q)
    shown = len(probe.images)
    probe.step(V)  # unstamped: steps
    assert len(probe.images) > shown and _moved(probe)
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
