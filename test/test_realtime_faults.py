"""
Faults while running (issue 14, items 8 and 9), over DDS.

- A NaN command after valid ones stops the arm at once (real time): the next frame is at
  rest, not ``cmd_timeout`` later.
- A features node killed and restarted keeps the taught desired (``desired_file``); one
  restarted without it leaves the servo saying ``teach again``, with zero twists.
- The detector killed mid-run in real time: the arm's joint velocity is zero within the
  documented stopping time (README, Safety), measured on ``joint_states`` stamps.
"""
from __future__ import annotations

import math
import time

from conftest import REPO
from malformed import alive, Group, in_log, stamp, twist_norm, values, WAIT
import numpy as np
import pytest

pytest.importorskip('rclpy')
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402, I100
from geometry_msgs.msg import TwistStamped  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from sphere_servo.bringup.processes import Launcher  # noqa: E402
from sphere_servo.bringup.supervisor import Supervisor  # noqa: E402
from sphere_servo.pipeline.config import load_scenario  # noqa: E402
from sphere_servo.pipeline.servo import ServoState, TEACH_AGAIN  # noqa: E402
from sphere_servo.ros.conversions import header, twist_from_array  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from test_hardening_cores import CMO, CMO_D, exact  # noqa: E402

PARAMS = REPO / 'config' / 'params'


@pytest.fixture
def group(install_space, tmp_path):
    g = Group(install_space, tmp_path)
    yield g
    g.close()


def test_a_nan_command_after_valid_ones_stops_the_arm_at_once(group):
    """Real time: the frame after the refusal is at rest (issue 14, item 8)."""
    g = group
    joints, status = [], []
    g.node.create_subscription(JointState, 'joint_states', joints.append, 500)
    g.node.create_subscription(DiagnosticArray, 'arm_sim/state',
                               lambda m: status.append(m), 500)
    pub = g.node.create_publisher(TwistStamped, 'camera/cmd_vel', 10)
    proc = g.start('arm_sim', '--ros-args', '--params-file', str(PARAMS / 'arm_sim.yaml'),
                   '-p', 'cmd_timeout:=2.0')  # long: only the refusal may stop the arm
    assert g.spin(60.0, until=lambda: joints and pub.get_subscription_count() > 0), proc.log()

    def send(v):
        pub.publish(TwistStamped(header=Header(frame_id='camera_optical_frame'),
                                 twist=twist_from_array(v)))
    v = [0.0, 0.0, 0.03, 0.0, 0.0, 0.1]
    end = time.monotonic() + WAIT
    while time.monotonic() < end and not any(np.any(j.velocity) for j in joints[-3:]):
        send(v)
        g.spin(0.05)
    assert any(np.any(j.velocity) for j in joints[-3:]), 'the arm never moved'
    send([math.nan] * 6)  # one NaN, then nothing: the arm must not keep the old twist

    def refused():
        return [s for s in status if 'is not finite' in values(s.status[0]).get(
            'command_error', '')]
    assert g.spin(WAIT, until=refused), proc.log()[-2000:]
    t_refused = stamp(refused()[0])  # the first frame after the refusal
    g.spin(0.5)
    by_stamp = sorted(joints, key=stamp)
    before = [j for j in by_stamp if stamp(j) < t_refused][-1]
    after = [j for j in by_stamp if stamp(j) >= t_refused]
    assert np.any(before.velocity)  # moving up to the refusal,
    assert after and all(not np.any(j.velocity) for j in after)  # at rest from the next frame
    print(f'moving at {stamp(before):.4f} s, at rest from {stamp(after[0]):.4f} s: '
          f'{(stamp(after[0]) - stamp(before)) * 1e3:.1f} ms later (one frame: 33.3 ms)')
    assert stamp(after[0]) - stamp(before) < 0.034
    assert in_log(proc, 'refusing', 'is not finite') and alive(proc)


def _measure(g, pub, cMo, state):
    """Publish the exact measurement of cMo, stamped now (wall clock)."""
    t = round(g.node.get_clock().now().nanoseconds * 1e-9, 4)
    state['t'] = max(t, state.get('t', 0.0) + 0.001)
    vals = exact(cMo)
    pub.publish(JointState(header=header(state['t'], 'camera_optical_frame'),
                           name=list(vals), position=[float(x) for x in vals.values()]))


def test_a_features_restart_keeps_the_desired_or_asks_to_teach_again(group, tmp_path):
    g = group
    desired_file = tmp_path / 'desired.json'
    twists, states = [], []
    g.node.create_subscription(TwistStamped, 'camera/cmd_vel', twists.append, 1000)
    g.node.create_subscription(DiagnosticArray, 'servo/state',
                               lambda m: states.append(m.status[0]), 1000)
    pub = g.node.create_publisher(JointState, 'detector/measurement', 10)
    features_args = ('--ros-args', '-p', f'desired_file:={desired_file}')
    features = g.start('features', *features_args)
    servo = g.start('servo', '--ros-args', '-p', 'max_image_age:=1.0', '-p', 'timeout:=0.5')
    feed = {}

    def spin(seconds, until=None, cMo=CMO):  # while a camera sends 20 measurements a second
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            _measure(g, pub, cMo, feed)
            if g.spin(0.05, until=until) and until is not None:
                return True
        return until() if until is not None else None

    def latest(state):
        return next((s for s in reversed(states) if s.message == state), None)
    assert g.spin(WAIT, until=lambda: pub.get_subscription_count() > 0 and states), \
        servo.log()
    cli = g.node.create_client(Trigger, '/features/teach')

    def teach() -> str:
        spin(0.3, cMo=CMO_D)
        fut = cli.call_async(Trigger.Request())
        assert g.spin(WAIT, until=fut.done) and fut.result().success, fut.result()
        return fut.result().message.split('stamped ')[1].split(',')[0]
    assert g.spin(WAIT, until=cli.service_is_ready)
    taught = teach()
    assert spin(WAIT, until=lambda: latest('servoing') is not None and values(
        latest('servoing'))['desired_stamp'] == taught), [s.message for s in states[-5:]]

    # 1. killed (SIGKILL) and restarted: it reloads the desired and publishes it again
    features.popen.kill()
    features.popen.wait(5)
    states.clear()
    n = len(twists)
    restarted = g.start('features', *features_args)
    assert spin(WAIT, until=lambda: in_log(restarted, 'desired features set')), restarted.log()
    assert spin(WAIT, until=lambda: latest('servoing') is not None), [
        s.message for s in states[-5:]]
    assert values(latest('servoing'))['desired_stamp'] == taught
    # it servos again (a twist of the stale time may still come after its state)
    assert spin(WAIT, until=lambda: any(twist_norm(t.twist) > 0 for t in twists[n:]))
    assert alive(servo)

    # 2. stopped and restarted without its file: the servo says teach again, zero twists
    assert restarted.stop() == 0
    states.clear()
    bare = g.start('features')
    assert spin(WAIT, until=lambda: any(s.message == ServoState.NO_DESIRED.value and values(
        s).get('reason') == TEACH_AGAIN for s in states)), servo.log()[-2000:]
    n = len(twists)
    spin(1.0)
    assert twists[n:] and all(twist_norm(t.twist) == 0 for t in twists[n:])
    assert in_log(servo, 'lost its publisher', 'teach again'), servo.log()[-2000:]
    assert in_log(servo, TEACH_AGAIN) and alive(servo) and alive(bare)
    again = teach()  # and a new teach makes it servo again
    assert spin(WAIT, until=lambda: latest('servoing') is not None and values(
        latest('servoing'))['desired_stamp'] == again)
    assert all(math.isfinite(v) for t in twists for v in (
        t.twist.linear.x, t.twist.linear.y, t.twist.linear.z, t.twist.angular.x,
        t.twist.angular.y, t.twist.angular.z))


def test_a_killed_detector_stops_the_arm_within_the_documented_time(ros_env, tmp_path):
    """
    Real time: kill the detector mid-run; the arm is at rest within the stopping time.

    README (Safety): no twist answers an image older than ``max_image_age``, and the arm's
    watchdog stops it ``⌊cmd_timeout/dt⌋ + 1`` steps after the last command, so the joint
    velocity is zero at most ``max_image_age + (⌊cmd_timeout/dt⌋ + 1)·dt`` after the stamp
    of the last image the detector measured. Measured on the stamps of ``joint_states``.
    """
    (tmp_path / 'rt.yaml').write_text(
        'arm_sim:\n  ros__parameters:\n    clock_mode: realtime\n'
        'servo:\n  ros__parameters:\n    max_image_age: 0.2\n')
    (tmp_path / 'rt_sc.yaml').write_text(
        f'nodes: [arm_sim, detector, features, servo]\nparams: [{PARAMS / "arm_sim.yaml"}, '
        f'{PARAMS / "special_sphere.yaml"}, rt.yaml]\nteach: true\n')
    sc = load_scenario(tmp_path / 'rt_sc.yaml')
    arm, srv = sc.node_params('arm_sim'), sc.node_params('servo')
    dt, cmd_timeout = 1.0 / arm.get('camera_rate', 30.0), arm['cmd_timeout']
    bound = srv['max_image_age'] + (math.floor(cmd_timeout / dt + 1e-9) + 1) * dt
    out = open(tmp_path / 'launch.log', 'w')
    run = Launcher(sc, out=out, env=ros_env)
    sup = None
    try:
        run.start()
        sup = Supervisor(sc, domain_id=int(ros_env['ROS_DOMAIN_ID']))
        joints, meas = [], []
        sup.node.create_subscription(JointState, 'joint_states', joints.append, 1000)
        sup.node.create_subscription(JointState, 'detector/measurement', meas.append, 1000)
        sup.teach(lambda msg: out.write(msg + '\n'), lambda: not run.dead())
        assert sup.wait(lambda: int(sup.state_values.get('iteration', 0)) > 20, 60.0)
        assert sup.state is ServoState.SERVOING, sup.state
        run.children['detector'].popen.kill()
        got = {'n': len(meas), 't': time.monotonic()}

        def settled():  # the dead detector's last words in, a second of rest after them
            if not meas:  # under load the observer may have matched after the kill
                return False
            if len(meas) != got['n']:
                got.update(n=len(meas), t=time.monotonic())
            if time.monotonic() - got['t'] < 2.0:
                return False
            t_last = max(stamp(m) for m in meas)
            return sum(1 for j in joints if stamp(j) > t_last + bound) > 30
        # under load Fast DDS delivers small topics up to seconds late: wait for them
        assert sup.wait(settled, 60.0), (len(meas), len(joints))
        t_last = max(stamp(m) for m in meas)  # the last image the detector measured
        by_stamp = sorted(joints, key=stamp)
        moving = [j for j in by_stamp if np.any(j.velocity)]
        assert moving and stamp(moving[-1]) > t_last - 0.5, 'the arm was not moving'
        t_rest = next(stamp(j) for j in by_stamp if stamp(j) > stamp(moving[-1]))
        rest = [j for j in by_stamp if stamp(j) >= t_rest]
        assert len(rest) > 30 and len({tuple(j.position) for j in rest}) == 1
        took = t_rest - t_last
        print(f'detector killed: last measured image {t_last:.4f} s, last motion '
              f'{stamp(moving[-1]):.4f} s, at rest from {t_rest:.4f} s: {took * 1e3:.0f} ms '
              f'(documented bound {bound * 1e3:.0f} ms)')
        assert took <= bound + 1e-6, (took, bound)
    finally:
        if sup is not None:
            sup.close()
        codes = run.stop()
        out.close()
    assert all(c == 0 for name, c in codes.items() if name != 'detector'), codes
