"""
The 3-D scene of a run as plain data (no ROS): what a 3-D viewer draws.

- Robot: each visual mesh of the UR5's URDF (``example-robot-data``), with its ``package://``
  URI as the URDF writes it, the file it resolves to, its scale and colour, and its pose in
  the world for a joint state: ``wMm = wMl(q) · lMm``, ``wMl`` the link frame from
  Pinocchio's forward kinematics, ``lMm`` the visual's URDF ``<origin>``.
- Target: the sphere (or ellipsoid) at ``wMo`` and its marks ``wP = wMo · oP``.
- Camera: the optical frame ``wMc`` (REP 103: z forward, x right, y down) and its frustum,
  the pyramid from the optical centre to the image rectangle at a depth ``d``: the corner
  pixels back-projected, ``cX = d · K⁻¹ (u, v, 1)``.
- The camera's path so far (:class:`CameraPath`) and the desired camera pose
  ``wMc* = wMo · (c*Mo)⁻¹``.

This is what both the ROS viewers' markers and the offline replay page draw.
:meth:`Scene.markers` lists it as ``visualization_msgs/Marker``-shaped plain data
(:class:`MarkerSpec`, frame ``world``): ``MESH_RESOURCE`` markers whose ``package://``
URIs resolve wherever ``example-robot-data`` is installed as a ROS package
(``ros-jazzy-example-robot-data``); the fallback for a viewer without it is
``mesh_uris='file'``, ``file://`` URIs of this machine's files (RViz on the same machine).

``package://PKG/REL`` resolves to ``DIR/PKG/REL`` for the first directory ``DIR`` of the
search list that has it (ROS's ``share`` directories; see :func:`package_dirs`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
import os
from pathlib import Path
from urllib.parse import unquote, urlparse
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import Target
from sphere_servo.sim.arm import ArmModel, pose_from_xyz_rpy

PACKAGE_SCHEME = 'package://'
#: the frustum's edges as index pairs into :meth:`Scene.frustum`'s 5 points (apex, then the
#: image corners (0, 0), (W, 0), (W, H), (0, H))
FRUSTUM_EDGES = ((0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 3), (3, 4), (4, 1))
DEFAULT_RGBA = (0.7, 0.7, 0.7, 1.0)


class MarkerKind(int, Enum):
    """The ``visualization_msgs/Marker`` types the scene uses (the message's integers)."""

    ARROW = 0
    SPHERE = 2
    LINE_STRIP = 4
    LINE_LIST = 5
    MESH_RESOURCE = 10


@dataclass(frozen=True)
class MarkerSpec:
    """
    One marker of the scene, as ``visualization_msgs/Marker`` has it, without ROS.

    ``pose`` is the marker's frame in ``world``; ``points`` (n, 3) are in that frame (line
    markers); ``scale`` is the message's (a sphere's diameters, a line's width in x, a
    mesh's scale); ``rgba`` in [0, 1]; ``mesh_uri`` for ``MESH_RESOURCE``.
    """

    ns: str
    id: int  # noqa: A003 - the message's field name
    kind: MarkerKind
    pose: pin.SE3
    scale: tuple
    rgba: tuple
    points: np.ndarray | None = None
    mesh_uri: str = ''


class SceneError(ValueError):
    """A URDF, a mesh URI or a scene input cannot be used; the message says why."""


def package_dirs(urdf_path: str | os.PathLike, package: str | None = None) -> list[Path]:
    """
    List the directories that hold ROS packages, to resolve ``package://`` URIs against.

    In this order: the directory holding the URDF's own package (the parent of the URDF's
    first ancestor named ``package``, e.g. ``…/share`` for ``…/share/example-robot-data/
    robots/…/ur5_robot.urdf``), then ``share`` of every prefix on ``AMENT_PREFIX_PATH`` (a
    ROS install), then every entry of ``ROS_PACKAGE_PATH``.
    """
    out: list[Path] = []
    urdf = Path(urdf_path).resolve()
    if package:
        out += [p.parent for p in urdf.parents if p.name == package][:1]
    for prefix in filter(None, os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)):
        out.append(Path(prefix) / 'share')
    out += [Path(p) for p in filter(None, os.environ.get('ROS_PACKAGE_PATH', '')
                                    .split(os.pathsep))]
    return list(dict.fromkeys(out))


def resolve_uri(uri: str, dirs: list[Path] | None = None, base: Path | None = None) -> Path:
    """
    Resolve a URDF mesh URI to the file it names.

    ``package://PKG/REL`` → ``DIR/PKG/REL`` for the first ``DIR`` in ``dirs`` where it
    exists; ``file:///ABS`` → ``/ABS``; a plain path is taken relative to ``base`` (the
    URDF's directory). Raises :class:`SceneError` naming the places searched when the file
    does not exist.
    """
    if uri.startswith(PACKAGE_SCHEME):
        pkg, _, rel = uri[len(PACKAGE_SCHEME):].partition('/')
        if not pkg or not rel:
            raise SceneError(f'malformed package URI {uri!r}: expected package://PKG/PATH')
        tried = [Path(d) / pkg / rel for d in dirs or []]
        for cand in tried:
            if cand.is_file():
                return cand
        raise SceneError(f'{uri!r} not found; looked in '
                         + (', '.join(map(str, tried)) or 'no package directory'))
    if uri.startswith('file://'):
        path = Path(unquote(urlparse(uri).path))
    elif '://' in uri:
        raise SceneError(f'unsupported mesh URI scheme in {uri!r} (package:// or file://)')
    else:
        path = Path(uri) if base is None or Path(uri).is_absolute() else Path(base) / uri
    if not path.is_file():
        raise SceneError(f'mesh file {str(path)!r} (from {uri!r}) does not exist')
    return path


@dataclass(frozen=True)
class LinkMesh:
    """
    One visual mesh of the robot.

    name   ``<link>_<k>``, the k-th visual of the link (Pinocchio's geometry object name).
    link   the URDF link it is attached to.
    uri    the mesh URI as the URDF writes it (``package://example-robot-data/...``).
    path   the file it resolves to.
    lMm    pose of the mesh in the link frame (the visual's ``<origin>``).
    scale  (3,) mesh scale; ``rgba`` its colour (the URDF material, else grey).
    """

    name: str
    link: str
    uri: str
    path: Path
    lMm: pin.SE3
    scale: np.ndarray
    rgba: tuple

    @property
    def file_uri(self) -> str:
        """
        Give the ``file://`` URI of the resolved file.

        The fallback for a viewer without the package installed on its machine.
        """
        return self.path.resolve().as_uri()


def _floats(text: str | None, n: int, default) -> np.ndarray:
    if text is None:
        return np.array(default, dtype=float)
    try:
        vals = np.array([float(x) for x in text.split()], dtype=float)
    except ValueError:
        vals = np.zeros(0)
    if vals.shape != (n,) or not np.all(np.isfinite(vals)):
        raise SceneError(f'expected {n} finite numbers, got {text!r}')
    return vals


def urdf_meshes(urdf_path: str | os.PathLike, dirs: list[Path] | None = None) -> list[LinkMesh]:
    """
    List every ``<visual>`` mesh of a URDF, in document order, with its URI resolved.

    See :func:`resolve_uri`; ``dirs`` defaults to :func:`package_dirs` of the URI's package.
    Visuals that are not meshes (box, cylinder, sphere) are not part of the list.
    """
    urdf_path = Path(urdf_path)
    try:
        root = ET.parse(urdf_path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise SceneError(f'cannot read URDF {str(urdf_path)!r}: {exc}') from None
    colors = {m.get('name'): m.find('color') for m in root.findall('material')}
    out = []
    for link in root.findall('link'):
        for k, vis in enumerate(link.findall('visual')):
            mesh = vis.find('geometry/mesh')
            if mesh is None or not mesh.get('filename'):
                continue
            uri = mesh.get('filename')
            pkg = uri[len(PACKAGE_SCHEME):].partition('/')[0] \
                if uri.startswith(PACKAGE_SCHEME) else None
            path = resolve_uri(uri, package_dirs(urdf_path, pkg) if dirs is None else dirs,
                               urdf_path.parent)
            origin = vis.find('origin')
            xyz = _floats(origin.get('xyz') if origin is not None else None, 3, [0, 0, 0])
            rpy = _floats(origin.get('rpy') if origin is not None else None, 3, [0, 0, 0])
            mat = vis.find('material')
            color = None
            if mat is not None:
                color = mat.find('color')
                if color is None:
                    color = colors.get(mat.get('name'))
            rgba = tuple(_floats(color.get('rgba'), 4, DEFAULT_RGBA)) if color is not None \
                else DEFAULT_RGBA
            out.append(LinkMesh(f'{link.get("name")}_{k}', link.get('name'), uri, path,
                                pose_from_xyz_rpy(xyz, rpy),
                                _floats(mesh.get('scale'), 3, [1, 1, 1]), rgba))
    return out


@dataclass
class CameraPath:
    """
    The camera centre's path so far, for drawing.

    A point is kept when it is at least ``min_step`` metres from the last one kept; past
    ``max_points`` every other point is dropped (the first and the latest stay), so the
    path stays light however long the run.
    """

    min_step: float = 1e-3
    max_points: int = 2000
    _points: list = field(default_factory=list)

    def __post_init__(self):
        if not (np.isfinite(self.min_step) and self.min_step >= 0):
            raise SceneError(f'min_step must be a finite number >= 0, got {self.min_step}')
        if self.max_points < 2:
            raise SceneError(f'max_points must be >= 2, got {self.max_points}')

    def add(self, p) -> bool:
        """Append a camera centre (world frame); return whether it was kept."""
        p = np.asarray(p, dtype=float).reshape(3)
        if not np.all(np.isfinite(p)):
            raise SceneError(f'camera position must be finite, got {p}')
        if self._points and np.linalg.norm(p - self._points[-1]) < self.min_step:
            return False
        self._points.append(p)
        if len(self._points) > self.max_points:
            self._points = self._points[:-1:2] + [self._points[-1]]
        return True

    def clear(self) -> None:
        self._points = []

    @property
    def points(self) -> np.ndarray:
        """Give the (k, 3) kept camera centres, oldest first."""
        return np.array(self._points).reshape(-1, 3)


@dataclass(frozen=True)
class TargetScene:
    """
    The target as drawn.

    Its pose ``wMo``, radius (or ellipsoid semi-axes ``axes``), the marks' world positions
    and the colours (rgb8) of the body and of each mark.
    """

    wMo: pin.SE3
    radius: float
    axes: np.ndarray | None
    marks: dict
    colors: dict


class Scene:
    """
    The robot, the target and the camera of a run, as plain data for a viewer.

    arm      the :class:`ArmModel` (its URDF, hand-eye transform and target pose ``wMo``).
    target   the target model; ``camera`` the intrinsics the frustum is drawn from.
    cMo_desired  desired pose of the target in the camera (None: no desired camera).
    frustum_depth  depth ``d`` (m) of the frustum's far rectangle.
    """

    def __init__(self, arm: ArmModel, target: Target, camera: CameraIntrinsics,
                 cMo_desired: pin.SE3 | None = None, frustum_depth: float = 0.1,
                 dirs: list[Path] | None = None):
        if not (np.isfinite(frustum_depth) and frustum_depth > 0):
            raise SceneError(f'frustum_depth must be a finite number > 0, got {frustum_depth}')
        self.arm, self.camera, self.frustum_depth = arm, camera, float(frustum_depth)
        self.model = arm.model
        self.data = self.model.createData()
        self.meshes = urdf_meshes(arm.urdf_path, dirs)
        self._frame_ids = []
        for m in self.meshes:
            if not self.model.existFrame(m.link, pin.FrameType.BODY):
                raise SceneError(f'URDF link {m.link!r} has no body frame in the model')
            self._frame_ids.append(self.model.getFrameId(m.link, pin.FrameType.BODY))
        wMo = arm.wMo
        self.target = TargetScene(
            wMo=pin.SE3(wMo), radius=target.radius,
            axes=None if target.axes is None else np.array(target.axes),
            marks={name: wMo.act(oP) for name, oP in target.marks().items()},
            colors={'body': target.colors['body'],
                    **{name: target.colors.get(name, target.colors.get('P2'))
                       for name in target.marks()}})
        self.set_desired(cMo_desired)
        self.cX_frustum = np.vstack([np.zeros(3), self.frustum_depth
                                     * _corner_rays(camera)])

    def set_desired(self, cMo_desired: pin.SE3 | None) -> None:
        """Set the desired camera from the desired target pose ``c*Mo`` (None: no desired)."""
        self.wMc_desired = None if cMo_desired is None else \
            self.target.wMo * cMo_desired.inverse()

    def _q(self, q) -> np.ndarray:
        q = np.asarray(q, dtype=float).ravel()
        if q.shape != (self.model.nq,) or not np.all(np.isfinite(q)):
            raise SceneError(f'joint state must be {self.model.nq} finite numbers, got {q}')
        return q

    def link_poses(self, q) -> list[pin.SE3]:
        """Give the world pose ``wMm`` of each mesh of :attr:`meshes` for joint state ``q``."""
        pin.framesForwardKinematics(self.model, self.data, self._q(q))
        return [self.data.oMf[fid] * m.lMm for fid, m in zip(self._frame_ids, self.meshes)]

    def camera_pose(self, q) -> pin.SE3:
        """Give the camera pose ``wMc`` for joint state ``q``."""
        return self.arm.wMc(self._q(q))

    def frustum(self, wMc: pin.SE3) -> np.ndarray:
        """
        Give the frustum's (5, 3) world points.

        The optical centre, then the image corners (0, 0), (W, 0), (W, H), (0, H) (outer
        pixel edges) at depth :attr:`frustum_depth`; edges in :data:`FRUSTUM_EDGES`.
        """
        return (wMc.rotation @ self.cX_frustum.T).T + wMc.translation

    def markers(self, q, path: np.ndarray | None = None, mesh_uris: str = 'package',
                line_width: float = 0.004) -> list[MarkerSpec]:
        """
        List the scene at joint state ``q`` as viewer markers: :class:`MarkerSpec`.

        Namespaces: ``robot`` (a mesh per link), ``target`` (the body, then the marks),
        ``camera`` (the frustum at ``wMc(q)``), ``camera_path`` (``path``, world points,
        when it has two or more) and ``desired_camera``. ``mesh_uris``: ``'package'`` (the
        URDF's ``package://`` URIs) or ``'file'`` (the fallback, ``file://`` URIs).
        """
        if mesh_uris not in ('package', 'file'):
            raise SceneError(f"mesh_uris must be 'package' or 'file', got {mesh_uris!r}")
        out = [MarkerSpec('robot', i, MarkerKind.MESH_RESOURCE, wMm, tuple(m.scale), m.rgba,
                          mesh_uri=m.uri if mesh_uris == 'package' else m.file_uri)
               for i, (m, wMm) in enumerate(zip(self.meshes, self.link_poses(q)))]
        tg = self.target
        size = 2 * (np.full(3, tg.radius) if tg.axes is None else np.asarray(tg.axes))
        out.append(MarkerSpec('target', 0, MarkerKind.SPHERE, tg.wMo, tuple(size),
                              _rgba(tg.colors['body'])))
        for i, (name, wP) in enumerate(tg.marks.items(), start=1):
            out.append(MarkerSpec('target', i, MarkerKind.SPHERE, pin.SE3(np.eye(3), wP),
                                  (0.3 * tg.radius,) * 3, _rgba(tg.colors[name])))
        edges = self.cX_frustum[np.array(FRUSTUM_EDGES).ravel()]
        width = (line_width, 0.0, 0.0)
        out.append(MarkerSpec('camera', 0, MarkerKind.LINE_LIST, self.camera_pose(q), width,
                              (1.0, 0.55, 0.0, 1.0), edges))
        path = None if path is None else np.asarray(path, dtype=float).reshape(-1, 3)
        if path is not None and len(path) >= 2:
            out.append(MarkerSpec('camera_path', 0, MarkerKind.LINE_STRIP, pin.SE3.Identity(),
                                  width, (1.0, 0.84, 0.0, 1.0), path))
        if self.wMc_desired is not None:
            out.append(MarkerSpec('desired_camera', 0, MarkerKind.LINE_LIST, self.wMc_desired,
                                  width, (0.0, 0.75, 0.0, 1.0), edges))
        return out


def _rgba(rgb8) -> tuple:
    return (*(float(c) / 255.0 for c in rgb8[:3]), 1.0)


def _corner_rays(camera) -> np.ndarray:
    """
    Return the (4, 3) frustum directions of the image corners, as points at depth 1.

    A pinhole's are its corners on the plane z = 1. A wide model's corners may lie beyond
    its field (a fisheye's image circle): each is pulled toward the principal point until
    it lifts, and the unit ray is used (it may point behind the image plane).
    """
    W, H = camera.width, camera.height
    uv = np.array([[0.0, 0.0], [W, 0.0], [W, H], [0.0, H]]) - 0.5  # pixel edges
    if hasattr(camera, 'pixel_to_normalized'):  # a pinhole (plumb_bob undistorted)
        return np.hstack([camera.pixel_to_normalized(uv), np.ones((4, 1))])
    centre = np.array([camera.u0, camera.v0])
    rays = np.empty((4, 3))
    for i, corner in enumerate(uv):
        for f in np.linspace(1.0, 0.0, 41):
            q, ok = camera.lift_where((centre + f * (corner - centre))[None])
            if ok[0]:
                break
        rays[i] = q[0] if ok[0] else (0.0, 0.0, 1.0)
    return rays
