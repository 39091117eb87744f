"""
The detector core without ROS: camera_info → camera or a refusal, image buffer → detection.

Images are rendered at known poses (the renderer's ground truth), and bad buffers are built
by hand: each gives a typed status, and a rejected or empty image an empty measurement.
"""
from __future__ import annotations

import numpy as np
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import special_sphere
from sphere_servo.pipeline.common import Level, Refusal
from sphere_servo.pipeline.detector import camera_from_info, DetectorCore, DetectStatus
from sphere_servo.pipeline.params import DetectorParams
from sphere_servo.pipeline.vectors import Measurement, SPHERE_NAMES
from sphere_servo.sim.arm import pose_from_xyz_rpy
from sphere_servo.vision.renderer import Renderer

CAM = CameraIntrinsics()
INFO = CAM.to_camera_info_fields()
CMO = pose_from_xyz_rpy([0.02, -0.01, 0.45], [0.05, -0.1, 0.3])


def buffer(img: np.ndarray) -> dict:
    h, w = img.shape[:2]
    return {'height': h, 'width': w, 'step': w * 3, 'encoding': 'rgb8',
            'data': img.tobytes()}


def info_args(**over):
    i = {**INFO, **over}
    return i['width'], i['height'], i['k'], i['d']


def test_camera_from_info_applies_the_relative_error_or_refuses():
    cam = camera_from_info(*info_args(), intrinsics_error=(0.35, 0.30, -0.25, 0.27))
    assert isinstance(cam, CameraIntrinsics)
    assert (cam.px, cam.py, cam.u0, cam.v0) == pytest.approx(
        (600 * 1.35, 600 * 1.30, 320 * 0.75, 240 * 1.27))
    assert (cam.width, cam.height) == (640, 480)
    short = camera_from_info(*info_args(k=INFO['k'][:8]))
    assert isinstance(short, Refusal) and 'must have 9 entries' in short.reason
    zero = camera_from_info(*info_args(k=[0.0] * 9))
    assert isinstance(zero, Refusal) and 'focal lengths must be > 0' in zero.reason
    nan = camera_from_info(*info_args(k=[float('nan')] + INFO['k'][1:]))
    assert isinstance(nan, Refusal) and 'finite' in nan.reason


def test_equal_camera_infos_give_one_camera_and_any_change_another():
    """The camera of each image's camera_info is built once, and never kept past a change."""
    k = np.asarray(INFO['k'], dtype=float)  # as rclpy gives it: an ndarray, new each message
    first = camera_from_info(INFO['width'], INFO['height'], k.copy(), list(INFO['d']))
    again = camera_from_info(INFO['width'], INFO['height'], k.copy(), np.asarray(INFO['d']))
    assert again is first
    moved = k.copy()
    moved[2] += 0.5
    other = camera_from_info(INFO['width'], INFO['height'], moved, INFO['d'])
    assert other is not first and other.u0 == pytest.approx(first.u0 + 0.5)
    assert camera_from_info(INFO['width'], INFO['height'], k, INFO['d'],
                            intrinsics_error=(0.1, 0, 0, 0)).px == pytest.approx(660.0)
    assert camera_from_info(INFO['width'], INFO['height'], k, INFO['d']) is first
    for _ in range(2):  # a refusal each time (NaN equals nothing, not even a cached NaN)
        nan = k.copy()
        nan[0] = np.nan
        assert isinstance(camera_from_info(INFO['width'], INFO['height'], nan, INFO['d']),
                          Refusal)
    assert isinstance(camera_from_info(INFO['width'], INFO['height'], [[1, 0], [0, 1]],
                                       INFO['d']), Refusal)  # not a sequence of numbers


def test_a_refused_camera_info_leaves_no_camera():
    c = DetectorCore(DetectorParams.from_mapping({'intrinsics_error': [0.1, 0, 0, 0]}))
    assert isinstance(c.on_camera_info(*info_args()), CameraIntrinsics)
    assert c.camera.px == pytest.approx(660.0)
    assert isinstance(c.on_camera_info(*info_args(width=0)), Refusal) and c.camera is None
    out = c.on_image(**buffer(np.zeros((480, 640, 3), np.uint8)))
    assert out.status is DetectStatus.REJECTED
    assert out.reason == 'no valid camera_info received yet'
    assert out.measurement == Measurement() and out.detection is None


@pytest.mark.parametrize('change, needle', [
    ({'encoding': 'yuv422'}, "unsupported image encoding 'yuv422'"),
    ({'data': bytes(1000)}, 'image data has 1000 bytes'),
    ({'height': 0}, 'zero size'),
    ({'step': 100}, 'step 100 is smaller than a row'),
])
def test_bad_buffers_are_rejected(change, needle):
    c = DetectorCore(DetectorParams.from_mapping({}))
    c.on_camera_info(*info_args())
    out = c.on_image(**{**buffer(np.zeros((480, 640, 3), np.uint8)), **change})
    assert out.status is DetectStatus.REJECTED and needle in out.reason
    assert out.measurement == Measurement() and out.image is None


def test_a_rendered_sphere_is_found_and_measured():
    c = DetectorCore(DetectorParams.from_mapping({}))
    c.on_camera_info(*info_args())
    img = Renderer(CAM, special_sphere()).render(CMO)
    out = c.on_image(**buffer(img))
    assert out.status is DetectStatus.FOUND and out.reason == ''
    assert out.image.shape == (480, 640, 3)
    m = out.measurement
    assert m.names[:len(SPHERE_NAMES)] == SPHERE_NAMES
    assert {'P1_qx', 'P2_qx'} <= set(m.names) and 'P3_qx' not in m.names
    vals = m.as_dict()
    cO = CMO.translation
    b = np.array([vals['b_x'], vals['b_y'], vals['b_z']])
    assert np.degrees(np.arccos(b @ cO / np.linalg.norm(cO))) < 0.1
    assert vals['r_delta'] == pytest.approx(0.05 / np.linalg.norm(cO), rel=5e-3)
    u, v = CAM.project(cO[None])[0]
    assert abs(vals['ellipse_u'] - u) < 3.0 and abs(vals['ellipse_v'] - v) < 3.0


def test_an_empty_image_is_not_found():
    c = DetectorCore(DetectorParams.from_mapping({}))
    c.on_camera_info(*info_args())
    out = c.on_image(**buffer(np.full((480, 640, 3), 30, np.uint8)))
    assert out.status is DetectStatus.NOT_FOUND and out.reason
    assert out.detection is not None and out.measurement == Measurement()


def test_status_is_the_latest_outcome_with_counts():
    """The node's status: waiting, then each image's outcome (levels OK, WARN, ERROR)."""
    c = DetectorCore(DetectorParams.from_mapping({}))
    st = c.status()
    assert (st.state, st.level, st.message) == (DetectStatus.WAITING, Level.OK, 'waiting')
    assert st.values == {'images': '0', 'found': '0', 'not_found': '0', 'rejected': '0',
                         'camera': 'no'}
    c.on_image(**buffer(np.zeros((480, 640, 3), np.uint8)))  # no camera yet
    st = c.status()
    assert (st.state, st.level) == (DetectStatus.REJECTED, Level.ERROR)
    assert st.values['reason'] == 'no valid camera_info received yet'
    c.on_camera_info(*info_args())
    c.on_image(**buffer(Renderer(CAM, special_sphere()).render(CMO)))
    st = c.status()
    assert (st.state, st.level) == (DetectStatus.FOUND, Level.OK) and 'reason' not in st.values
    c.on_image(**buffer(np.full((480, 640, 3), 30, np.uint8)))
    st = c.status()
    assert (st.state, st.level, st.message) == (DetectStatus.NOT_FOUND, Level.WARN,
                                                'not found')
    assert st.values == {'images': '3', 'found': '1', 'not_found': '1', 'rejected': '1',
                         'camera': 'yes', 'reason': c.last.reason}
