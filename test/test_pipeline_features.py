"""
The features core without ROS: desired sources (teach, pose, image), teaching, features.

Measurements are written here from ground truth (the exact projection of a pose), in the
published layout, so the core reads data it did not make; features are checked against the
pose's own quantities (s_n,t = O/r, θu = log(ᶜ*R_c)).
"""
from __future__ import annotations

import cv2
import numpy as np
import pinocchio as pin
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.measurement import observe
from sphere_servo.core.targets import special_sphere
from sphere_servo.pipeline.common import Level, Refusal
from sphere_servo.pipeline.features import FeaturesCore, FeaturesOutput, FeaturesState
from sphere_servo.pipeline.params import FeaturesParams, ParameterError
from sphere_servo.pipeline.vectors import Measurement
from sphere_servo.sim.arm import pose_from_xyz_rpy
from sphere_servo.vision.renderer import Renderer

R = 0.05
CMO_D = pose_from_xyz_rpy([0.0, 0.0, 0.45], [0.0, 0.0, 0.0])
CMO_1 = pose_from_xyz_rpy([0.03, -0.02, 0.5], [0.1, -0.15, 0.2])


def measurement(cMo: pin.SE3, marks=('P1', 'P2')) -> Measurement:
    """Build the detector's measurement of the exact image of the special sphere at cMo."""
    cO = cMo.translation
    names = ['b_x', 'b_y', 'b_z', 'r_delta', 'quality']
    values = [*(cO / np.linalg.norm(cO)), R / np.linalg.norm(cO), 0.0]
    target = special_sphere(R)
    for name in marks:
        P = cMo.act(target.marks()[name])
        names += [f'{name}_u', f'{name}_v', f'{name}_qx', f'{name}_qy', f'{name}_qz']
        values += [0.0, 0.0, *(P / np.linalg.norm(P))]
    return Measurement.of(names, values)


def core(**over) -> FeaturesCore:
    return FeaturesCore(FeaturesParams.from_mapping({'sets': ['s_n'], **over}))


def check_s_n(out: FeaturesOutput, cMo: pin.SE3, cMo_d: pin.SE3):
    """s_n = (O/r, log(ᶜ*R_c)) of the poses, s* that of the desired pose."""
    f = out.values['s_n']
    np.testing.assert_allclose(f.s[:3], cMo.translation / R, atol=1e-9)
    np.testing.assert_allclose(f.s_star[:3], cMo_d.translation / R, atol=1e-9)
    cdRc = cMo_d.rotation @ cMo.rotation.T
    np.testing.assert_allclose(f.s[3:], pin.log3(cdRc), atol=1e-9)
    np.testing.assert_allclose(f.s_star[3:], 0.0, atol=1e-12)


def test_teach_by_showing_takes_the_latest_measurement():
    c = core()
    taught = c.teach()
    assert not taught.success and taught.message == 'no measurement received yet'
    assert c.on_measurement(1 * 10**9, measurement(CMO_1)) is None  # no desired yet
    assert c.on_measurement(2 * 10**9 + 5, measurement(CMO_D)) is None
    taught = c.teach()
    assert taught.success and taught.stamp_ns == 2 * 10**9 + 5
    assert taught.message == 'desired features taught from the image stamped 2.000000005'
    same = c.on_measurement(3 * 10**9, measurement(CMO_D))
    np.testing.assert_allclose(same.values['s_n'].error, 0.0, atol=1e-12)
    check_s_n(c.on_measurement(4 * 10**9, measurement(CMO_1)), CMO_1, CMO_D)
    assert 's*_n,t = [0.0, 0.0, 9.0]' in c.describe_desired()


def test_a_lost_measurement_neither_teaches_nor_gives_features():
    c = core(sets=['s_n', 's'])
    c.on_measurement(1, measurement(CMO_D))
    assert c.teach().success
    lost = c.on_measurement(2, measurement(CMO_1, marks=('P1',)))
    assert lost.values == {} and lost.lost == 'mark P2 is not visible'
    assert c.on_measurement(3, Measurement()).lost == 'sphere not detected'
    torn = c.on_measurement(4, Measurement(('b_x', 'b_y'), (1.0,)))
    assert 'names but' in torn.lost
    failed = c.teach()  # the latest is the torn one: the desired stays
    assert not failed.success and failed.message.startswith('cannot teach this image:')
    np.testing.assert_allclose(
        c.on_measurement(5, measurement(CMO_D)).values['s'].error, 0.0, atol=1e-12)


def test_every_set_is_anchored_on_the_desired():
    c = core(sets=['s_n', 's', 's_cc'])
    c.on_measurement(1, measurement(CMO_D))
    c.teach()
    out = c.on_measurement(2, measurement(CMO_1))
    assert list(out.values) == ['s_n', 's', 's_cc']
    # s = (s*_n,t − ᶜ*R_c s_n,t, θu): zero translation part iff the camera centre is at the
    # desired one; here it is not
    cdRc = CMO_D.rotation @ CMO_1.rotation.T
    s_t = CMO_D.translation / R - cdRc @ (CMO_1.translation / R)
    np.testing.assert_allclose(out.values['s'].s[:3], s_t, atol=1e-9)
    assert out.values['s_cc'].s.shape == (7,)


def test_desired_from_a_pose():
    c = core(desired_source='pose', desired_cMo=[0.0, 0.0, 0.45, 0.0, 0.0, 0.0])
    assert c.has_desired
    check_s_n(c.on_measurement(1, measurement(CMO_1)), CMO_1, CMO_D)
    with pytest.raises(ParameterError, match='needs a spherical target'):
        core(desired_source='pose', target_kind='balloon')
    with pytest.raises(ParameterError, match='does not show the target'):
        core(desired_source='pose', desired_cMo=[0.0, 0.0, -0.45, 0.0, 0.0, 0.0])


def test_desired_from_an_image_file(tmp_path):
    cam = CameraIntrinsics()
    png = tmp_path / 'desired.png'
    rgb = Renderer(cam, special_sphere(R)).render(CMO_D)
    assert cv2.imwrite(str(png), np.ascontiguousarray(rgb[..., ::-1]))
    c = core(desired_source='image', desired_image=str(png))
    assert not c.has_desired
    info = cam.to_camera_info_fields()
    bad = c.on_camera_info(info['width'], info['height'], info['k'][:8], info['d'])
    assert isinstance(bad, Refusal) and 'unusable' in bad.reason and not c.has_desired
    assert c.on_camera_info(info['width'], info['height'], info['k'], info['d']) is not None
    assert c.has_desired
    assert c.on_camera_info(info['width'], info['height'], info['k'], info['d']) is None
    # the detector's s*, from a rendered image, against the exact one of the pose
    f = c.on_measurement(1, measurement(CMO_D)).values['s_n']
    assert np.linalg.norm(f.error[:3]) < 0.02 * np.linalg.norm(f.s_star[:3])
    assert np.degrees(np.linalg.norm(f.error[3:])) < 0.5
    with pytest.raises(ParameterError, match='is not a file'):
        core(desired_source='image', desired_image=str(tmp_path / 'none.png'))
    (tmp_path / 'junk.png').write_bytes(b'not a png')
    with pytest.raises(ParameterError, match='not a readable image'):
        core(desired_source='image', desired_image=str(tmp_path / 'junk.png'))


def test_exact_observation_equals_the_measurement_layout():
    """The measurement written here from ground truth is read back as that pose's observation."""
    obs = measurement(CMO_1).observation('special')
    ref = observe(CMO_1, special_sphere(R))
    np.testing.assert_allclose(obs.sphere.b, ref.sphere.b, atol=1e-12)
    assert obs.sphere.r_delta == pytest.approx(ref.sphere.r_delta, abs=1e-12)
    for name in ('P1', 'P2'):
        np.testing.assert_allclose(obs.q[name], ref.q[name], atol=1e-12)


def test_desired_features_and_the_taught_stamp():
    """
    Each teach sets s* of every set, from the taught image's stamp; the status follows.

    States: waiting → no desired → tracking → target lost, with the stamps as values.
    """
    c = core(sets=['s_n', 's'])
    st = c.status()
    assert (st.state, st.level) == (FeaturesState.WAITING, Level.OK)
    assert st.values == {'sets': 's_n,s', 'desired_source': 'teach'}
    assert c.desired_features() == {} and c.desired_stamp_ns is None
    c.on_measurement(3 * 10**9 + 7, measurement(CMO_D))
    assert c.status().state is FeaturesState.NO_DESIRED
    assert c.teach().success and c.desired_stamp_ns == 3 * 10**9 + 7
    star = c.desired_features()
    assert list(star) == ['s_n', 's']
    np.testing.assert_allclose(star['s_n'][:3], CMO_D.translation / R, atol=1e-9)
    np.testing.assert_allclose(star['s_n'][3:], 0.0, atol=1e-12)
    np.testing.assert_allclose(star['s'], 0.0, atol=1e-9)  # s* = (0, 0) for the 3-D set
    out = c.on_measurement(4 * 10**9, measurement(CMO_1))
    np.testing.assert_array_equal(out.values['s_n'].s_star, star['s_n'])
    st = c.status()
    assert (st.state, st.message) == (FeaturesState.TRACKING, 'tracking')
    assert st.values['stamp'] == '4.000000000'
    assert st.values['desired_stamp'] == '3.000000007'
    c.on_measurement(5 * 10**9, Measurement())
    st = c.status()
    assert (st.state, st.level) == (FeaturesState.TARGET_LOST, Level.WARN)
    assert st.values['reason'] == 'sphere not detected'
    posed = core(desired_source='pose')
    assert posed.desired_stamp_ns == 0 and list(posed.desired_features()) == ['s_n']
