"""
Adversarial tests of ``arm_sim``'s 3-D scene messages (``ros/markers.py`` on ``sim/scene.py``).

The ``visualization_msgs/MarkerArray`` built for joint states all over the UR5's range
(its joint limits, folded and stretched poses) is checked against computations of its
own: the link meshes at Pinocchio's placements of the URDF's visual geometry, the camera at
``tool0``'s frame times the params file's hand-eye transform, the frustum at the
back-projected image corners of the params' intrinsics; every number finite, every
quaternion of unit norm. A marker that is not finite never reaches the wire.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from sphere_servo.pipeline.arm_sim import sim_scene
from sphere_servo.pipeline.config import load_node_params, section
from sphere_servo.pipeline.params import ArmSimParams
from sphere_servo.ros.markers import marker_array
from sphere_servo.sim.arm import pose_from_xyz_rpy
from sphere_servo.sim.scene import MarkerKind, MarkerSpec, SceneError
from std_msgs.msg import Header
from test_markers import Geometry
from visualization_msgs.msg import Marker


@pytest.fixture(scope='module')
def params() -> ArmSimParams:
    return ArmSimParams.from_mapping(section(load_node_params('special_sphere'), 'arm_sim'))


@pytest.fixture(scope='module')
def scene(params):
    return sim_scene(params)


def _se3(pose) -> pin.SE3:
    p, o = pose.position, pose.orientation
    return pin.XYZQUATToSE3(np.array([p.x, p.y, p.z, o.x, o.y, o.z, o.w]))


def _numbers(m: Marker) -> np.ndarray:
    p, o, s, c = m.pose.position, m.pose.orientation, m.scale, m.color
    vals = [p.x, p.y, p.z, o.x, o.y, o.z, o.w, s.x, s.y, s.z, c.r, c.g, c.b, c.a]
    vals += [v for pt in m.points for v in (pt.x, pt.y, pt.z)]
    return np.array(vals, dtype=float)


def _joint_states(geometry) -> list[np.ndarray]:
    """Joint states over the whole range: random, zero, at the limits, folded."""
    lo, hi = geometry.model.lowerPositionLimit, geometry.model.upperPositionLimit
    rng = np.random.default_rng(23)
    qs = [rng.uniform(lo, hi) for _ in range(25)]
    qs += [np.zeros(6), lo.copy(), hi.copy(), np.array([0, -np.pi / 2, np.pi, 0, np.pi, 0]),
           np.array([np.pi, 0, -np.pi, np.pi, -np.pi, 2 * np.pi])]
    return qs


def test_marker_poses_are_forward_kinematics(scene, params):
    geometry = Geometry()
    model, data = geometry.model, geometry.model.createData()
    tool0 = model.getFrameId('tool0')
    tool0Mc = pose_from_xyz_rpy(params.hand_eye[:3], params.hand_eye[3:])
    W, H = params.camera_width, params.camera_height
    corners = np.array([[0, 0], [W, 0], [W, H], [0, H]], float) - 0.5
    rays = np.column_stack([(corners[:, 0] - params.camera_u0) / params.camera_px,
                            (corners[:, 1] - params.camera_v0) / params.camera_py,
                            np.ones(4)])
    frustum = np.vstack([np.zeros(3), scene.frustum_depth * rays])
    edges = [(0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 3), (3, 4), (4, 1)]
    want_edges = {tuple(sorted((tuple(np.round(frustum[a], 9)), tuple(np.round(frustum[b], 9)))))
                  for a, b in edges}
    wMo = pose_from_xyz_rpy(params.target_pose[:3], params.target_pose[3:])
    wMcd = wMo * pose_from_xyz_rpy(params.desired_cMo[:3], params.desired_cMo[3:]).inverse()
    worst = 0.0
    for q in _joint_states(geometry):
        path = np.array([[0.1, 0.2, 0.3], [0.1, 0.2, 0.31], [0.12, 0.2, 0.3]])
        arr = marker_array(scene.markers(q, path), Header(frame_id='world'))
        assert arr.markers[0].action == Marker.DELETEALL
        ms = arr.markers[1:]
        for m in ms:
            vals = _numbers(m)
            assert np.all(np.isfinite(vals)), (m.ns, m.id)
            o = m.pose.orientation
            assert abs(np.linalg.norm([o.x, o.y, o.z, o.w]) - 1.0) < 1e-12, (m.ns, m.id, q)
        robot = sorted((m for m in ms if m.ns == 'robot'), key=lambda m: m.id)
        assert len(robot) == len(geometry.geom.geometryObjects) == 7
        for m, M in zip(robot, geometry.placements(q)):
            worst = max(worst, float(np.max(np.abs(_se3(m.pose).homogeneous - M.homogeneous))))
        pin.framesForwardKinematics(model, data, q)
        wMc = data.oMf[tool0] * tool0Mc
        (camera,) = [m for m in ms if m.ns == 'camera']
        np.testing.assert_allclose(_se3(camera.pose).homogeneous, wMc.homogeneous, atol=1e-9)
        pts = np.array([[p.x, p.y, p.z] for p in camera.points])
        got = {tuple(sorted((tuple(np.round(a, 9)), tuple(np.round(b, 9)))))
               for a, b in zip(pts[::2], pts[1::2])}
        assert got == want_edges
        (line,) = [m for m in ms if m.ns == 'camera_path']
        np.testing.assert_array_equal([[p.x, p.y, p.z] for p in line.points], path)
        (des,) = [m for m in ms if m.ns == 'desired_camera']
        np.testing.assert_allclose(_se3(des.pose).homogeneous, wMcd.homogeneous, atol=1e-12)
    assert worst < 1e-9, worst


def test_a_scene_with_nan_state_sends_no_nan(scene):
    """
    Joint states with a NaN are refused by the scene; a non-finite marker is left out.

    Before, a marker with a NaN pose, points or scale, or with a matrix that is not a
    rotation (its quaternion NaN), was sent as it was.
    """
    for q in (np.full(6, np.nan), np.array([0, 0, np.inf, 0, 0, 0]), np.zeros(5)):
        with pytest.raises(SceneError, match='joint state'):
            scene.markers(q)
    good = scene.markers(np.zeros(6))
    nan_pose = pin.SE3(np.eye(3), np.array([np.nan, 0.0, 0.0]))
    not_rotation = pin.SE3(np.eye(3), np.zeros(3))
    not_rotation.rotation = np.zeros((3, 3))
    mirror = pin.SE3(np.eye(3), np.zeros(3))
    mirror.rotation = np.diag([1.0, 1.0, -1.0])
    bad = [MarkerSpec('bad', 0, MarkerKind.SPHERE, nan_pose, (1, 1, 1), (1, 1, 1, 1)),
           MarkerSpec('bad', 1, MarkerKind.SPHERE, not_rotation, (1, 1, 1), (1, 1, 1, 1)),
           MarkerSpec('bad', 2, MarkerKind.SPHERE, mirror, (1, 1, 1), (1, 1, 1, 1)),
           MarkerSpec('bad', 3, MarkerKind.SPHERE, pin.SE3.Identity(), (np.inf, 1, 1),
                      (1, 1, 1, 1)),
           MarkerSpec('bad', 4, MarkerKind.LINE_STRIP, pin.SE3.Identity(), (0.01, 0, 0),
                      (1, 1, 1, 1), np.array([[0, 0, 0], [np.nan, 0, 0]], float)),
           MarkerSpec('bad', 5, MarkerKind.SPHERE, pin.SE3.Identity(), (1, 1, 1),
                      (1, np.nan, 1, 1))]
    arr = marker_array(good[:3] + bad + good[3:], Header(frame_id='world'))
    assert [(m.ns, m.id) for m in arr.markers[1:]] == [(s.ns, s.id) for s in good]
    for m in arr.markers[1:]:
        assert np.all(np.isfinite(_numbers(m)))


SCENARIOS = sorted(p.stem for p in (Path(__file__).resolve().parents[1] / 'config'
                                    / 'scenarios').glob('*.yaml'))


@pytest.mark.parametrize('name', SCENARIOS)
def test_every_scenarios_scene_is_finite_and_its_frustum_meets_the_corners(name):
    """
    The scene of each scenario (pinhole, fisheye, catadioptric, CC target, balloon).

    Every number finite, every quaternion unit; the frustum's far points project (the
    scenario's camera model) onto the image corners, or, for a corner beyond a wide
    camera's field, onto the segment from the principal point to it.
    """
    p = ArmSimParams.from_mapping(section(load_node_params(name), 'arm_sim'))
    scene = sim_scene(p)
    cam = scene.camera
    W, H = cam.width, cam.height
    corners = np.array([[0, 0], [W, 0], [W, H], [0, H]], float) - 0.5
    centre = np.array([cam.u0, cam.v0])
    for q in (np.asarray(p.start_joints, float), np.zeros(6)):
        arr = marker_array(scene.markers(q), Header(frame_id='world'))
        for m in arr.markers[1:]:
            assert np.all(np.isfinite(_numbers(m))), (name, m.ns, m.id)
            o = m.pose.orientation
            assert abs(np.linalg.norm([o.x, o.y, o.z, o.w]) - 1.0) < 1e-12
        (camera,) = [m for m in arr.markers if m.ns == 'camera']
        pts = np.array([[pt.x, pt.y, pt.z] for pt in camera.points])
        far = pts[1:8:2]  # the 4 apex edges' far ends, in corner order
        np.testing.assert_allclose(pts[0:8:2], 0.0)
        uv = cam.project(far)
        _, ok = cam.lift_where(corners)
        for c, got, lifts in zip(corners, uv, ok):
            if lifts:
                np.testing.assert_allclose(got, c, atol=1e-6)
            else:  # pulled toward the principal point, along the line to the corner
                d, g = c - centre, got - centre
                assert abs(d[0] * g[1] - d[1] * g[0]) < 1e-6 * np.linalg.norm(d) ** 2
                assert 0 < g @ d < d @ d, (name, c, got)
