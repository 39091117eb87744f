"""
The 3-D scene as ``visualization_msgs/MarkerArray``, for RViz and Foxglove (no TF needed).

Each array is the whole scene (:meth:`sphere_servo.sim.scene.Scene.markers`, frame
``world``): first a ``DELETEALL`` marker, then every marker of the scene with ``ADD``, so a
viewer that gets only the latest array (a late subscriber of the latched topic, Foxglove
seeking in a bag) shows the whole scene, and a marker that left the scene (the camera path
after a jump) leaves the viewer too. A ``MESH_RESOURCE`` marker carries only its URI
(viewers load and cache the mesh), so re-sending the robot costs a few hundred bytes.

A marker whose pose, scale, colour or points are not finite (or whose rotation has no
quaternion) is left out of the array: a viewer is never sent a NaN pose (RViz drops such
a marker with an error; the scene's core refuses the joint states that would make one).
"""
from __future__ import annotations

from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point, Vector3
import numpy as np
from sphere_servo.ros.conversions import pose_from_se3
from sphere_servo.ros.qos import LATCHED
from sphere_servo.sim.scene import MarkerKind, MarkerSpec
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

WORLD_FRAME = 'world'
# latched: the last scene reaches a viewer that subscribes later (RViz: Durability Policy
# "Transient Local"; ``ros2 topic echo --qos-durability transient_local``)
MARKERS_QOS = LATCHED


def finite_spec(spec: MarkerSpec) -> bool:
    """Tell whether every number of a marker is finite and its rotation has a quaternion."""
    M = np.asarray(spec.pose.homogeneous, dtype=float)
    parts = [M, np.asarray(spec.scale, dtype=float), np.asarray(spec.rgba, dtype=float)]
    if spec.points is not None:
        parts.append(np.asarray(spec.points, dtype=float))
    if not all(np.all(np.isfinite(p)) for p in parts):
        return False
    R = M[:3, :3]
    return bool(np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0)


def marker_msg(spec: MarkerSpec, header: Header) -> Marker:
    """Build the ``ADD`` marker of one :class:`MarkerSpec` (lifetime 0: until replaced)."""
    r, g, b, a = (float(c) for c in spec.rgba)
    m = Marker(header=header, ns=spec.ns, id=int(spec.id), type=int(spec.kind),
               action=Marker.ADD, pose=pose_from_se3(spec.pose),
               scale=Vector3(x=float(spec.scale[0]), y=float(spec.scale[1]),
                             z=float(spec.scale[2])),
               color=ColorRGBA(r=r, g=g, b=b, a=a), lifetime=Duration(), frame_locked=False)
    if spec.points is not None:
        m.points = [Point(x=x, y=y, z=z) for x, y, z in spec.points.tolist()]
    if spec.kind == MarkerKind.MESH_RESOURCE:
        m.mesh_resource = spec.mesh_uri
        m.mesh_use_embedded_materials = True  # tinted by the URDF's colour
    return m


def marker_array(specs: list[MarkerSpec], header: Header) -> MarkerArray:
    """
    Build the scene's array: ``DELETEALL``, then every marker (module docstring).

    A marker that is not :func:`finite_spec` is left out.
    """
    return MarkerArray(markers=[Marker(header=header, action=Marker.DELETEALL)]
                       + [marker_msg(s, header) for s in specs if finite_spec(s)])
