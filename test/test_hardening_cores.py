"""
The node cores refuse what no camera, arm or operator could mean (issue 14), without ROS.

Measurements are the exact projections of poses, then broken deliberately one quantity at a
time, a little past each bound; every refusal is checked for its safe output (empty
features, a zero twist, a command not executed) and for naming the quantity.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pinocchio as pin
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import FisheyeCamera
from sphere_servo.core.measurement import PINHOLE_FIELD
from sphere_servo.core.targets import special_sphere
from sphere_servo.core.validation import Bound
from sphere_servo.pipeline import detector as detector_module
from sphere_servo.pipeline.arm_sim import ArmSimCore, HELD, SERVO_ENABLED
from sphere_servo.pipeline.common import Level, Refusal
from sphere_servo.pipeline.detector import camera_from_info, DetectorCore, DetectStatus
from sphere_servo.pipeline.features import FeaturesCore, FeaturesState
from sphere_servo.pipeline.params import (ArmSimParams, DetectorParams, FeaturesParams,
                                          ParameterError, ServoParams)
from sphere_servo.pipeline.servo import ServoCommand, ServoCore, ServoState, TEACH_AGAIN
from sphere_servo.pipeline.vectors import Measurement
from sphere_servo.sim.arm import pose_from_xyz_rpy, Status
from sphere_servo.vision.renderer import Renderer

R = 0.05
CMO = pose_from_xyz_rpy([0.03, -0.02, 0.5], [0.1, -0.15, 0.2])
CMO_D = pose_from_xyz_rpy([0.0, 0.0, 0.45], [0.0, 0.0, 0.0])
MS = 1_000_000
S_STAR = np.array([0.0, 0.0, 9.0, 0.0, 0.0, 0.0])
CAM = CameraIntrinsics()


def exact(cMo: pin.SE3 = CMO, **over) -> dict:
    """Return the detector's named values of the exact image of the special sphere at cMo."""
    cO = cMo.translation
    vals = {'b_x': 0.0, 'b_y': 0.0, 'b_z': 0.0, 'r_delta': R / np.linalg.norm(cO),
            'quality': 0.0}
    vals['b_x'], vals['b_y'], vals['b_z'] = cO / np.linalg.norm(cO)
    for name, P in special_sphere(R).marks().items():
        q = cMo.act(P)
        q = q / np.linalg.norm(q)
        vals.update({f'{name}_u': 0.0, f'{name}_v': 0.0, f'{name}_qx': q[0],
                     f'{name}_qy': q[1], f'{name}_qz': q[2]})
    vals.update(over)
    return vals


def meas(vals: dict) -> Measurement:
    return Measurement.of(list(vals), [float(v) for v in vals.values()])


def features(**over) -> FeaturesCore:
    return FeaturesCore(FeaturesParams.from_mapping(
        {'desired_source': 'pose', 'sets': ['s_n', 's'], **over}))


# --- features: impossible measurements -----------------------------------------------------
def _off_sphere(angle: float) -> dict:
    """P1's ray turned ``angle`` rad away from b, about an axis normal to both."""
    v = exact()
    b = np.array([v['b_x'], v['b_y'], v['b_z']])
    q = pin.exp3(np.cross(b, [0.0, 1.0, 0.0]) / np.linalg.norm(np.cross(b, [0, 1, 0]))
                 * angle) @ b
    return exact(P1_qx=q[0], P1_qy=q[1], P1_qz=q[2])


BAD_MEASUREMENTS = {
    'r_delta zero': (exact(r_delta=0.0), 'r_delta'),
    'r_delta negative': (exact(r_delta=-0.1), 'r_delta'),
    'r_delta one': (exact(r_delta=1.0), 'r_delta'),
    'r_delta above one': (exact(r_delta=1.5), 'r_delta'),
    'r_delta NaN': (exact(r_delta=math.nan), 'r_delta'),
    'b twice a unit vector': (exact(b_x=0.12, b_y=-0.08, b_z=1.98), '‖b‖'),
    'b zero': (exact(b_x=0.0, b_y=0.0, b_z=0.0), '‖b‖'),
    'b infinite': (exact(b_z=math.inf), 'b'),
    'P1 ray not unit': (exact(P1_qz=1.5), '‖P1 ray‖'),
    'P1 ray NaN': (exact(P1_qx=math.nan), 'P1 ray'),
    'P1 off the sphere': (_off_sphere(0.3), 'P1 ray'),
    'silhouette beyond the pinhole field': (exact(b_x=math.sin(1.5), b_y=0.0,
                                                  b_z=math.cos(1.5), r_delta=0.2), 'silhouette'),
    'quality negative': (exact(quality=-1.0), 'quality'),
}


@pytest.mark.parametrize('kind', BAD_MEASUREMENTS)
def test_an_impossible_measurement_gives_empty_features_and_names_the_quantity(kind):
    vals, quantity = BAD_MEASUREMENTS[kind]
    c = features()
    assert c.on_measurement(1, meas(exact())).values  # the exact one is tracked
    out = c.on_measurement(2, meas(vals))
    assert out.values == {} and out.violation is not None, out.lost
    assert quantity in out.lost and quantity in out.violation.quantity
    st = c.status()
    assert (st.state, st.level) == (FeaturesState.REFUSED, Level.ERROR)
    assert st.values['reason'] == out.lost
    assert c.on_measurement(3, meas(exact())).values  # and the next good one is tracked


def test_a_lost_target_is_not_a_refusal():
    c = features()
    v = exact()
    del v['P2_qx']  # P2 not visible: lost, not impossible
    out = c.on_measurement(1, meas(v))
    assert out.values == {} and out.violation is None
    assert c.status().state is FeaturesState.TARGET_LOST


def test_an_impossible_measurement_is_not_taught():
    c = features(desired_source='teach')
    c.on_measurement(1, meas(exact(r_delta=0.0)))
    taught = c.teach()
    assert not taught.success and 'r_delta' in taught.message and not c.has_desired


def test_the_field_of_the_camera_info_bounds_the_silhouette():
    """Beyond 90°, a pinhole sees nothing, a fisheye does: its camera_info sets the field."""
    t = 0.25 * np.array([math.sin(1.55), 0.0, math.cos(1.55)])  # 89° off axis, r_δ = 0.2
    R_z_to_t = pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), t).matrix()
    wide = exact(pin.SE3(R_z_to_t, t))  # the marks (on the target's −z cap) face the camera
    c = features()
    assert c.field == PINHOLE_FIELD
    refused = c.on_measurement(1, meas(wide))
    assert refused.violation.bound is Bound.FIELD and 'silhouette' in refused.lost
    fish = FisheyeCamera().to_camera_info_fields()
    assert c.on_camera_info(fish['width'], fish['height'], fish['k'], fish['d'],
                            fish['distortion_model']) is None
    assert c.field > math.radians(170)
    out = c.on_measurement(2, meas(wide))
    assert out.violation is None and out.values, out.lost


# --- features: the desired kept in a file ----------------------------------------------------
def test_the_taught_desired_survives_a_restart_in_its_file(tmp_path):
    path = tmp_path / 'desired.json'
    c = features(desired_source='teach', desired_file=str(path))
    assert not c.has_desired  # no file yet: nothing to reload
    c.on_measurement(7 * 10**9 + 3, meas(exact(CMO_D)), 'cam')
    taught = c.teach()
    assert taught.success and str(path) in taught.message and path.is_file()
    again = features(desired_source='teach', desired_file=str(path))
    assert again.has_desired and again.desired_stamp_ns == 7 * 10**9 + 3
    assert again.desired_frame_id == 'cam'
    for name, s_star in c.desired_features().items():
        np.testing.assert_array_equal(again.desired_features()[name], s_star)
    out = again.on_measurement(8 * 10**9, meas(exact()))
    ref = c.on_measurement(8 * 10**9, meas(exact()))
    for name in ('s_n', 's'):
        np.testing.assert_array_equal(out.values[name].s, ref.values[name].s)


@pytest.mark.parametrize('content, needle', [
    ('{"format": "something else"}', 'format'),
    ('not json at all', 'JSONDecodeError'),
    ('{"format": "sphere_servo desired 1", "stamp_ns": 1, "frame_id": "c", '
     '"target_kind": "special", "names": ["b_x"], "values": ["x"]}', 'values numbers'),
])
def test_a_bad_desired_file_is_refused_at_start(tmp_path, content, needle):
    path = tmp_path / 'desired.json'
    path.write_text(content)
    with pytest.raises(ParameterError, match=needle):
        features(desired_source='teach', desired_file=str(path))


def test_a_desired_file_of_another_target_or_impossible_is_refused(tmp_path):
    path = tmp_path / 'desired.json'
    c = features(desired_source='teach', desired_file=str(path))
    c.on_measurement(1, meas(exact(CMO_D)))
    assert c.teach().success
    with pytest.raises(ParameterError, match="taught on a 'special' target"):
        features(desired_source='teach', desired_file=str(path), target_kind='cc')
    data = json.loads(path.read_text())
    data['values'][data['names'].index('r_delta')] = 0.0
    path.write_text(json.dumps(data))
    with pytest.raises(ParameterError, match='r_delta'):
        features(desired_source='teach', desired_file=str(path))


def test_a_desired_file_that_cannot_be_written_is_said(tmp_path):
    c = features(desired_source='teach', desired_file=str(tmp_path / 'no' / 'dir.json'))
    c.on_measurement(1, meas(exact(CMO_D)))
    taught = c.teach()
    assert taught.success and c.has_desired and 'NOT kept' in taught.message


# --- detector: cameras it cannot use ---------------------------------------------------------
def _image() -> dict:
    img = Renderer(CAM, special_sphere()).render(CMO)
    return {'height': 480, 'width': 640, 'step': 1920, 'encoding': 'rgb8',
            'data': img.tobytes()}


def _info(**over):
    i = {**CAM.to_camera_info_fields(), **over}
    return i['width'], i['height'], i['k'], i['d'], i['distortion_model']


@pytest.mark.parametrize('over, needles', [
    ({'width': 320, 'height': 240,
      'k': [300.0, 0, 160.0, 0, 300.0, 120.0, 0, 0, 1]}, ['320x240', '640x480']),
    (FisheyeCamera(px=300, py=300, u0=640.0, v0=360.0, width=1280, height=720)
     .to_camera_info_fields(), ['1280x720', '640x480']),  # every model: the size is checked
])
def test_a_camera_the_detector_cannot_use_rejects_the_image(over, needles):
    c = DetectorCore(DetectorParams.from_mapping({}))
    assert not isinstance(c.on_camera_info(*_info(**over)), Refusal)
    out = c.on_image(**_image())
    assert out.status is DetectStatus.REJECTED and out.measurement == Measurement()
    assert all(n in out.reason for n in needles), out.reason
    c.on_camera_info(*_info())  # the right one: found again
    assert c.on_image(**_image()).status is DetectStatus.FOUND


def test_the_distortion_refusal_is_lifted_in_one_place(monkeypatch):
    """DISTORTION_APPLIED is the one switch: a model not in it is refused, never ignored."""
    c = DetectorCore(DetectorParams.from_mapping({}))
    c.on_camera_info(*_info(d=[1e-4, 0.0, 0.0, 0.0, 0.0]))
    assert c.on_image(**_image()).status is DetectStatus.FOUND  # plumb_bob is applied
    monkeypatch.setattr(detector_module, 'DISTORTION_APPLIED', frozenset())
    out = c.on_image(**_image())
    assert out.status is DetectStatus.REJECTED and 'plumb_bob distortion d' in out.reason


@pytest.mark.parametrize('over, error, needle', [
    ({'k': [1e300, 0, 320.0, 0, 600.0, 240.0, 0, 0, 1]}, None, 'px'),
    ({'k': [600.0, 0, 320.0, 0, -600.0, 240.0, 0, 0, 1]}, None, 'py'),
    ({'k': [600.0, 0.5, 320.0, 0, 600.0, 240.0, 0, 0, 1]}, None, 'skew'),
    ({'k': [600.0, 0, 320.0, 0, 600.0, math.nan, 0, 0, 1]}, None, 'finite'),
    ({'distortion_model': 'rational_polynomial', 'd': [0.0] * 8}, None,
     'unsupported distortion_model'),
    ({'k': [600.0, 0, 600.0, 0, 600.0, 240.0, 0, 0, 1]}, (0.0, 0.0, 2.5, 0.0),
     'intrinsics error u0 = 2.5'),  # u0 = 600·3.5 = 2100 > 2·640: off the image
])
def test_an_impossible_camera_info_is_refused_naming_why(over, error, needle):
    c = DetectorCore(DetectorParams.from_mapping({'intrinsics_error': list(error or (0,) * 4)}))
    refused = c.on_camera_info(*_info(**over))
    assert isinstance(refused, Refusal) and needle in refused.reason, refused
    assert c.camera is None and c.status().values['camera_refused'] == refused.reason
    assert c.on_image(**_image()).status is DetectStatus.REJECTED


def test_camera_from_info_gives_the_model_of_the_camera_info():
    fish = FisheyeCamera(px=300, py=300).to_camera_info_fields()
    cam = camera_from_info(fish['width'], fish['height'], fish['k'], fish['d'],
                           distortion_model='equidistant')
    assert isinstance(cam, FisheyeCamera) and cam.px == 300


# --- servo: stamps and values ----------------------------------------------------------------
def servo(**over) -> ServoCore:
    c = ServoCore(ServoParams.from_mapping({'max_image_age': 0.5, 'timeout': 0.3,
                                            'future_tolerance': 0.1, **over}))
    assert c.set_desired(S_STAR, 0) is None
    return c


S = S_STAR + np.array([0.02, -0.01, 0.03, 0.0, 0.0, 0.0])


def _zero_unstamped(cmd) -> None:
    assert isinstance(cmd, ServoCommand) and cmd.state is ServoState.BAD_STAMP
    assert np.array_equal(cmd.twist, np.zeros(6)) and cmd.stamp_ns is None
    assert cmd.level is Level.WARN and cmd.fault == cmd.reason


def test_features_stamped_in_the_future_are_refused():
    c = servo()
    now = 10 * 10**9
    assert c.on_features(now + 100 * MS, S, now, 0.0).state is ServoState.SERVOING  # = tol
    ahead = c.on_features(now + 5 * 10**9, S, now, 0.0)
    _zero_unstamped(ahead)
    assert 'in the future' in ahead.reason, ahead.reason
    assert '+5.000000 s from the clock' in ahead.reason, ahead.reason
    assert c.iteration == 1 and c.last_stamp_ns == now + 100 * MS  # not answered, not news
    assert c.on_features(now + 200 * MS, S, now + 150 * MS, 0.0).state is ServoState.SERVOING


def test_features_whose_stamps_go_backwards_are_refused():
    c = servo()
    assert c.on_features(2 * 10**9, S, 2 * 10**9, 0.0).state is ServoState.SERVOING
    back = c.on_features(2 * 10**9 - 300 * MS, S, 2 * 10**9 + 10 * MS, 0.0)
    _zero_unstamped(back)
    assert 'older than the last stamp' in back.reason and '-0.300000 s' in back.reason
    # a simulator restarted: its clock jumped back, the rule starts again
    assert c.on_features(1 * 10**9, S, 1 * 10**9, 0.0).state is ServoState.SERVOING


@pytest.mark.parametrize('theta_u, needle', [
    ([math.inf, 0.0, 0.0], 'not finite'), ([-math.inf, 0.0, 0.0], 'not finite'),
    ([1e154, 1e154, 0.0], '‖θu of s‖'), ([0.0, 0.0, 1e300], '‖θu of s‖'),
    ([0.0, 0.0, 3.2], '‖θu of s‖'),
])
def test_absurd_theta_u_gives_a_zero_twist_naming_it(theta_u, needle):
    c = servo()
    out = c.on_features(1 * MS, np.r_[S[:3], theta_u], 1 * MS, 0.0)
    assert out.state is ServoState.TARGET_LOST and needle in out.fault, out.fault
    assert np.array_equal(out.twist, np.zeros(6))


@pytest.mark.parametrize('s_star, needle', [
    (np.r_[S_STAR[:3], 0.0, 0.0, 1e300], '‖θu of s*‖'),
    (np.r_[0.0, 0.0, 0.5, 0.0, 0.0, 0.0], '‖s_n,t‖ of s*'),  # inside the sphere
])
def test_an_impossible_desired_is_refused_and_the_one_held_stays(s_star, needle):
    c = servo()
    refused = c.set_desired(s_star, 9)
    assert isinstance(refused, Refusal) and needle in refused.reason, refused
    assert c.desired_stamp_ns == 0 and np.array_equal(c.s_star, S_STAR)


def test_a_desired_whose_publisher_is_gone_is_dropped_teach_again():
    c = ServoCore(ServoParams.from_mapping({'timeout': 0.3}))
    assert c.set_desired(S_STAR, 5, publishers=frozenset({b'a'})) is None
    assert not c.on_desired_publishers(frozenset({b'a', b'b'}))  # still there
    assert c.s_star is not None
    assert c.on_desired_publishers(frozenset({b'b'}))  # gone: dropped
    assert c.s_star is None and c.desired_stamp_ns is None
    out = c.on_features(1 * MS, S, 1 * MS, 10.0)
    assert out.state is ServoState.NO_DESIRED and out.reason == TEACH_AGAIN
    assert np.array_equal(out.twist, np.zeros(6)) and 'desired_stamp' not in out.values()
    stale = c.on_tick(11.0)  # nothing comes: the state still says what to do
    assert stale.state is ServoState.NO_DESIRED and stale.reason == TEACH_AGAIN
    assert c.set_desired(S_STAR, 6, publishers=frozenset({b'b'})) is None  # taught again
    assert c.on_features(2 * MS, S, 2 * MS, 11.1).state is ServoState.SERVOING


# --- arm_sim: hold, arming, drivers, error ---------------------------------------------------
@pytest.fixture(scope='module')
def arm_params():
    return ArmSimParams.from_mapping({'clock_mode': 'lockstep', 'velocity_scale': 0.5,
                                      'hand_eye': [0.0, -0.04, 0.02, 0.0, 0.0, 0.0],
                                      'camera': {'width': 160, 'height': 120, 'px': 150.0,
                                                 'py': 150.0, 'u0': 80.0, 'v0': 60.0}})


V = [0.0, 0.0, 0.03, 0.0, 0.0, 0.05]


def test_hold_latches_until_release_or_reset(arm_params):
    sim = ArmSimCore(arm_params)
    assert np.any(sim.on_command(V).frame.qdot)
    sim.hold()
    for _ in range(3):
        out = sim.on_command(V)
        assert not out.valid and out.reason == HELD and not np.any(out.frame.qdot)
    st = out.frame.status()
    assert st.level is Level.WARN and st.values['hold'] == HELD
    assert sim.release().success and np.any(sim.on_command(V).frame.qdot)
    assert 'hold' not in sim.frame().status_values()
    sim.hold()
    assert sim.reset().success and not sim.held and sim.on_command(V).valid


def test_jumps_are_refused_while_the_servo_is_enabled(arm_params):
    sim = ArmSimCore(arm_params)
    q = sim.frame().q
    sim.on_servo_enabled(True)
    for jump in (sim.reset, lambda: sim.go('start'), lambda: sim.go('desired')):
        out = jump()
        assert not out.success and out.message == SERVO_ENABLED and out.frame is None
    np.testing.assert_array_equal(sim.frame().q, q)
    sim.on_servo_enabled(False)
    assert sim.go('desired').success


def test_a_second_driver_is_refused_while_the_first_drives(arm_params):
    sim = ArmSimCore(arm_params)
    assert sim.on_command(V, seq=100).valid and sim.on_command(V, seq=101).valid
    sim.on_command_publishers(['/servo', '/rogue'])
    rogue = sim.on_command(V, seq=3)
    assert not rogue.valid and 'out of sequence' in rogue.reason and '/rogue' in rogue.reason
    assert not np.any(rogue.frame.qdot)  # refused: the arm stops at once
    st = rogue.frame.status()
    assert st.level is Level.WARN and st.values['command_publishers'] == '/servo,/rogue'
    assert sim.on_command(V, seq=102).valid  # the first driver goes on
    # its driver stopped (no command for longer than cmd_timeout): another may drive
    sim2 = ArmSimCore(arm_params)
    sim2.on_command(V, seq=50)
    sim2.arm.t += arm_params.cmd_timeout + 0.1
    assert sim2.on_command(V, seq=1).valid
    sim2.on_command_publishers(['/servo'])  # one publisher left: any number goes
    assert sim2.on_command(V, seq=0).valid


def test_an_invalid_state_is_reported_error_and_refuses_until_reset(arm_params):
    sim = ArmSimCore(arm_params)
    sim.arm.q = sim.arm.q.copy()
    sim.arm.q[2] = math.nan  # a state no step made: the arm must not integrate it
    out = sim.on_command(V)
    f = out.frame
    assert f.info.status is Status.ERROR and f.level is Level.ERROR
    assert f.status().message == 'error' and 'joint positions q' in f.info.message
    assert not np.any(f.qdot)
    refused = sim.on_command(V)
    assert not refused.valid and 'reset first' in refused.reason
    assert sim.reset().success
    good = sim.on_command(V)
    assert good.valid and good.frame.info.status is not Status.ERROR
    assert np.all(np.isfinite(good.frame.q))
