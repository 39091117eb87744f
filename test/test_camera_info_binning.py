"""
CameraInfo ``binning_x``, ``binning_y`` and ``roi``, without ROS.

The camera of a published image that is a crop and/or a decimation of the calibrated one
(image_proc's crop_decimate, hardware binning) follows image_geometry's
``PinholeCameraModel``: size ``(roi.width // bx, roi.height // by)``, K ``fx/bx, fy/by,
(cx − x_offset)/bx, (cy − y_offset)/by``, the same distortion. Checked against values
computed by hand, and against an independent mapping: 3-D points projected by the
calibrated camera (and by the independent renderer's own wide models), their pixels mapped
by ``(u − x_offset)/bx``, against the reduced camera's projection of the same points. Every
refusal at and past its bound.
"""
from __future__ import annotations

import math
from pathlib import Path

from camera_cases import field_rays, MODELS
import cv2
from independent_render import Camera
import numpy as np
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import (calibrated_camera, camera_from_camera_info_fields,
                                             camera_info_reduction, FisheyeCamera,
                                             UnifiedCamera)
from sphere_servo.core.central import CameraError, FOCAL_RATIO_MAX, FOCAL_RATIO_MIN
from sphere_servo.core.measurement import PINHOLE_FIELD
from sphere_servo.core.targets import special_sphere
from sphere_servo.core.validation import Bound, Violation
from sphere_servo.pipeline.common import Refusal
from sphere_servo.pipeline.detector import camera_from_info, detector_camera, DetectorCore
from sphere_servo.pipeline.features import FeaturesCore
from sphere_servo.pipeline.params import DetectorParams, FeaturesParams
from sphere_servo.sim.arm import pose_from_xyz_rpy
from sphere_servo.vision.renderer import Renderer
from wide_cameras import twin, WIDE

CAM = CameraIntrinsics(px=600.0, py=610.0, u0=320.0, v0=240.0)
INFO = CAM.to_camera_info_fields()
ARGS = (INFO['width'], INFO['height'], INFO['k'], INFO['d'])
CMO_D = pose_from_xyz_rpy([0.02, -0.01, 0.45], [0.1, -0.2, 0.3])

#: (binning_x, binning_y, roi) → (width, height, fx, fy, cx, cy), by hand for CAM
HAND = [
    ((2, 2, None), (320, 240, 300.0, 305.0, 160.0, 120.0)),
    ((0, 2, (0, 0, 0, 0)), (640, 240, 600.0, 305.0, 320.0, 120.0)),
    ((4, 1, None), (160, 480, 150.0, 610.0, 80.0, 240.0)),
    ((1, 1, (100, 50, 400, 300)), (400, 300, 600.0, 610.0, 220.0, 190.0)),
    ((0, 0, (100, 50, 400, 300)), (400, 300, 600.0, 610.0, 220.0, 190.0)),
    ((2, 3, (101, 51, 401, 301)), (200, 100, 300.0, 610.0 / 3, 109.5, 63.0)),
    ((3, 3, (540, 380, 100, 100)), (33, 33, 200.0, 610.0 / 3, -220.0 / 3, -140.0 / 3)),
    ((640, 480, None), (1, 1, 600.0 / 640, 610.0 / 480, 0.5, 0.5)),
]


@pytest.mark.parametrize('reduce, want', HAND, ids=str)
def test_the_reduced_camera_by_hand(reduce, want):
    bx, by, roi = reduce
    cam = camera_from_info(*ARGS, binning_x=bx, binning_y=by, roi=roi)
    assert isinstance(cam, CameraIntrinsics), cam
    assert (cam.width, cam.height) == want[:2]
    assert (cam.px, cam.py, cam.u0, cam.v0) == pytest.approx(want[2:], rel=1e-12)
    assert cam.dist == CAM.dist and cam.reduction is not None
    full = calibrated_camera(cam)  # and back
    assert (full.width, full.height, full.reduction) == (640, 480, None)
    assert (full.px, full.py, full.u0, full.v0) == pytest.approx((600, 610, 320, 240), rel=1e-12)
    # the factory gives the same camera; its CameraInfo fields are those of a plain camera
    # (whose principal point must then be near its own image: the corner crop's is not)
    again = camera_from_camera_info_fields(**INFO, binning_x=bx, binning_y=by, roi=roi)
    assert again == cam
    if -cam.width <= cam.u0 <= 2 * cam.width and -cam.height <= cam.v0 <= 2 * cam.height:
        assert camera_from_camera_info_fields(**again.to_camera_info_fields()) == cam
    else:
        with pytest.raises(CameraError, match='outside its physical range'):
            camera_from_camera_info_fields(**again.to_camera_info_fields())


@pytest.mark.parametrize('bx, by, roi', [(0, 0, None), (1, 1, None), (0, 1, (0, 0, 0, 0)),
                                         (1, 0, (0, 0, 640, 480))])
def test_no_binning_and_the_full_roi_are_the_calibrated_camera(bx, by, roi):
    """Binning 0 is 1; an roi all zero (CameraInfo.msg) or the full one is none."""
    assert camera_info_reduction(640, 480, bx, by, roi) is None
    cam = camera_from_info(*ARGS, binning_x=bx, binning_y=by, roi=roi)
    assert cam == CAM and cam.reduction is None


# --- against an independent mapping of the calibrated camera's pixels -------------------------
REDUCTIONS = [(2, 2, (0, 0, 0, 0)), (1, 1, (37, 21, 300, 200)), (2, 3, (64, 30, 501, 397)),
              (4, 4, (300, 0, 340, 480))]
FULL = {'plumb_bob': MODELS['plumb_bob'], 'fisheye_kb': MODELS['fisheye_kb'],
        'unified_distorted': MODELS['unified_distorted'], **WIDE}


def _mapped(uv: np.ndarray, bx: int, by: int, roi) -> np.ndarray:
    """image_geometry's map of calibrated pixels to the reduced image's: (u − x_off)/bx."""
    x, y = roi[:2]
    return np.column_stack([(uv[:, 0] - x) / bx, (uv[:, 1] - y) / by])


@pytest.mark.parametrize('bx, by, roi', REDUCTIONS, ids=str)
@pytest.mark.parametrize('name', sorted(FULL))
def test_the_reduced_camera_projects_where_the_calibrated_pixels_map(name, bx, by, roi):
    full = FULL[name]
    info = full.to_camera_info_fields()
    red = camera_from_info(info['width'], info['height'], info['k'], info['d'],
                           distortion_model=info['distortion_model'], binning_x=bx,
                           binning_y=by, roi=roi)
    assert type(red) is type(full) and red.max_angle == full.max_angle
    q = field_rays(full, 400, 11)
    P = q * np.random.default_rng(5).uniform(0.1, 3.0, (len(q), 1))  # any depth
    want = _mapped(full.project(P), bx, by, roi)
    np.testing.assert_allclose(red.project(P), want, atol=1e-9)
    if name in WIDE:  # the independent renderer's own projection formulas
        np.testing.assert_allclose(_mapped(twin(full).project(P), bx, by, roi), want,
                                   atol=1e-6)
    # and back: the reduced pixels inside the reduced image lift to the points' rays
    inside = red.in_image(want)
    assert inside.sum() > 20
    np.testing.assert_allclose(red.lift(want[inside]), q[inside], atol=1e-9)


def test_a_pinhole_against_the_independent_camera():
    """The independent renderer's pinhole, with image_geometry's K, is the reduced camera."""
    bx, by, (x, y, w, h) = 2, 3, (64, 30, 501, 397)
    red = camera_from_info(*ARGS, binning_x=bx, binning_y=by, roi=(x, y, w, h))
    ind = Camera(CAM.px / bx, CAM.py / by, (CAM.u0 - x) / bx, (CAM.v0 - y) / by, w // bx,
                 h // by)
    P = np.random.default_rng(3).uniform([-0.3, -0.2, 0.5], [0.3, 0.2, 2.0], (200, 3))
    np.testing.assert_allclose(red.project(P), ind.project(P), atol=1e-9)
    assert (red.width, red.height) == (ind.width, ind.height) == (250, 132)


# --- refusals ---------------------------------------------------------------------------------
def refusal(**kw) -> str:
    out = camera_from_info(*ARGS, **kw)
    assert isinstance(out, Refusal), out
    return out.reason


@pytest.mark.parametrize('field, size', [('binning_x', 640), ('binning_y', 480)])
def test_binning_at_and_past_its_bounds(field, size):
    assert camera_from_info(*ARGS, binning_x=640, binning_y=480).reduction.size == (1, 1)
    assert camera_from_info(*ARGS, **{field: 2.0}).reduction.size != (640, 480)  # whole
    for value, bound in ((size + 1, Bound.RANGE), (-1, Bound.RANGE), (2.5, Bound.RANGE),
                         (1e12, Bound.RANGE), (math.nan, Bound.FINITE), ('2x', Bound.SHAPE),
                         ('2', Bound.SHAPE), (None, Bound.SHAPE), (True, Bound.SHAPE),
                         (np.True_, Bound.SHAPE)):
        with pytest.raises(CameraError) as err:
            camera_info_reduction(640, 480, **{field: value})
        v = err.value.violation
        assert (v.quantity, v.bound) == (f'CameraInfo.{field}', bound), v
        assert v.value is value or v.value == value, v
        assert refusal(**{field: value}) == str(v)  # the node's refusal names field and value


def test_an_roi_at_and_past_the_image():
    assert camera_from_info(*ARGS, roi=(40, 30, 600, 450)).reduction.size == (600, 450)
    assert camera_from_info(*ARGS, roi=(639, 479, 1, 1)).reduction.size == (1, 1)
    for roi, needles in (((41, 30, 600, 450), ['roi.x_offset + roi.width', '41 + 600 = 641',
                                               '≤ width = 640']),
                         ((40, 31, 600, 450), ['roi.y_offset + roi.height', '31 + 450 = 481',
                                               '≤ height = 480']),
                         ((640, 0, 1, 1), ['640 + 1 = 641']),
                         ((0, 0, 641, 480), ['0 + 641 = 641'])):
        reason = refusal(roi=roi)
        assert all(n in reason for n in needles), reason


@pytest.mark.parametrize('roi', [(0, 0, 0, 480), (0, 0, 640, 0), (10, 20, 0, 5)])
def test_an_roi_of_zero_width_or_height_only(roi):
    reason = refusal(roi=roi)
    assert f'CameraInfo.roi (x_offset, y_offset, width, height) = {roi}' in reason
    assert 'both 0 (the full image) or both > 0' in reason


@pytest.mark.parametrize('binning', [0, 2])
@pytest.mark.parametrize('roi', [(10, 0, 0, 0), (0, 20, 0, 0), (639, 479, 0, 0)])
def test_an_roi_of_no_size_at_an_offset_is_no_full_image(roi, binning):
    # image_geometry takes only (0, 0, 0, 0) as the full image; this one has no pixel
    with pytest.raises(CameraError) as err:
        camera_info_reduction(640, 480, binning, binning, roi)
    assert err.value.violation.bound is Bound.GEOMETRY
    assert err.value.violation.value == roi
    assert camera_info_reduction(640, 480, binning, binning, (0, 0, 0, 0)) == \
        camera_info_reduction(640, 480, binning, binning, None)


@pytest.mark.parametrize('roi, needle', [((1, 2, 3), 'CameraInfo.roi = (1, 2, 3)'),
                                         (5, 'CameraInfo.roi = 5'),
                                         ((0, -1, 10, 10), 'CameraInfo.roi.y_offset = -1'),
                                         ((0, 0, 10.5, 10), 'CameraInfo.roi.width = 10.5'),
                                         ((0, 0, 10, math.inf), 'CameraInfo.roi.height = inf')])
def test_an_roi_that_is_not_four_whole_numbers(roi, needle):
    assert needle in refusal(roi=roi)


def test_a_reduced_image_of_no_pixel():
    assert camera_from_info(*ARGS, binning_x=3, roi=(0, 0, 3, 3)).reduction.size == (1, 3)
    reason = refusal(binning_x=4, roi=(0, 0, 3, 3))
    assert 'reduced image size = 0x3' in reason and 'roi.width // binning_x = 3 // 4 = 0' in reason
    reason = refusal(binning_y=480, roi=(0, 10, 640, 470))
    assert 'reduced image size = 640x0' in reason and '470 // 480 = 0' in reason


def test_the_calibrated_size_must_be_whole_when_reduced():
    for width, needle in ((0, 'width = 0'), (640.5, 'width = 640.5'), (-3, 'width = -3')):
        out = camera_from_info(width, 480, INFO['k'], INFO['d'], binning_x=2)
        assert isinstance(out, Refusal) and needle in out.reason, out


def test_refusals_are_typed():
    with pytest.raises(CameraError) as err:
        camera_info_reduction(640, 480, roi=(0, 0, 641, 480))
    assert err.value.violation.bound is Bound.RANGE
    with pytest.raises(CameraError) as err:
        camera_info_reduction(640, 480, roi=(0, 0, 0, 1))
    assert err.value.violation.bound is Bound.GEOMETRY


# --- a reduced camera past a bound of every camera: named with its binning and roi -------------
def _reduced_refusal(info: dict, **kw) -> Violation:
    with pytest.raises(CameraError) as err:
        camera_from_camera_info_fields(**info, **kw)
    out = camera_from_info(info['width'], info['height'], info['k'], info['d'],
                           distortion_model=info['distortion_model'], **kw)
    assert isinstance(out, Refusal) and out.reason == str(err.value)  # the nodes say the same
    return err.value.violation


@pytest.mark.parametrize('f', [300.0, 610.0, 1200.0])
@pytest.mark.parametrize('axis', ['x', 'y'])
def test_a_binning_that_leaves_a_focal_length_no_camera_has_is_named(axis, f):
    """
    No limit of binning's own: the focal-length bound of every camera decides, and names it.

    Binning one axis divides its focal length and keeps the other side, so the bound
    (``FOCAL_RATIO_MIN`` × the reduced image's larger side) moves with ``f``: the last
    binning it allows is read, the next refused naming that binning, the calibrated focal
    length it divided and the image it leaves.
    """
    info = CameraIntrinsics(px=f, py=f).to_camera_info_fields()
    field, n = f'binning_{axis}', 640 if axis == 'x' else 480

    def size(b):
        return (640 // b, 480) if axis == 'x' else (640, 480 // b)
    last = max(b for b in range(1, n + 1) if f / b >= FOCAL_RATIO_MIN * max(size(b)))
    assert 1 < last < n
    cam = camera_from_info(*ARGS[:2], info['k'], info['d'], **{field: last})
    assert (cam.width, cam.height) == size(last)
    assert (cam.px if axis == 'x' else cam.py) == f / last
    v = _reduced_refusal(info, **{field: last + 1})
    assert v.bound is Bound.RANGE and v.value == f / (last + 1)
    assert v.quantity == f'p{axis} = f{axis} / {field} = {f!r} / {last + 1}', v
    w, h = size(last + 1)
    assert f'{field} = {last + 1}' in v.limit and f'leave a {w}x{h} image' in v.limit, v


def test_an_roi_that_leaves_a_focal_length_no_camera_has_is_named():
    """A crop keeps the focal length and shrinks the image: the upper bound, by the roi."""
    f = FOCAL_RATIO_MAX * 600  # a telescope: allowed for the 640 px image and a 600 px crop
    info = CameraIntrinsics(px=f, py=f).to_camera_info_fields()
    assert camera_from_info(*ARGS[:2], info['k'], info['d'], roi=(0, 0, 600, 1)).px == f
    v = _reduced_refusal(info, roi=(0, 0, 599, 1))
    assert (v.bound, v.value) == (Bound.RANGE, f) and v.quantity.startswith('px = fx'), v
    assert '(0, 0, 599, 1)' in v.limit and 'leave a 599x1 image' in v.limit, v


def test_a_crop_that_no_ray_reaches_is_named_with_its_roi():
    """A catadioptric image ends at its limit circle: a crop of the corner sees nothing."""
    info = UnifiedCamera(xi=2.0).to_camera_info_fields()
    centre = camera_from_info(*ARGS[:2], info['k'], info['d'], distortion_model='unified',
                              roi=(310, 230, 20, 20))
    assert isinstance(centre, UnifiedCamera) and centre.width == 20
    v = _reduced_refusal(info, roi=(0, 0, 20, 20))
    assert v.bound is Bound.FIELD and '(0, 0, 20, 20)' in v.limit, v


# --- the principal point, the intrinsics error, the cache, the size mismatch -------------------
def test_a_crop_far_from_the_principal_point_is_no_corrupt_k():
    """The principal point is bounded by the calibrated image, not by the crop."""
    corner = camera_from_info(*ARGS, roi=(560, 400, 80, 80))
    assert corner.u0 == pytest.approx(-240.0)  # 3 crop widths off: kept
    far = [1e4, 0.0, 320.0, 0.0, 1e4, 240.0, 0.0, 0.0, 1.0]
    far[2] = 2.0 * 640 + 1.0                    # past the calibrated image's bound
    for roi in (None, (600, 0, 40, 40)):
        reason = camera_from_info(640, 480, far, INFO['d'], roi=roi).reason
        assert 'u0' in reason and '1281.0' in reason, reason


def test_the_intrinsics_error_is_of_the_received_intrinsics():
    """Relative errors apply to the calibrated K, then the reduction: (1.1·cx − x_off)/bx."""
    cam = camera_from_info(*ARGS, intrinsics_error=(0.2, 0.0, 0.1, -0.1), binning_x=2,
                           binning_y=2, roi=(100, 40, 400, 400))
    assert (cam.px, cam.py, cam.u0, cam.v0) == pytest.approx(
        (720.0 / 2, 305.0, (352.0 - 100) / 2, (216.0 - 40) / 2))


def test_the_cache_is_keyed_on_binning_and_roi():
    a = camera_from_info(*ARGS, binning_x=2, binning_y=2, roi=[10, 10, 600, 400])
    assert camera_from_info(*ARGS, binning_x=2, binning_y=2, roi=(10, 10, 600, 400)) is a
    for other in ({'binning_x': 2, 'binning_y': 1, 'roi': (10, 10, 600, 400)},
                  {'binning_x': 2, 'binning_y': 2, 'roi': (12, 10, 600, 400)},
                  {'binning_x': 2, 'binning_y': 2}):
        b = camera_from_info(*ARGS, **other)
        assert b is not a and b != a
    assert isinstance(camera_from_info(*ARGS, roi=[[0, 0], [1, 1]]), Refusal)  # unhashable


def test_a_size_mismatch_names_the_binning_and_roi():
    half = camera_from_info(*ARGS, binning_x=2, binning_y=2, roi=(0, 0, 640, 480))
    with pytest.raises(CameraError) as err:
        detector_camera(half, 640, 480)  # the full image with a decimated image's info
    text = str(err.value)
    assert 'camera size = 320x240' in text and 'the size of the image, 640x480' in text
    assert 'binning_x = 2, binning_y = 2' in text and '(0, 0, 640, 480)' in text
    assert 'calibrated 640x480 image' in text
    with pytest.raises(CameraError) as err:  # no binning, no roi: nothing about them
        detector_camera(CAM, 320, 240)
    assert 'binning' not in str(err.value) and 'roi' not in str(err.value)


def test_replay3d_takes_a_reduced_stream_as_its_calibrated_camera():
    """The simulator's camera is the calibrated one: its crop_decimate stream is that run's."""
    from types import SimpleNamespace

    from sphere_servo.bag.bagio import BagError
    from sphere_servo.bag.run import Run
    from sphere_servo.experiments.replay3d import check_scenario

    def scene(cam):
        return SimpleNamespace(camera=cam, target=SimpleNamespace(marks=('P1', 'P2')))
    roi = (40, 20, 600, 400)
    half = camera_from_info(*ARGS, binning_x=2, binning_y=2, roi=roi)
    for rec in (CAM, half, camera_from_info(*ARGS, binning_x=3, binning_y=1)):
        check_scenario(Run(Path('bag'), [], camera=rec), scene(CAM))
    check_scenario(Run(Path('bag'), [], camera=half), scene(half))  # its images' camera
    other = [620.0, 0.0, 320.0, 0.0, 610.0, 240.0, 0.0, 0.0, 1.0]
    for rec, named in ((camera_from_info(640, 480, other, INFO['d'], binning_x=2, binning_y=2,
                                         roi=roi), True),
                       (camera_from_info(640, 480, other, INFO['d']), False)):
        with pytest.raises(BagError) as err:
            check_scenario(Run(Path('bag'), [], camera=rec), scene(CAM))
        text = str(err.value)
        assert f'({rec.width}x{rec.height}, px={rec.px:g}' in text and '640x480, px=600' in text
        if named:
            assert 'binning_x = 2, binning_y = 2' in text and str(roi) in text
            assert 'px=620 there' in text, text
        else:
            assert 'binning' not in text and 'roi' not in text, text


# --- the cores ----------------------------------------------------------------------------------
def test_the_detector_core_takes_and_refuses_binning_and_roi():
    c = DetectorCore(DetectorParams.from_mapping({}))
    cam = c.on_camera_info(*ARGS, binning_x=2, binning_y=2)
    assert c.camera is cam and (cam.width, cam.height) == (320, 240)
    out = c.on_camera_info(*ARGS, roi=(0, 0, 700, 480))
    assert isinstance(out, Refusal) and c.camera is None
    assert 'roi.x_offset + roi.width' in c.status().values['camera_refused']


def test_the_features_field_is_that_of_the_reduced_camera():
    """A refused roi leaves the field as it was; a good one gives the camera's field."""
    c = FeaturesCore(FeaturesParams.from_mapping({'sets': ['s_n']}))
    fish = FisheyeCamera().to_camera_info_fields()
    args = (fish['width'], fish['height'], fish['k'], fish['d'], 'equidistant')
    c.on_camera_info(*args, roi=(0, 0, 0, 9))
    assert c.field == PINHOLE_FIELD
    c.on_camera_info(*args, binning_x=2, binning_y=2, roi=(100, 40, 440, 400))
    assert c.field == pytest.approx(math.pi) and c.field > PINHOLE_FIELD


def test_the_features_desired_image_is_read_with_the_reduced_camera(tmp_path):
    """``desired_source: image``: an image of the decimated stream, with the full camera_info."""
    half = CameraIntrinsics(px=300.0, py=305.0, u0=160.0, v0=120.0, width=320, height=240)
    png = tmp_path / 'desired.png'
    bgr = Renderer(half, special_sphere(0.05)).render(CMO_D)[..., ::-1]
    assert cv2.imwrite(str(png), np.ascontiguousarray(bgr))
    params = FeaturesParams.from_mapping({'sets': ['s_n'], 'desired_source': 'image',
                                          'desired_image': str(png)})
    full = FeaturesCore(params).on_camera_info(*ARGS)  # binning left unset: refused
    assert isinstance(full, Refusal) and 'camera size = 640x480' in full.reason
    c = FeaturesCore(params)
    obs = c.on_camera_info(*ARGS, binning_x=2, binning_y=2)
    assert c.has_desired and not isinstance(obs, Refusal)
    b = CMO_D.translation / np.linalg.norm(CMO_D.translation)
    assert math.degrees(math.acos(min(1.0, obs.sphere.b @ b))) < 0.1


# --- the bag tools: rosbags' CameraInfo has the same fields ------------------------------------
def _rosbags_info(ts, binning: int, roi: tuple):
    CameraInfo = ts.types['sensor_msgs/msg/CameraInfo']
    Roi = ts.types['sensor_msgs/msg/RegionOfInterest']
    Header, Time = ts.types['std_msgs/msg/Header'], ts.types['builtin_interfaces/msg/Time']
    return CameraInfo(header=Header(stamp=Time(sec=1, nanosec=0), frame_id='cam'),
                      height=480, width=640, distortion_model='plumb_bob',
                      d=np.asarray(INFO['d']), k=np.asarray(INFO['k']),
                      r=np.asarray(INFO['r']), p=np.asarray(INFO['p']), binning_x=binning,
                      binning_y=binning, roi=Roi(x_offset=roi[0], y_offset=roi[1],
                                                 width=roi[2], height=roi[3],
                                                 do_rectify=False))


def test_the_bag_tools_read_binning_and_roi(tmp_path):
    """Give refeatures and a recorded run the reduced camera, and refeatures its refusal."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from sphere_servo.bag.bagio import typestore
    from sphere_servo.bag.offline import Pipeline, Settings
    from sphere_servo.bag.run import read_run
    ts = typestore()
    info = _rosbags_info(ts, 2, (40, 20, 400, 300))
    cam = Pipeline(Settings.from_params()).camera_or_refusal(info)
    assert (cam.width, cam.height, cam.u0, cam.v0) == (200, 150, 140.0, 110.0)
    bad = Pipeline(Settings.from_params()).camera_or_refusal(
        _rosbags_info(ts, 2, (400, 20, 400, 300)))
    assert isinstance(bad, Refusal) and '400 + 400 = 800' in bad.reason
    Image = ts.types['sensor_msgs/msg/Image']
    img = Image(header=info.header, height=150, width=200, encoding='rgb8', is_bigendian=0,
                step=600, data=np.zeros(600 * 150, np.uint8))
    with Writer(tmp_path / 'bag', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        for topic, msg in (('/camera/camera_info', info), ('/camera/image_raw', img)):
            conn = w.add_connection(topic, msg.__msgtype__, typestore=ts)
            w.write(conn, 1_000_000_000, bytes(ts.serialize_cdr(msg, msg.__msgtype__)))
    run = read_run(tmp_path / 'bag')
    assert (run.camera.width, run.camera.height, run.camera.px) == (200, 150, 300.0)
