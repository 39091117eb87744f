"""
Test the 3-D scene of a run (``sim/scene.py``).

Mesh poses against Pinocchio's own geometry placements, mesh files of the installed
example-robot-data, ``package://`` resolution, the camera frustum against the camera
model's projection, the target and the desired camera.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import cc_target, special_sphere
from sphere_servo.sim.arm import ArmModel, pose_from_xyz_rpy
from sphere_servo.sim.scene import (CameraPath, FRUSTUM_EDGES, MarkerKind, package_dirs,
                                    resolve_uri, Scene, SceneError, urdf_meshes)

HAND_EYE = pose_from_xyz_rpy([0.0, -0.04, 0.02], [0.0, 0.0, 0.0])
WMO = pose_from_xyz_rpy([0.5, 0.1, 0.05], [np.pi, 0.0, -np.pi / 2])
CMO_DESIRED = pose_from_xyz_rpy([0.0, 0.0, 0.45], [0.0, 0.0, 0.0])


@pytest.fixture(scope='module')
def scene():
    return Scene(ArmModel(tool0Mc=HAND_EYE, wMo=WMO), special_sphere(), CameraIntrinsics(),
                 cMo_desired=CMO_DESIRED)


@pytest.fixture(scope='module')
def pin_geometry(scene):
    """
    Build Pinocchio's own visual geometry model of the URDF.

    Pinocchio parses the URDF and resolves the meshes itself.
    """
    share = Path(scene.arm.urdf_path).parents[4]
    geom = pin.buildGeomFromUrdf(scene.model, scene.arm.urdf_path, pin.GeometryType.VISUAL,
                                 package_dirs=[str(share)])
    return geom, geom.createData()


def _random_q(model, rng):
    lo = np.maximum(model.lowerPositionLimit, -2 * np.pi)
    hi = np.minimum(model.upperPositionLimit, 2 * np.pi)
    return lo + rng.random(model.nq) * (hi - lo)


def test_link_poses_equal_pinocchio_fk(scene, pin_geometry):
    geom, gdata = pin_geometry
    assert [m.name for m in scene.meshes] == [g.name for g in geom.geometryObjects]
    data = scene.model.createData()
    rng = np.random.default_rng(19)
    worst = 0.0
    for _ in range(100):
        q = _random_q(scene.model, rng)
        pin.forwardKinematics(scene.model, data, q)
        pin.updateGeometryPlacements(scene.model, data, geom, gdata)
        for wMm, oMg in zip(scene.link_poses(q), gdata.oMg):
            worst = max(worst, np.max(np.abs(wMm.homogeneous - oMg.homogeneous)))
    assert worst < 1e-9, worst
    # and the poses move with q (not a constant): the wrist's mesh between two states
    a, b = (scene.link_poses(_random_q(scene.model, rng))[-1] for _ in range(2))
    assert np.linalg.norm(a.translation - b.translation) > 1e-3


STL = """solid t
facet normal 0 0 1
outer loop
vertex 0 0 0
vertex 0.1 0 0
vertex 0 0.1 0
endloop
endfacet
endsolid t
"""


def test_visual_origins_compose_as_pinocchio_does(tmp_path):
    """
    Check offset, rotated, scaled visual origins (the UR5's are all identity).

    On a two-joint arm, each mesh pose still equals Pinocchio's geometry placement.
    """
    (tmp_path / 'm.stl').write_text(STL)
    vis = ('<visual><origin xyz="{}" rpy="{}"/><geometry><mesh filename="m.stl" '
           'scale="1 2 3"/></geometry></visual>')
    urdf = tmp_path / 'two.urdf'
    urdf.write_text(f"""<robot name="two">
      <link name="base">{vis.format('0.1 0 0.05', '0.3 0 0')}</link>
      <link name="l1">{vis.format('0 0.2 0', '0 0.4 -0.2')}
        {vis.format('0.05 0 0.3', '1.0 0.2 0.1')}</link>
      <link name="tool0"/>
      <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
        <origin xyz="0 0 0.3" rpy="0 0.2 0"/><axis xyz="0 0 1"/>
        <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
      <joint name="j2" type="revolute"><parent link="l1"/><child link="tool0"/>
        <origin xyz="0.4 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/>
        <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
    </robot>""")
    sc = Scene(ArmModel(urdf_path=urdf), special_sphere(), CameraIntrinsics())
    geom = pin.buildGeomFromUrdf(sc.model, str(urdf), pin.GeometryType.VISUAL,
                                 package_dirs=[str(tmp_path)])
    gdata, data = geom.createData(), sc.model.createData()
    assert [m.name for m in sc.meshes] == [g.name for g in geom.geometryObjects]
    rng = np.random.default_rng(5)
    for _ in range(20):
        q = rng.uniform(-3, 3, 2)
        pin.forwardKinematics(sc.model, data, q)
        pin.updateGeometryPlacements(sc.model, data, geom, gdata)
        for wMm, oMg in zip(sc.link_poses(q), gdata.oMg):
            np.testing.assert_allclose(wMm.homogeneous, oMg.homogeneous, atol=1e-9)


def test_camera_pose_is_the_arm_camera(scene):
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = _random_q(scene.model, rng)
        wMc = scene.camera_pose(q)
        # tool0's pose from the link chain, composed with the hand-eye transform by hand
        data = scene.model.createData()
        pin.framesForwardKinematics(scene.model, data, q)
        wMtool0 = data.oMf[scene.model.getFrameId('tool0')]
        np.testing.assert_allclose(wMc.homogeneous, (wMtool0 * HAND_EYE).homogeneous,
                                   atol=1e-12)


def test_mesh_files_exist_in_example_robot_data(scene, pin_geometry):
    geom, _ = pin_geometry
    assert len(scene.meshes) == 7
    for m, g in zip(scene.meshes, geom.geometryObjects):
        assert m.uri.startswith('package://example-robot-data/robots/ur_description/meshes/')
        assert m.path.is_file() and m.path.stat().st_size > 10_000, m.path
        assert m.path.resolve() == Path(g.meshPath).resolve()
        assert m.file_uri.startswith('file:///') and m.file_uri.endswith(m.path.name)
        np.testing.assert_array_equal(m.scale, g.meshScale)


def test_package_uri_resolution(tmp_path, monkeypatch):
    first, second = tmp_path / 'a' / 'share', tmp_path / 'b' / 'share'
    (second / 'pkg' / 'meshes').mkdir(parents=True)
    (second / 'pkg' / 'meshes' / 'm.stl').write_bytes(b'solid x')
    (first / 'other').mkdir(parents=True)
    uri = 'package://pkg/meshes/m.stl'
    assert resolve_uri(uri, [first, second]) == second / 'pkg/meshes/m.stl'
    # the first directory that has it wins
    (first / 'pkg' / 'meshes').mkdir(parents=True)
    (first / 'pkg' / 'meshes' / 'm.stl').write_bytes(b'solid y')
    assert resolve_uri(uri, [first, second]) == first / 'pkg/meshes/m.stl'
    with pytest.raises(SceneError, match='not found; looked in .*nope'):
        resolve_uri('package://nope/m.stl', [first, second])
    with pytest.raises(SceneError, match='malformed'):
        resolve_uri('package://pkg', [first])
    with pytest.raises(SceneError, match='unsupported'):
        resolve_uri('http://example.org/m.stl', [first])
    assert resolve_uri((second / 'pkg/meshes/m.stl').as_uri()) == second / 'pkg/meshes/m.stl'
    assert resolve_uri('meshes/m.stl', base=second / 'pkg') == second / 'pkg/meshes/m.stl'
    with pytest.raises(SceneError, match='does not exist'):
        resolve_uri('meshes/none.stl', base=second / 'pkg')
    # the search list: the URDF's own package's parent, then a ROS install's share dirs
    urdf = second / 'pkg' / 'urdf' / 'r.urdf'
    monkeypatch.setenv('AMENT_PREFIX_PATH', f'{tmp_path / "ros"}:{tmp_path / "ws"}')
    monkeypatch.delenv('ROS_PACKAGE_PATH', raising=False)
    assert package_dirs(urdf, 'pkg') == [second, tmp_path / 'ros/share', tmp_path / 'ws/share']


def test_installed_urdf_uris_resolve_through_the_search_list():
    urdf = Path(ArmModel().urdf_path)
    dirs = package_dirs(urdf, 'example-robot-data')
    assert dirs[0] == urdf.parents[4] and dirs[0].name == 'share'
    for m in urdf_meshes(urdf):
        assert resolve_uri(m.uri, dirs) == m.path


def _urdf(tmp_path, body: str) -> Path:
    (tmp_path / 'meshes').mkdir(exist_ok=True)
    (tmp_path / 'meshes' / 'a.stl').write_bytes(b'solid a')
    path = tmp_path / 'r.urdf'
    path.write_text(f'<robot name="r"><material name="red"><color rgba="1 0 0 1"/></material>'
                    f'{body}</robot>')
    return path


def test_urdf_visuals_origin_colour_and_bad_files(tmp_path):
    path = _urdf(tmp_path, """
      <link name="l1"><visual><origin xyz="0 0 0.1" rpy="0 0 1.5"/>
        <geometry><mesh filename="meshes/a.stl" scale="2 2 2"/></geometry>
        <material name="red"/></visual>
        <visual><geometry><box size="1 1 1"/></geometry></visual>
        <visual><geometry><mesh filename="meshes/a.stl"/></geometry>
        <material name="m"><color rgba="0 0.5 0 1"/></material></visual></link>""")
    meshes = urdf_meshes(path)
    assert [m.name for m in meshes] == ['l1_0', 'l1_2']  # the box is not a mesh
    np.testing.assert_allclose(meshes[0].lMm.translation, [0, 0, 0.1])
    np.testing.assert_allclose(meshes[0].lMm.rotation, pin.rpy.rpyToMatrix(0, 0, 1.5))
    np.testing.assert_array_equal(meshes[0].scale, [2, 2, 2])
    assert meshes[0].rgba == (1, 0, 0, 1) and meshes[1].rgba == (0, 0.5, 0, 1)
    bad = _urdf(tmp_path, '<link name="l"><visual><geometry><mesh filename="meshes/b.stl"/>'
                          '</geometry></visual></link>')
    with pytest.raises(SceneError, match='does not exist'):
        urdf_meshes(bad)
    bad.write_text('<robot><link name="l"><visual><origin xyz="0 nan"/><geometry><mesh '
                   'filename="meshes/a.stl"/></geometry></visual></link></robot>')
    with pytest.raises(SceneError, match='3 finite numbers'):
        urdf_meshes(bad)
    bad.write_text('<robot>')
    with pytest.raises(SceneError, match='cannot read URDF'):
        urdf_meshes(bad)


def test_frustum_corners_project_to_the_image_corners():
    cam = CameraIntrinsics(px=520.0, py=610.0, u0=300.0, v0=260.0, width=640, height=480)
    scene = Scene(ArmModel(tool0Mc=HAND_EYE, wMo=WMO), special_sphere(), cam,
                  frustum_depth=0.25)
    wMc = pin.SE3(pin.exp3(np.array([0.3, -1.1, 0.4])), np.array([0.4, -0.2, 0.7]))
    pts = scene.frustum(wMc)
    assert pts.shape == (5, 3) and len(FRUSTUM_EDGES) == 8
    np.testing.assert_allclose(pts[0], wMc.translation, atol=1e-12)
    cX = (wMc.rotation.T @ (pts[1:] - wMc.translation).T).T
    np.testing.assert_allclose(cX[:, 2], 0.25, atol=1e-12)
    np.testing.assert_allclose(cam.project(cX), [[-0.5, -0.5], [639.5, -0.5], [639.5, 479.5],
                                                 [-0.5, 479.5]], atol=1e-9)
    with pytest.raises(SceneError, match='frustum_depth'):
        Scene(scene.arm, special_sphere(), cam, frustum_depth=0.0)


def test_target_marks_and_desired_camera(scene):
    sp = special_sphere()
    for name, oP in sp.marks().items():
        np.testing.assert_allclose(scene.target.marks[name], WMO.act(oP), atol=1e-12)
    assert scene.target.radius == sp.radius and scene.target.axes is None
    # the desired camera pose seen by the arm: IK to c*Mo, then the arm's ground truth
    q, ok, _ = scene.arm.ik_for_cMo(CMO_DESIRED, [0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
    assert ok
    wMc = scene.camera_pose(q)
    np.testing.assert_allclose(wMc.homogeneous, scene.wMc_desired.homogeneous, atol=1e-5)
    # in the desired camera the sphere centre is on the optical axis, 0.45 m ahead
    np.testing.assert_allclose(scene.wMc_desired.actInv(scene.target.wMo.translation),
                               [0, 0, 0.45], atol=1e-12)
    cc = Scene(scene.arm, cc_target(), CameraIntrinsics())
    assert set(cc.target.marks) == {'P1', 'P3'} and cc.wMc_desired is None
    assert cc.target.colors['P3'] == cc_target().colors['P2']


def test_bad_joint_states(scene):
    for q in (np.zeros(5), np.full(6, np.nan), [0, 0, 0, 0, 0, np.inf]):
        with pytest.raises(SceneError, match='6 finite numbers'):
            scene.link_poses(q)
        with pytest.raises(SceneError):
            scene.camera_pose(q)


def test_camera_path_spacing_and_bound():
    path = CameraPath(min_step=0.01, max_points=10)
    assert path.add([0, 0, 0]) and not path.add([0.005, 0, 0]) and path.add([0.011, 0, 0])
    np.testing.assert_allclose(path.points, [[0, 0, 0], [0.011, 0, 0]])
    for k in range(2, 40):
        path.add([0.011 * k, 0, 0])
    pts = path.points
    assert len(pts) <= 10 and pts[0, 0] == 0.0 and np.isclose(pts[-1, 0], 0.011 * 39)
    assert np.all(np.diff(pts[:, 0]) > 0)
    with pytest.raises(SceneError):
        path.add([np.nan, 0, 0])
    for kw in ({'min_step': -1.0}, {'max_points': 1}):
        with pytest.raises(SceneError):
            CameraPath(**kw)
    path.clear()
    assert path.points.shape == (0, 3)


def test_markers_of_the_scene(scene, pin_geometry):
    """The markers a ROS viewer draws: meshes at Pinocchio's placements, URIs that resolve."""
    geom, gdata = pin_geometry
    rng = np.random.default_rng(11)
    path = CameraPath(min_step=0.0)
    for _ in range(5):
        q = _random_q(scene.model, rng)
        path.add(scene.camera_pose(q).translation)
    markers = scene.markers(q, path.points)
    assert len({(m.ns, m.id) for m in markers}) == len(markers)
    ns = {}
    for m in markers:
        ns.setdefault(m.ns, []).append(m)
    assert set(ns) == {'robot', 'target', 'camera', 'camera_path', 'desired_camera'}
    data = scene.model.createData()
    pin.forwardKinematics(scene.model, data, q)
    pin.updateGeometryPlacements(scene.model, data, geom, gdata)
    dirs = package_dirs(scene.arm.urdf_path, 'example-robot-data')
    assert len(ns['robot']) == 7
    for m, g, oMg in zip(ns['robot'], geom.geometryObjects, gdata.oMg):
        assert m.kind == MarkerKind.MESH_RESOURCE == 10
        np.testing.assert_allclose(m.pose.homogeneous, oMg.homogeneous, atol=1e-9)
        assert m.mesh_uri.startswith('package://example-robot-data/')
        assert resolve_uri(m.mesh_uri, dirs).resolve() == Path(g.meshPath).resolve()
    for m, g in zip(scene.markers(q, mesh_uris='file')[:7], geom.geometryObjects):
        assert m.mesh_uri.startswith('file:///')
        assert resolve_uri(m.mesh_uri).resolve() == Path(g.meshPath).resolve()
    body, *marks = ns['target']
    assert body.kind == MarkerKind.SPHERE and body.scale == (0.1, 0.1, 0.1)  # diameters
    np.testing.assert_allclose(body.pose.translation, WMO.translation, atol=1e-12)
    for m, oP in zip(marks, special_sphere().marks().values()):
        np.testing.assert_allclose(m.pose.translation, WMO.act(oP), atol=1e-12)
    cam, = ns['camera']
    assert cam.kind == MarkerKind.LINE_LIST and cam.points.shape == (16, 3)
    world = (cam.pose.rotation @ cam.points.T).T + cam.pose.translation
    wMc = scene.camera_pose(q)
    np.testing.assert_allclose(world, scene.frustum(wMc)[np.array(FRUSTUM_EDGES).ravel()],
                               atol=1e-12)
    np.testing.assert_allclose(cam.pose.homogeneous, wMc.homogeneous, atol=1e-12)
    np.testing.assert_array_equal(ns['camera_path'][0].points, path.points)
    np.testing.assert_allclose(ns['desired_camera'][0].pose.homogeneous,
                               scene.wMc_desired.homogeneous, atol=1e-12)
    assert all(0 <= c <= 1 for m in markers for c in m.rgba)
    assert 'camera_path' not in {m.ns for m in scene.markers(q, path.points[:1])}
    with pytest.raises(SceneError, match='mesh_uris'):
        scene.markers(q, mesh_uris='http')
