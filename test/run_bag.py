"""
Record a headless UR5 servo run as a rosbag2, with the topics as the nodes publish them.

No DDS: the loop below is what ``arm_sim``, ``detector``, ``features`` and ``servo`` do in
lockstep (the project's ArmModel, Renderer, Detector, feature set and VectorController, and
the nodes' own message codecs), written message by message with ``rosbags``. The scene is
``config/arm_sim.yaml``'s: the arm at the desired pose is taught (two frames, the first
re-published once with the same stamp, as the lockstep arm_sim does while idle), the arm
jumps to the start pose, one frame with the servo still disabled, then the servo runs until
it converges, plus a few converged frames.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class RecordedRun:
    """What the test run recorded: the bag and what the loop knows about it."""

    bag: Path
    iterations: int         # images the enabled servo answered (servoing or converged)
    images: int             # distinct image stamps in the bag
    taught_stamp: int       # ns
    desired_meas: dict      # the taught image's measurement values
    frames_q: list          # joint positions of the servo's frames, in order


_DTYPES = {'double': np.float64, 'float': np.float32, 'uint8': np.uint8, 'octet': np.uint8,
           'int8': np.int8, 'uint16': np.uint16, 'int16': np.int16, 'uint32': np.uint32,
           'int32': np.int32, 'uint64': np.uint64, 'int64': np.int64}


def to_rosbags(msg):
    """
    Convert an rclpy message into the rosbags dataclass of the same type.

    The bag is then serialized by rosbags: rclpy's ``serialize_message`` (the PyPI build)
    can leave trailing bytes that rosbags' reader refuses.
    """
    from sphere_servo.bag.bagio import typestore
    pkg = type(msg).__module__.split('.')[0]
    cls = typestore().types[f'{pkg}/msg/{type(msg).__name__}']
    kw = {}
    for name, ftype in msg.get_fields_and_field_types().items():
        val = getattr(msg, name)
        elem = ftype.split('<')[-1].rstrip('>').split('[')[0]
        if hasattr(val, 'get_fields_and_field_types'):
            kw[name] = to_rosbags(val)
        elif isinstance(val, bytes) and len(val) == 1 and '<' not in ftype:
            kw[name] = val[0]  # a byte scalar (DiagnosticStatus.level)
        elif elem in _DTYPES and not isinstance(val, (int, float, bool)):
            kw[name] = np.asarray(val, dtype=_DTYPES[elem])
        elif isinstance(val, (list, tuple)) and val and \
                hasattr(val[0], 'get_fields_and_field_types'):
            kw[name] = [to_rosbags(v) for v in val]
        else:
            kw[name] = list(val) if isinstance(val, tuple) else val
    return cls(**kw)


def _arm_scene():
    from sphere_servo.core.camera import CameraIntrinsics
    from sphere_servo.core.targets import special_sphere
    from sphere_servo.sim.arm import ArmModel, pose_from_xyz_rpy
    arm = ArmModel(tool0Mc=pose_from_xyz_rpy([0.0, -0.04, 0.02], [0, 0, 0]),
                   wMo=pose_from_xyz_rpy([0.5, 0.1, 0.05], [np.pi, 0.0, -np.pi / 2]),
                   q0=[0.0, -1.57, 1.57, -1.57, -1.57, 0.0], velocity_scale=0.5,
                   cmd_timeout=1.0)
    return arm, special_sphere(), CameraIntrinsics()


def record_run(path: Path, gain: float = 1.0, max_iter: int = 400,
               with_features: bool = True) -> RecordedRun:
    """Run the loop and write its bag to ``path`` (which must not exist)."""
    from builtin_interfaces.msg import Time
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PoseStamped, TwistStamped
    from rosbags.rosbag2 import StoragePlugin, Writer
    from sensor_msgs.msg import JointState

    from sphere_servo.bag.bagio import typestore
    from sphere_servo.core.control import VectorController
    from sphere_servo.core.features import make_feature_set
    from sphere_servo.ros.conversions import (camera_info_from_intrinsics, header,
                                              image_from_array, pose_from_se3,
                                              twist_from_array)
    from sphere_servo.ros.vectors import features_msg, measurement_msg, measurement_values
    from sphere_servo.sim.arm import pose_from_xyz_rpy
    from sphere_servo.vision.detector import Detector
    from sphere_servo.vision.renderer import Renderer

    arm, target, cam = _arm_scene()
    renderer, detector = Renderer(cam, target), Detector.for_target(target)
    q_des, ok, _ = arm.ik_for_cMo(pose_from_xyz_rpy([0, 0, 0.45], [0, 0, 0]))
    assert ok
    q_start, ok, _ = arm.ik_for_cMo(pose_from_xyz_rpy([0.07, 0.12, 0.56], [-0.46, 0.40, -0.72]),
                                    q_des)
    assert ok
    law = VectorController('s_n', target.radius, gain=gain, v_max=0.25, w_max=1.5, tol=5e-4)
    topics = {
        '/camera/image_raw': 'sensor_msgs/msg/Image',
        '/camera/camera_info': 'sensor_msgs/msg/CameraInfo',
        '/detector/measurement': 'sensor_msgs/msg/JointState',
        '/joint_states': 'sensor_msgs/msg/JointState',
        '/ground_truth/camera_pose': 'geometry_msgs/msg/PoseStamped',
        '/servo/state': 'diagnostic_msgs/msg/DiagnosticStatus',
        '/camera/cmd_vel_stamped': 'geometry_msgs/msg/TwistStamped',
    }
    if with_features:
        topics['/features/s_n'] = 'sensor_msgs/msg/JointState'
    dt, t = 1.0 / 30.0, 1.0
    fs = None
    out = RecordedRun(Path(path), 0, 0, 0, {}, [])
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {tp: w.add_connection(tp, ty, typestore=typestore())
                 for tp, ty in topics.items()}
        bag_ns = [1_000_000_000]

        def put(topic, msg):
            bag_ns[0] += 1000
            if topic in conns:
                w.write(conns[topic], bag_ns[0],
                        bytes(typestore().serialize_cdr(to_rosbags(msg), topics[topic])))

        def frame(state: str | None, repeat: int = 1):
            """One lockstep period: what arm_sim, detector, features, servo publish."""
            nonlocal fs
            hdr = header(t, 'camera_optical_frame')
            img = renderer.render(arm.cMo())
            det = detector.detect(img, 'rgb8', cam)
            meas = measurement_msg(det, hdr)
            for _ in range(repeat):
                put('/camera/camera_info', camera_info_from_intrinsics(cam, hdr))
                put('/joint_states', JointState(header=header(t, ''), name=arm.joint_names,
                                                position=arm.q.tolist(),
                                                velocity=arm.qdot.tolist()))
                put('/ground_truth/camera_pose', PoseStamped(
                    header=header(t, 'target'), pose=pose_from_se3(arm.oMc())))
                put('/camera/image_raw', image_from_array(img, hdr))
            put('/detector/measurement', meas)
            out.images += 1
            obs = det.to_observation(target.kind)
            if fs is None:
                return meas, obs, np.zeros(6)
            s = fs.features(obs)
            put('/features/s_n', features_msg('s_n', hdr, s, fs.desired))
            v = np.zeros(6)
            vals = {}
            if state == 'servoing':
                res = law.compute(s, fs.desired)
                state = 'converged' if res.converged else 'servoing'
                v = np.zeros(6) if res.converged else res.v_c
                vals = {'error_norm': f'{res.error_norm:.6g}'}
                out.iterations += 1
                out.frames_q.append(arm.q.copy())
            put('/camera/cmd_vel_stamped', TwistStamped(header=hdr, twist=twist_from_array(v)))
            stamp = Time(sec=hdr.stamp.sec, nanosec=hdr.stamp.nanosec)
            vals['stamp'] = f'{stamp.sec}.{stamp.nanosec:09d}'
            put('/servo/state', DiagnosticStatus(
                name='servo', message=state,
                values=[KeyValue(key=k, value=str(x)) for k, x in vals.items()]))
            return meas, obs, v

        arm.set_q(q_des)
        meas, obs, _ = frame(None, repeat=2)       # the taught image, re-published once
        out.taught_stamp = int(round(t * 1e9))
        out.desired_meas = measurement_values(meas)
        fs = make_feature_set('s_n', obs)
        t += dt
        frame('disabled')                          # still at the desired pose
        arm.set_q(q_start)
        t += dt
        frame('disabled')                          # at the start, not enabled yet
        converged_frames = 0
        for _ in range(max_iter):
            t += dt
            _, _, v = frame('servoing')
            if not np.any(v):
                converged_frames += 1
                if converged_frames == 3:
                    break
            arm.command(v)
            arm.step(dt)
    return out


def run_bag(tmp_root: Path, name: str = 'run', **kw) -> RecordedRun:
    """:func:`record_run` into ``tmp_root/name/bag`` once per test session (cached)."""
    key = (str(tmp_root), name, tuple(sorted(kw.items())))
    if key not in _CACHE:
        d = Path(tmp_root) / name
        d.mkdir(parents=True, exist_ok=True)
        _CACHE[key] = record_run(d / 'bag', **kw)
    return _CACHE[key]


_CACHE: dict = {}
