"""
Record a servo run as a rosbag2 without DDS: the nodes' cores in lockstep, their messages.

The loop below is what ``arm_sim``, ``detector``, ``features`` and ``servo`` do in the
``special_sphere`` scenario (its params files), with the same cores
(:mod:`sphere_servo.pipeline`) and the nodes' own message codecs, in the order of the
launcher's teach sequence: the first frame (re-published once with the same stamp, as the
idle lockstep arm_sim does), the jump to the desired pose, the teach, the jump to the start
pose, then the enabled servo until it converges, plus a few converged frames. Messages are
serialized to exact CDR by :func:`sphere_servo.bag.compare.cdr` and written with rosbags.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

TOPICS = {
    '/camera/image_raw': 'sensor_msgs/msg/Image',
    '/camera/camera_info': 'sensor_msgs/msg/CameraInfo',
    '/joint_states': 'sensor_msgs/msg/JointState',
    '/ground_truth/camera_pose': 'geometry_msgs/msg/PoseStamped',
    '/arm_sim/state': 'diagnostic_msgs/msg/DiagnosticArray',
    '/arm_sim/markers': 'visualization_msgs/msg/MarkerArray',
    '/detector/measurement': 'sensor_msgs/msg/JointState',
    '/features/s_n': 'sensor_msgs/msg/JointState',
    '/features/s_n/desired': 'sensor_msgs/msg/JointState',
    '/camera/cmd_vel': 'geometry_msgs/msg/TwistStamped',
    '/servo/state': 'diagnostic_msgs/msg/DiagnosticArray',
}


@dataclass
class RecordedRun:
    """What the recorded run was, as the loop knows it (not read back from the bag)."""

    bag: Path
    iterations: int = 0          # images the enabled servo answered
    images: int = 0              # distinct image stamps in the bag
    taught_stamp: int = 0        # ns
    desired_meas: dict = field(default_factory=dict)  # the taught image's measurement
    frames_q: list = field(default_factory=list)      # joint positions of the servo's frames
    markers: int = 0             # MarkerArray messages


def _state(status, name: str, hardware_id: str, hdr):
    from diagnostic_msgs.msg import DiagnosticArray
    from sphere_servo.ros.diagnostics import diagnostic_status
    return DiagnosticArray(header=hdr, status=[diagnostic_status(status, name, hardware_id)])


def record_run(path: Path, gain: float | None = None, max_iter: int = 400,
               with_features: bool = True) -> RecordedRun:
    """
    Run the loop and write its bag to ``path`` (which must not exist).

    ``gain``: the servo's gain (the scenario's when None); ``with_features`` False leaves
    ``features/s_n`` and its desired out of the bag.
    """
    from geometry_msgs.msg import PoseStamped, TwistStamped
    from rosbags.rosbag2 import StoragePlugin, Writer
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Header

    from sphere_servo.bag.bagio import typestore
    from sphere_servo.bag.compare import cdr
    from sphere_servo.pipeline.arm_sim import ArmSimCore
    from sphere_servo.pipeline.config import load_node_params, section
    from sphere_servo.pipeline.detector import DetectorCore
    from sphere_servo.pipeline.features import FeaturesCore
    from sphere_servo.pipeline.params import (ArmSimParams, DetectorParams, FeaturesParams,
                                              ServoParams)
    from sphere_servo.pipeline.servo import ServoCommand, ServoCore
    from sphere_servo.ros.conversions import (camera_info_from_intrinsics, image_from_array,
                                              pose_from_se3, stamp_from_ns, twist_from_array)
    from sphere_servo.ros.markers import marker_array, WORLD_FRAME
    from sphere_servo.ros.vectors import features_msg, measurement_msg
    from sphere_servo.sim.arm import CAMERA_FRAME

    params = load_node_params('special_sphere')
    sim = ArmSimCore(ArmSimParams.from_mapping(section(params, 'arm_sim')))
    assert sim.lockstep
    detector = DetectorCore(DetectorParams.from_mapping(section(params, 'detector')))
    features = FeaturesCore(FeaturesParams.from_mapping(section(params, 'features')))
    servo_p = section(params, 'servo')
    servo = ServoCore(ServoParams.from_mapping(
        servo_p if gain is None else {**servo_p, 'gain': gain}))
    topics = {t: ty for t, ty in TOPICS.items()
              if with_features or not t.startswith('/features/')}
    out = RecordedRun(Path(path))
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {t: w.add_connection(t, ty, typestore=typestore()) for t, ty in topics.items()}
        clock = {'ns': 0}

        def put(topic, msg):
            """Write ``msg`` on ``topic`` (bag time: the sim time plus 1 µs per message)."""
            if topic in conns:
                clock['ns'] += 1000
                w.write(conns[topic], clock['ns'], cdr(msg, topics[topic]))

        def publish_sim(f, repeat: int = 1) -> Header:
            """Publish what arm_sim does for one frame, ``repeat`` times (re-publications)."""
            clock['ns'] = max(clock['ns'], f.stamp_ns)
            stamp = stamp_from_ns(f.stamp_ns)
            hdr = Header(stamp=stamp, frame_id=CAMERA_FRAME)
            for _ in range(repeat):
                put('/camera/camera_info', camera_info_from_intrinsics(sim.camera, hdr))
                put('/joint_states', JointState(header=Header(stamp=stamp),
                                                name=list(f.joint_names),
                                                position=f.q.tolist(), velocity=f.qdot.tolist()))
                put('/ground_truth/camera_pose', PoseStamped(
                    header=Header(stamp=stamp, frame_id='target'), pose=pose_from_se3(f.oMc)))
                put('/arm_sim/state', _state(f.status(), 'arm_sim: state', 'ur5', hdr))
                put('/camera/image_raw', image_from_array(f.image, hdr))
            markers = sim.markers(f)  # latched: not re-published
            if markers is not None:
                put('/arm_sim/markers', marker_array(markers, Header(stamp=stamp,
                                                                     frame_id=WORLD_FRAME)))
                out.markers += 1
            stamps.add(f.stamp_ns)
            return hdr

        def pipeline(f, hdr: Header, repeat: int = 1) -> ServoCommand | None:
            """Publish what detector, features and servo do for one frame, per delivery."""
            info = camera_info_from_intrinsics(sim.camera, hdr)
            detector.on_camera_info(info.width, info.height, info.k, info.d)
            img = image_from_array(f.image, hdr)
            cmd = None
            for _ in range(repeat):
                meas = detector.on_image(img.height, img.width, img.step, img.encoding,
                                         img.data).measurement
                put('/detector/measurement', measurement_msg(meas, hdr))
                fo = features.on_measurement(f.stamp_ns, meas)
                if fo is None:
                    continue  # no desired yet: no features, nothing for the servo
                fs = fo.values.get(servo.feature_set)
                s = None if fs is None else fs.s
                put('/features/s_n', features_msg('s_n', hdr, s))
                ans = servo.on_features(f.stamp_ns, s, f.stamp_ns, 0.0)
                if isinstance(ans, ServoCommand):  # else: a repeat of the last image
                    put('/camera/cmd_vel', TwistStamped(header=hdr,
                                                        twist=twist_from_array(ans.twist)))
                    put('/servo/state', _state(ans.status(0), 'servo: state', 'camera', hdr))
                    cmd = ans
            return cmd

        def jump(which: str):
            j = sim.go(which)
            assert j.success, j.message
            return j.frame

        stamps: set[int] = set()
        f = sim.frame()
        assert pipeline(f, publish_sim(f, repeat=2), repeat=2) is None  # idle: no desired
        f = jump('desired')
        hdr = publish_sim(f)
        pipeline(f, hdr)
        taught = features.teach()
        assert taught.success, taught.message
        out.taught_stamp = f.stamp_ns
        out.desired_meas = detector.last.measurement.as_dict()
        s_star = features.desired_features()[servo.feature_set]
        put('/features/s_n/desired', features_msg('s_n', hdr, s_star))
        assert servo.set_desired(s_star, out.taught_stamp) is None
        # the idle re-publication of the taught image: now features, the disabled servo answers
        cmd = pipeline(f, publish_sim(f))
        f = sim.on_command(cmd.twist).frame
        cmd = pipeline(f, publish_sim(f))
        f = jump('start')
        cmd = pipeline(f, publish_sim(f))                 # at the start, not enabled yet
        assert not servo.enabled and cmd.twist.tolist() == [0.0] * 6
        f = sim.on_command(cmd.twist).frame
        servo.enable(True)
        converged = 0
        for _ in range(max_iter):
            cmd = pipeline(f, publish_sim(f))
            out.frames_q.append(f.q.copy())
            if cmd.converged:
                converged += 1
                if converged == 3:
                    break
            f = sim.on_command(cmd.twist).frame
        else:
            raise AssertionError(f'the servo did not converge in {max_iter} iterations')
        out.iterations = servo.iteration
        out.images = len(stamps)
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
