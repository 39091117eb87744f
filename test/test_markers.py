"""
The 3-D scene for ROS viewers: ``arm_sim``'s ``~/markers`` (visualization_msgs/MarkerArray).

Over DDS, the installed ``arm_sim`` in lockstep, driven by a test node: each array's robot
meshes are at Pinocchio's own placements of the URDF's visual geometry for the
``joint_states`` published with the same stamp (to 1e-9); the camera, its path, the target
and the desired camera agree with the published ground truth and the params file; the mesh
URIs resolve, as a Jazzy install resolves ``package://`` (the ament index), to the installed
example-robot-data's files; a subscriber that comes late still gets the whole scene. The
core's timing (first frame, every ``1/markers_rate`` s of sim time, after a jump), the
``file://`` fallback and ``markers_rate: 0`` are checked without ROS.
"""
from __future__ import annotations

import importlib.metadata
import os
from pathlib import Path
from urllib.parse import urlparse

from conftest import REPO, wait_for
import numpy as np
import pinocchio as pin
import pytest
from sphere_servo.pipeline.arm_sim import ArmSimCore
from sphere_servo.pipeline.config import load_params_files, section
from sphere_servo.pipeline.params import ArmSimParams
from sphere_servo.sim.arm import pose_from_xyz_rpy
from sphere_servo.sim.ur5 import find_ur5_urdf
import yaml

CONFIG = REPO / 'config' / 'params' / 'arm_sim.yaml'
DT = 1.0 / 30.0
WAIT = 20.0  # bound on any single wait (a loaded machine); never asserted on
PKG = 'package://example-robot-data/'


def _config() -> dict:
    return yaml.safe_load(CONFIG.read_text())['arm_sim']['ros__parameters']


def _pose(xyz_rpy) -> pin.SE3:
    return pose_from_xyz_rpy(xyz_rpy[:3], xyz_rpy[3:])


class Geometry:
    """Pinocchio's own visual geometry of the UR5 URDF: placements for a joint state."""

    def __init__(self):
        urdf = find_ur5_urdf()
        self.model = pin.buildModelFromUrdf(urdf)
        share = Path(urdf).parents[4]  # …/share/example-robot-data/robots/ur_description/urdf
        self.geom = pin.buildGeomFromUrdf(self.model, urdf, pin.GeometryType.VISUAL,
                                          package_dirs=[str(share)])
        self.data, self.gdata = self.model.createData(), self.geom.createData()

    def placements(self, q) -> list[pin.SE3]:
        pin.forwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        pin.updateGeometryPlacements(self.model, self.data, self.geom, self.gdata)
        return [pin.SE3(M) for M in self.gdata.oMg]


def ament_share(package: str, env: dict) -> Path:
    """Find a package's share directory as a Jazzy install does: the ament index."""
    from ament_index_python.packages import get_package_share_directory
    old = os.environ.get('AMENT_PREFIX_PATH')
    os.environ['AMENT_PREFIX_PATH'] = env['AMENT_PREFIX_PATH']
    try:
        return Path(get_package_share_directory(package))
    finally:
        if old is None:
            del os.environ['AMENT_PREFIX_PATH']
        else:
            os.environ['AMENT_PREFIX_PATH'] = old


def _robot_data_prefix() -> Path:
    """Return the install prefix of the example-robot-data wheel (its ament index marker)."""
    dist = importlib.metadata.distribution('example-robot-data')
    marker = next(f for f in dist.files
                  if str(f).endswith('resource_index/packages/example-robot-data'))
    return Path(dist.locate_file(marker)).parents[4]


def _se3(pose) -> pin.SE3:
    p, o = pose.position, pose.orientation
    return pin.XYZQUATToSE3(np.array([p.x, p.y, p.z, o.x, o.y, o.z, o.w]))


def _ns(array) -> dict:
    out = {}
    for m in array.markers[1:]:
        out.setdefault(m.ns, []).append(m)
    return out


def _ns_of(ms) -> dict:
    out = {}
    for m in ms:
        out.setdefault(m.ns, []).append(m)
    return out


def test_markers_follow_the_joint_states_over_dds(launch, test_node):
    from geometry_msgs.msg import PoseStamped, TwistStamped
    from sensor_msgs.msg import Image, JointState
    from sphere_servo.ros.conversions import twist_from_array
    from sphere_servo.ros.markers import MARKERS_QOS
    from std_msgs.msg import Header
    from visualization_msgs.msg import Marker, MarkerArray
    node, spin = test_node
    proc = launch('arm_sim', '--ros-args', '--params-file', str(CONFIG),
                  '-p', 'clock_mode:=lockstep')
    images, joints, poses, arrays = [], {}, {}, []

    def stamp(msg) -> int:
        """Return a message's header stamp in ns (a MarkerArray: its first marker's)."""
        hdr = msg.markers[0].header if isinstance(msg, MarkerArray) else msg.header
        return hdr.stamp.sec * 1_000_000_000 + hdr.stamp.nanosec
    node.create_subscription(Image, 'camera/image_raw', images.append, 50)
    node.create_subscription(JointState, 'joint_states',
                             lambda m: joints.setdefault(stamp(m), m), 100)
    node.create_subscription(PoseStamped, 'ground_truth/camera_pose',
                             lambda m: poses.setdefault(stamp(m), m), 100)
    node.create_subscription(MarkerArray, 'arm_sim/markers', arrays.append, MARKERS_QOS)
    pub = node.create_publisher(TwistStamped, 'camera/cmd_vel', 10)
    assert spin(WAIT, until=lambda: images and arrays), proc.log()
    wait_for(lambda: pub.get_subscription_count() > 0, WAIT, what='cmd_vel match')
    t0 = stamp(images[-1])
    n_steps = 13
    for k in range(n_steps):
        n = len(images)
        pub.publish(TwistStamped(header=Header(frame_id='camera_optical_frame'),
                                 twist=twist_from_array([0.04, -0.02, 0.05, 0.1, -0.05, 0.2])))
        assert spin(WAIT, until=lambda: len(images) > n), f'no image after command {k}'
    t_end = stamp(images[-1])
    assert t_end == pytest.approx(t0 + n_steps * DT * 1e9, abs=1e3)
    spin(WAIT, until=lambda: arrays and stamp(arrays[-1]) >= t0 + 12 * DT * 1e9 - 1e3
         and t_end in joints and t_end in poses)
    # at the first frame, then every 1/markers_rate = 0.1 s of sim time (3 frames)
    got = [stamp(a) for a in arrays]
    want = [t0 + int(round(k * DT * 1e9)) for k in range(0, n_steps + 1, 3)]
    np.testing.assert_allclose(got, want, atol=1e3)
    cfg = _config()
    wMo, cdMo = _pose(cfg['target_pose']), _pose(cfg['desired_cMo'])
    geometry = Geometry()
    share = ament_share('example-robot-data', {
        'AMENT_PREFIX_PATH': str(_robot_data_prefix())})
    path_so_far = []
    worst = 0.0
    for a in arrays:
        st = stamp(a)
        assert a.markers[0].action == Marker.DELETEALL
        assert {m.header.frame_id for m in a.markers} == {'world'}
        assert {stamp(m) for m in a.markers} == {st}
        by_ns = _ns(a)
        assert set(by_ns) >= {'robot', 'target', 'camera', 'desired_camera'}
        q = joints[st].position
        robot = sorted(by_ns['robot'], key=lambda m: m.id)
        assert len(robot) == len(geometry.geom.geometryObjects) == 7
        for m, oMg, go in zip(robot, geometry.placements(q), geometry.geom.geometryObjects):
            assert m.type == Marker.MESH_RESOURCE and m.action == Marker.ADD
            worst = max(worst, float(np.max(np.abs(_se3(m.pose).homogeneous
                                                   - oMg.homogeneous))))
            # package:// as a ROS install resolves it: <share of the package>/<rest>
            assert m.mesh_resource.startswith(PKG), m.mesh_resource
            f = share / m.mesh_resource[len(PKG):]
            assert f.is_file() and f.resolve() == Path(go.meshPath).resolve(), f
            np.testing.assert_array_equal([m.scale.x, m.scale.y, m.scale.z], go.meshScale)
        # the camera frustum at the published ground truth, the target, the desired camera
        wMc = wMo * _se3(poses[st].pose)
        (cam,) = by_ns['camera']
        np.testing.assert_allclose(_se3(cam.pose).homogeneous, wMc.homogeneous, atol=1e-9)
        assert cam.type == Marker.LINE_LIST and len(cam.points) == 16
        body = next(m for m in by_ns['target'] if m.id == 0)
        np.testing.assert_allclose([body.pose.position.x, body.pose.position.y,
                                    body.pose.position.z], wMo.translation, atol=1e-12)
        assert body.scale.x == pytest.approx(2 * cfg['target']['radius'])
        (des,) = by_ns['desired_camera']
        np.testing.assert_allclose(_se3(des.pose).homogeneous,
                                   (wMo * cdMo.inverse()).homogeneous, atol=1e-9)
        # the path: the camera centres of the frames so far (each a few mm apart)
        path_so_far = [(wMo * _se3(poses[s].pose)).translation
                       for s in sorted(poses) if t0 <= s <= st]
        if len(path_so_far) >= 2:
            (line,) = by_ns['camera_path']
            pts = np.array([[p.x, p.y, p.z] for p in line.points])
            np.testing.assert_allclose(pts, path_so_far, atol=1e-9)
        else:
            assert 'camera_path' not in by_ns
    assert worst < 1e-9, worst
    # a viewer that subscribes now still gets the whole scene, the latest one (latched)
    late = []
    node.create_subscription(MarkerArray, 'arm_sim/markers', late.append, MARKERS_QOS)
    assert spin(WAIT, until=lambda: late), 'a late subscriber got no markers'
    assert stamp(late[-1]) == stamp(arrays[-1]) and len(late[-1].markers) == \
        len(arrays[-1].markers)
    assert proc.stop() == 0, proc.log()


@pytest.fixture(scope='module')
def params() -> ArmSimParams:
    merged = load_params_files([CONFIG, REPO / 'config' / 'params' / 'special_sphere.yaml'])
    return ArmSimParams.from_mapping({**section(merged, 'arm_sim'),
                                      'camera': {'width': 160, 'height': 120, 'px': 150.0,
                                                 'py': 150.0, 'u0': 80.0, 'v0': 60.0}})


def test_markers_timing_jumps_and_fallback(params):
    sim = ArmSimCore(params.replace({'markers_rate': 7.5}))
    geometry = Geometry()
    first = sim.frame()
    assert sim.markers(first) is not None and sim.markers(first) is None  # once a frame
    times, kinds = [], []
    v = [0.03, 0.0, 0.05, 0.0, 0.05, 0.0]
    for _ in range(20):
        f = sim.on_command(v).frame
        ms = sim.markers(f)
        if ms is not None:
            times.append(f.t - first.t)
            kinds.append(ms)
            for m, oMg in zip(ms[:7], geometry.placements(f.q)):
                np.testing.assert_allclose(m.pose.homogeneous, oMg.homogeneous, atol=1e-9)
    # every 1/7.5 s of sim time: each 4th frame at 30 Hz
    np.testing.assert_allclose(times, [4 * DT * k for k in range(1, 6)], atol=1e-9)
    path = _ns_of(kinds[-1])['camera_path'][0].points
    assert len(path) == 21  # every frame's camera centre since the start (a few mm apart)
    np.testing.assert_allclose(path[-1], sim.arm.wMc().translation, atol=1e-12)
    # a jump: the scene at once, and the path starts again where the arm jumped to
    jumped = sim.go('desired').frame
    ms = sim.markers(jumped)
    assert ms is not None and 'camera_path' not in _ns_of(ms)
    np.testing.assert_allclose(_ns_of(ms)['camera'][0].pose.homogeneous,
                               sim.arm.wMc().homogeneous, atol=1e-12)
    # the desired camera follows a runtime change of desired_cMo
    cdMo = [0.01, 0.02, 0.4, 0.1, 0.0, 0.2]
    sim.params = sim.params.replace({'desired_cMo': cdMo})
    f = sim.on_command([0.0] * 6).frame
    for _ in range(3):
        f = sim.on_command([0.0] * 6).frame
    des = _ns_of(sim.markers(f))['desired_camera'][0]
    np.testing.assert_allclose(des.pose.homogeneous,
                               (sim.arm.wMo * _pose(cdMo).inverse()).homogeneous, atol=1e-12)
    # the fallback for a viewer without the package: file:// URIs of the same files
    files = ArmSimCore(params.replace({'markers_mesh_uris': 'file'}))
    for m, go in zip(files.markers(files.frame())[:7], geometry.geom.geometryObjects):
        assert m.mesh_uri.startswith('file:///')
        assert Path(urlparse(m.mesh_uri).path).resolve() == Path(go.meshPath).resolve()
    # markers_rate 0: none, and no scene built
    off = ArmSimCore(params.replace({'markers_rate': 0.0}))
    assert off.scene is None and off.markers(off.frame()) is None


def test_markers_without_meshes_leave_the_simulation_running(params, tmp_path):
    """A URDF whose meshes cannot be found: no markers and why, the arm still simulates."""
    urdf = Path(find_ur5_urdf())
    bad = tmp_path / 'ur5.urdf'
    bad.write_text(urdf.read_text().replace('package://example-robot-data/',
                                            'package://not-installed-pkg/'))
    sim = ArmSimCore(params.replace({'urdf_path': str(bad)}))
    assert sim.scene is None and 'not-installed-pkg' in sim.markers_error
    assert sim.markers(sim.frame()) is None
    assert sim.on_command([0.0, 0.0, 0.01, 0.0, 0.0, 0.0]).frame.image.shape == (120, 160, 3)
