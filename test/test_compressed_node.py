"""
The installed detector with ``image_transport: compressed``, over DDS.

It reads ``camera/image_raw/compressed`` (sensor_msgs/CompressedImage) as image_transport's
compressed plugin publishes it: a PNG of the frame gives the measurement the raw rgb8 frame
gives; a JPEG a close one; corrupt bytes and a depth format are answered with an empty
measurement and the state ``rejected``, and the node runs on; a raw image on
``camera/image_raw`` is not read (the transport is the one the parameter names).
"""
from __future__ import annotations

import cv2
from malformed import alive, at, Group, stamp, values, WAIT
import numpy as np
import pytest

pytest.importorskip('rclpy')
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402, I100
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState  # noqa: E402
from sphere_servo.core.camera import CameraIntrinsics  # noqa: E402
from sphere_servo.core.targets import special_sphere  # noqa: E402
from sphere_servo.experiments.scenarios import CMO_DESIRED  # noqa: E402
from sphere_servo.pipeline.detector import DetectorCore  # noqa: E402
from sphere_servo.pipeline.params import DetectorParams  # noqa: E402
from sphere_servo.ros.conversions import header, image_from_array  # noqa: E402
from sphere_servo.vision.renderer import Renderer  # noqa: E402

CAM = CameraIntrinsics()
INFO = CAM.to_camera_info_fields()


@pytest.fixture(scope='module')
def compressed(install_space, tmp_path_factory):
    g = Group(install_space, tmp_path_factory.mktemp('compressed'))
    meas, states = [], []
    g.node.create_subscription(JointState, 'detector/measurement', meas.append, 500)
    g.node.create_subscription(DiagnosticArray, 'detector/state', states.append, 500)
    pubs = {'c': g.node.create_publisher(CompressedImage, 'camera/image_raw/compressed', 10),
            'raw': g.node.create_publisher(Image, 'camera/image_raw', 10),
            'info': g.node.create_publisher(CameraInfo, 'camera/camera_info', 10)}
    proc = g.start('detector', '--ros-args', '-p', 'image_transport:=compressed')
    assert g.spin(WAIT, until=lambda: pubs['c'].get_subscription_count() > 0
                  and pubs['info'].get_subscription_count() > 0), proc.log()
    assert pubs['raw'].get_subscription_count() == 0     # it reads one transport
    yield g, proc, pubs, meas, states
    codes = g.close()
    assert all(c == 0 for c in codes.values()), codes


def _answer(g, proc, pubs, meas, states, msg, t):
    """Publish camera_info and ``msg`` (stamped ``t``) until answered; (meas, status)."""
    for _ in range(10):
        pubs['info'].publish(CameraInfo(header=header(t, 'camera_optical_frame'), **INFO))
        pubs['c' if isinstance(msg, CompressedImage) else 'raw'].publish(msg)
        if g.spin(2.0, until=lambda: any(at(m, t) for m in meas)
                  and any(at(s, t) for s in states)):
            return ([m for m in meas if at(m, t)][0],
                    [s for s in states if at(s, t)][0].status[0])
    raise AssertionError(f'no answer to the image stamped {t}: {proc.log()[-2000:]}')


def _compressed(t: float, fmt: str, data: bytes) -> CompressedImage:
    return CompressedImage(header=header(t, 'camera_optical_frame'), format=fmt, data=data)


def test_compressed_images_are_measured_and_bad_ones_refused(compressed):
    g, proc, pubs, meas, states = compressed
    rgb = Renderer(CAM, special_sphere()).render(CMO_DESIRED)
    want = DetectorCore(DetectorParams.from_mapping({}))
    want.on_camera_info(INFO['width'], INFO['height'], INFO['k'], INFO['d'])
    want = want.on_image(480, 640, 1920, 'rgb8', rgb.tobytes()).measurement

    png = cv2.imencode('.png', rgb[..., ::-1])[1].tobytes()
    for k in range(20):     # until the camera_info has come (no camera: rejected)
        got, st = _answer(g, proc, pubs, meas, states,
                          _compressed(1.0 + k, 'rgb8; png compressed bgr8', png), 1.0 + k)
        if st.message != 'rejected':
            break
    got, st = _answer(g, proc, pubs, meas, states,
                      _compressed(10.0, 'rgb8; png compressed bgr8', png), 10.0)
    assert st.message == 'found', values(st)
    assert list(got.name) == list(want.names) and 'P2_qx' in got.name
    assert np.array_equal(got.position, want.values)

    jpg = cv2.imencode('.jpg', rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 80])[1].tobytes()
    got, st = _answer(g, proc, pubs, meas, states,
                      _compressed(10.1, 'rgb8; jpeg compressed bgr8', jpg), 10.1)
    assert st.message == 'found' and list(got.name) == list(want.names)
    i = list(got.name).index('r_delta')
    assert abs(got.position[i] - want.values[i]) < 1e-3 * want.values[i]

    for t, fmt, data in ((10.2, 'jpeg', bytes(range(256)) * 8),
                         (10.3, '16UC1; compressedDepth png', png)):
        got, st = _answer(g, proc, pubs, meas, states, _compressed(t, fmt, data), t)
        assert st.message == 'rejected' and len(got.name) == 0, values(st)
        assert st.level == b'\x02'
    assert alive(proc)

    # a raw image is on a topic this detector does not read: no answer, it keeps running
    pubs['raw'].publish(image_from_array(rgb, header(10.4, 'camera_optical_frame')))
    g.spin(1.0)
    assert not any(stamp(m) == 10.4 for m in meas) and alive(proc)
