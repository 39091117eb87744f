"""
The installed ``arm_sim`` executable as a process, driven from a test rclpy node.

Kinematic checks run in lockstep (one period per command), so they do not depend on the
machine's speed; nothing here asserts on wall-clock time (timeouts only bound the waits).
"""
import hashlib
import time

from conftest import REPO, wait_for
import numpy as np
import pinocchio as pin
import pytest

pytest.importorskip('rclpy')
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402, I100
from geometry_msgs.msg import PoseStamped, TwistStamped  # noqa: E402
from sensor_msgs.msg import Image, JointState  # noqa: E402
from sphere_servo.ros.conversions import se3_from_pose, twist_from_array  # noqa: E402
from sphere_servo.sim.arm import ArmModel, CAMERA_FRAME, pose_from_xyz_rpy  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

CONFIG = str(REPO / 'config' / 'params' / 'arm_sim.yaml')
DT = 1.0 / 30.0
WAIT = 20.0  # generous bound on any single wait (a loaded CI machine); never asserted on


class Probe:
    """Subscribes to the simulator's outputs and sends twists, in lockstep if asked."""

    def __init__(self, node, spin):
        self.node, self.spin = node, spin
        self.images, self.poses, self.status, self.joints = [], [], [], []
        node.create_subscription(Image, 'camera/image_raw', self.images.append, 50)
        node.create_subscription(PoseStamped, 'ground_truth/camera_pose', self.poses.append, 50)
        # arm_sim's ~/state: one status a frame, with the image's header
        node.create_subscription(DiagnosticArray, 'arm_sim/state',
                                 lambda m: self.status.append(m.status[0]), 50)
        node.create_subscription(JointState, 'joint_states', self.joints.append, 50)
        self.pub = node.create_publisher(TwistStamped, 'camera/cmd_vel', 10)

    def twist(self, v, frame_id: str = CAMERA_FRAME) -> TwistStamped:
        return TwistStamped(header=Header(frame_id=frame_id), twist=twist_from_array(v))

    def wait_first_image(self):
        self.spin(WAIT, until=lambda: self.images and self.poses and self.status)
        assert self.images, 'no image from arm_sim'
        # wait for the subscription of the simulator to match ours
        wait_for(lambda: self.pub.get_subscription_count() > 0, WAIT, what='cmd_vel match')

    def step(self, v, frame_id: str = CAMERA_FRAME):
        """Send one twist and wait for the image (and pose, status) it produces."""
        n = len(self.images)
        stamp = self.images[-1].header.stamp
        self.pub.publish(self.twist(v, frame_id))

        def done():
            if not (len(self.images) > n and self.images[-1].header.stamp != stamp
                    and self.status and self.joints):
                return False
            s = self.images[-1].header.stamp
            t = f'{s.sec + s.nanosec * 1e-9:.6f}'
            return (self.poses[-1].header.stamp == s and self.joints[-1].header.stamp == s
                    and {kv.key: kv.value for kv in self.status[-1].values}['sim_time'] == t)
        assert self.spin(WAIT, until=done), 'no image after a command'

    def call(self, service: str):
        """Call the simulator's std_srvs/Trigger ``/arm_sim/<service>``."""
        cli = self.node.create_client(Trigger, f'/arm_sim/{service}')
        assert cli.wait_for_service(timeout_sec=WAIT)
        fut = cli.call_async(Trigger.Request())
        assert self.spin(WAIT, until=fut.done)
        return fut.result()

    def oMc(self) -> pin.SE3:
        return se3_from_pose(self.poses[-1].pose)


@pytest.fixture
def probe(test_node):
    return Probe(*test_node)


def lockstep(launch, *params):
    args = ['--ros-args', '--params-file', CONFIG, '-p', 'clock_mode:=lockstep']
    for p in params:
        args += ['-p', p]
    return launch('arm_sim', *args)


def test_translation_and_rotation_in_lockstep(launch, probe):
    proc = lockstep(launch)
    probe.wait_first_image()
    assert probe.poses[-1].header.frame_id == 'target'
    img = probe.images[-1]
    assert (img.encoding, img.header.frame_id, img.width, img.height) == (
        'rgb8', 'camera_optical_frame', 640, 480)
    # pure translation along the camera z axis: the camera moves by v·t along its own z
    M0, v, n = probe.oMc(), 0.06, 12
    for _ in range(n):
        probe.step([0, 0, v, 0, 0, 0])
    c0Mc1 = M0.inverse() * probe.oMc()
    expected = np.array([0, 0, v * n * DT])
    assert np.linalg.norm(c0Mc1.translation - expected) < 0.01 * expected[2], \
        c0Mc1.translation
    assert np.degrees(np.linalg.norm(pin.log3(c0Mc1.rotation))) < 0.05
    # pure rotation: the camera centre stays put (1 mm), the rotation is ω·t
    M0, w = probe.oMc(), np.array([0.15, -0.2, 0.3])
    for _ in range(n):
        probe.step([0, 0, 0, *w])
    c0Mc1 = M0.inverse() * probe.oMc()
    assert np.linalg.norm(c0Mc1.translation) < 1e-3
    assert np.allclose(pin.log3(c0Mc1.rotation), w * n * DT, atol=2e-3)
    assert probe.status[-1].message == 'ok'
    # the go_desired service jumps to the IK solution of desired_cMo and publishes its image
    n = len(probe.images)
    res = probe.call('go_desired')
    assert res.success
    assert probe.spin(WAIT, until=lambda: len(probe.images) > n and
                      probe.poses[-1].header.stamp == probe.images[-1].header.stamp)
    oMc_des = pose_from_xyz_rpy([0, 0, 0.45], [0, 0, 0]).inverse()  # config/params/arm_sim.yaml
    assert np.allclose(probe.oMc().homogeneous, oMc_des.homogeneous, atol=1e-5)
    # the reply names the stamp of the first image at the new pose
    assert float(res.message.rsplit(' ', 1)[-1]) == pytest.approx(
        _stamp(probe.images[n]), abs=1e-9), res.message
    assert proc.stop() == 0, proc.log()  # SIGINT, as Ctrl-C


def test_joint_stops_at_limit_and_status_says_so(launch, probe):
    q0 = [0.0, -1.57, 1.57, -1.57, -1.57, 2 * np.pi - 0.1]
    lockstep(launch, 'start_mode:=joints', f'start_joints:={q0}')
    # the camera twist that turns wrist_3 positively (same hand-eye as the config)
    arm = ArmModel(tool0Mc=pose_from_xyz_rpy([0.0, -0.04, 0.02], [0, 0, 0]), q0=q0)
    v = 0.8 * arm.camera_jacobian()[:, 5]
    probe.wait_first_image()
    for _ in range(8):  # 0.8 rad/s × 8/30 s > 0.1 rad
        probe.step(v)
        assert probe.joints[-1].position[5] <= 2 * np.pi + 1e-9
    assert probe.joints[-1].position[5] == pytest.approx(2 * np.pi, abs=1e-6)
    st = probe.status[-1]
    values = {kv.key: kv.value for kv in st.values}
    assert st.message == 'joint_limit' and st.level == DiagnosticStatus.WARN
    assert values['joints'] == 'wrist_3_joint'
    probe.step(-v)  # moving away is allowed
    assert probe.joints[-1].position[5] < 2 * np.pi - 1e-3
    assert probe.status[-1].message == 'ok'


def test_command_timeout_brings_the_arm_to_rest(launch, probe):
    proc = launch('arm_sim', '--ros-args', '--params-file', CONFIG,
                  '-p', 'clock_mode:=realtime', '-p', 'cmd_timeout:=0.2')
    probe.wait_first_image()

    def moving():
        return any(np.any(np.abs(j.velocity) > 1e-6) for j in probe.joints)
    # command until the arm moves (the first twists after a match can still be lost while
    # the reader side completes discovery), then stop commanding
    deadline = time.monotonic() + WAIT
    while not moving() and time.monotonic() < deadline:
        probe.pub.publish(probe.twist([0.0, 0.0, 0.05, 0.0, 0.0, 0.1]))
        probe.spin(0.03)
    assert moving(), 'the arm never moved'
    assert probe.spin(WAIT, until=lambda: probe.status[-1].message == 'timeout')
    n = len(probe.joints)
    probe.spin(WAIT, until=lambda: len(probe.joints) > n + 3 and len(probe.poses) > n + 3)
    assert all(np.all(np.array(j.velocity) == 0) for j in probe.joints[n:])
    assert len({tuple(j.position) for j in probe.joints[n:]}) == 1
    assert probe.status[-1].level == DiagnosticStatus.WARN
    assert proc.stop() == 0


def _stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def _lockstep_run(launch, probe):
    """Five commands (one NaN among them) → exactly five new images; their digests."""
    proc = lockstep(launch)
    probe.wait_first_image()
    t_first = _stamp(probe.images[0])  # re-published unchanged (same stamp) until a command
    twists = [[0.02, 0, 0.03, 0, 0, 0.1], [0, -0.02, 0, 0.1, 0, 0],
              [np.nan, 0, 0, 0, 0, 0], [0.01, 0.01, 0.01, 0, 0.05, 0], [0, 0, 0, 0, 0, 0.2]]
    for i, v in enumerate(twists):
        before = probe.oMc()
        probe.step(v)
        if i == 2:  # NaN: clock advances, the arm holds still
            assert np.allclose(probe.oMc().homogeneous, before.homogeneous, atol=1e-12)
    probe.spin(1.2)  # longer than idle_republish_period: nothing more may come (no servo)
    new = [im for im in probe.images if _stamp(im) > t_first]
    stamps = [_stamp(im) for im in new]
    assert len(new) == len(twists), stamps
    assert np.allclose(np.diff(stamps), DT, atol=1e-6)
    assert 'camera twist = [nan' in proc.log() and 'is not finite' in proc.log()
    assert proc.stop() == 0
    return [hashlib.sha256(bytes(im.data)).hexdigest() for im in new]


def test_lockstep_one_image_per_command_and_reproducible(launch, probe):
    first = _lockstep_run(launch, probe)
    probe.images.clear()
    probe.poses.clear()
    second = _lockstep_run(launch, probe)
    assert first == second
    assert len(set(first)) >= 4  # the arm moved between frames (not one image re-sent)


@pytest.mark.parametrize('param,needle', [
    ('camera_rate:=-1.0', 'camera_rate'),
    ('target.radius:=0.0', 'target.radius'),
    ('start_joints:=[0.0, 1.0]', 'start_joints needs 6'),
    ('damping:=.nan', 'damping'),
])
def test_invalid_parameter_is_refused(launch, param, needle):
    proc = launch('arm_sim', '--ros-args', '--params-file', CONFIG, '-p', param)
    rc = proc.popen.wait(WAIT)
    assert rc != 0
    assert 'refused to start' in proc.log() and needle in proc.log(), proc.log()


def test_a_twist_in_another_frame_is_refused_and_the_arm_holds_still(launch, probe):
    """
    Refuse a TwistStamped whose frame_id is not camera_optical_frame (lockstep).

    It is not executed: the joint velocities are zero and the pose does not change; the
    loop goes on (one new image for it), the state says why and the log says so.
    """
    proc = lockstep(launch)
    probe.wait_first_image()
    v = [0.02, -0.01, 0.03, 0.05, 0.0, 0.1]
    probe.step(v)
    assert np.any(np.abs(probe.joints[-1].velocity) > 1e-6)  # a valid one moves the arm
    M0, q0, t0 = probe.oMc(), list(probe.joints[-1].position), _stamp(probe.images[-1])
    for frame_id in ('tool0', ''):
        probe.step(v, frame_id)
        assert _stamp(probe.images[-1]) > t0  # the period passed: the loop goes on
        assert np.all(np.array(probe.joints[-1].velocity) == 0.0)
        assert list(probe.joints[-1].position) == q0
        np.testing.assert_array_equal(probe.oMc().homogeneous, M0.homogeneous)
        st = probe.status[-1]
        values = {kv.key: kv.value for kv in st.values}
        assert st.level == DiagnosticStatus.WARN and st.message == 'ok'
        assert f'a camera twist in frame {frame_id!r}' in values['command_error']
        t0 = _stamp(probe.images[-1])
    assert "refusing a camera twist in frame 'tool0'" in proc.log()
    probe.step(v)  # and a valid one is executed again
    assert np.any(np.abs(probe.joints[-1].velocity) > 1e-6)
    assert 'command_error' not in {kv.key for kv in probe.status[-1].values}
    assert proc.stop() == 0
