"""
A camera that publishes best effort (``SensorDataQoS``), against the installed nodes.

By default the detector's and the features node's camera readers are reliable (lockstep
needs every image): a best-effort camera is never matched, so nothing of it is measured,
and the node says how to read it. With ``image_reliability: best_effort`` the detector
measures that camera, and a reliable one too, and the features node takes its camera_info
(its desired image is detected with it).
"""
from __future__ import annotations

from malformed import alive, at, Group, in_log, values, WAIT
import pytest

pytest.importorskip('rclpy')
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402, I100
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile  # noqa: E402
import cv2  # noqa: E402, I100
from sensor_msgs.msg import CameraInfo, Image, JointState  # noqa: E402
from sphere_servo.core.camera import CameraIntrinsics  # noqa: E402
from sphere_servo.core.targets import special_sphere  # noqa: E402
from sphere_servo.experiments.scenarios import CMO_DESIRED  # noqa: E402
from sphere_servo.ros.conversions import header, image_from_array  # noqa: E402
from sphere_servo.vision.renderer import Renderer  # noqa: E402

CAM = CameraIntrinsics()
INFO = CAM.to_camera_info_fields()
RELIABLE = QoSProfile(depth=10)


@pytest.fixture(scope='module')
def rgb():
    return Renderer(CAM, special_sphere()).render(CMO_DESIRED)


def _run(install_space, tmp_path, rgb, camera_qos, *args):
    """Start a detector (``args``), feed it a camera of ``camera_qos``: (answers, proc)."""
    g = Group(install_space, tmp_path)
    meas, states = [], []
    g.node.create_subscription(JointState, 'detector/measurement', meas.append, 500)
    sub = g.node.create_subscription(DiagnosticArray, 'detector/state', states.append, 500)
    pub_img = g.node.create_publisher(Image, 'camera/image_raw', camera_qos)
    pub_info = g.node.create_publisher(CameraInfo, 'camera/camera_info', camera_qos)
    proc = g.start('detector', *args)
    try:
        assert g.spin(WAIT, until=lambda: sub.get_publisher_count() > 0), proc.log()
        found = []
        for k in range(40):
            t = 20.0 + 0.1 * k
            pub_info.publish(CameraInfo(header=header(t, 'camera_optical_frame'), **INFO))
            pub_img.publish(image_from_array(rgb, header(t, 'camera_optical_frame')))
            g.spin(0.1)
            found = [s for s in states if s.status[0].message == 'found']
            if len(found) >= 3:
                break
        answered = [m for m in meas if any(at(m, 20.0 + 0.1 * k) for k in range(40))]
        return answered, found, proc, g
    finally:
        assert alive(proc), proc.log()
        codes = g.close()
        assert all(c == 0 for c in codes.values()), codes


def test_a_best_effort_camera_is_not_matched_by_default_and_the_log_says_why(
        install_space, tmp_path, rgb):
    answered, found, proc, _ = _run(install_space, tmp_path, rgb, qos_profile_sensor_data)
    assert not answered and not found
    assert in_log(proc, 'image_reliability: best_effort'), proc.log()[-2000:]


@pytest.mark.parametrize('camera', ['best effort', 'reliable'])
def test_image_reliability_best_effort_measures_either_camera(install_space, tmp_path, rgb,
                                                              camera):
    qos = qos_profile_sensor_data if camera == 'best effort' else RELIABLE
    answered, found, proc, _ = _run(install_space, tmp_path, rgb, qos, '--ros-args', '-p',
                                    'image_reliability:=best_effort')
    assert len(found) >= 3, [values(s.status[0]) for s in found]
    assert any('P2_qx' in m.name for m in answered)
    assert not in_log(proc, 'cannot match'), proc.log()[-2000:]


@pytest.mark.parametrize('reliability', ['reliable', 'best_effort'])
def test_the_features_node_takes_a_best_effort_camera_info_only_when_told(
        install_space, tmp_path, rgb, reliability):
    """With ``desired_source: image`` it publishes s* once a camera_info has come."""
    desired = tmp_path / 'desired.png'
    cv2.imwrite(str(desired), rgb[..., ::-1])
    g = Group(install_space, tmp_path)
    got = []
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    sub = g.node.create_subscription(JointState, 'features/s_n/desired', got.append, latched)
    pub_info = g.node.create_publisher(CameraInfo, 'camera/camera_info',
                                       qos_profile_sensor_data)
    proc = g.start('features', '--ros-args', '-p', 'desired_source:=image', '-p',
                   f'desired_image:={desired}', '-p', f'image_reliability:={reliability}')
    try:
        assert g.spin(WAIT, until=lambda: sub.get_publisher_count() > 0), proc.log()
        for k in range(30):
            pub_info.publish(CameraInfo(header=header(30.0 + k, 'camera_optical_frame'),
                                        **INFO))
            if g.spin(0.1, until=lambda: got):
                break
        if reliability == 'best_effort':
            assert got and len(got[0].position) == 6, proc.log()[-2000:]
        else:
            assert not got
            assert in_log(proc, 'image_reliability: best_effort'), proc.log()[-2000:]
        assert alive(proc)
    finally:
        codes = g.close()
        assert all(c == 0 for c in codes.values()), codes
