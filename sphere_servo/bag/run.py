"""
A recorded run, read back from its rosbag2: what the video and the 3-D replay show.

Everything is keyed by the *image stamp* (the header every message derived from an image
carries), so the topics line up whatever order the recorder got them in. Read:
``camera/camera_info`` (the first one), ``detector/measurement``, ``features/<set>`` and
``features/<set>/desired``, ``camera/cmd_vel`` (TwistStamped; the watchdog's zero-stamped
twists answer no image and are left out), ``servo/state`` (DiagnosticArray),
``joint_states`` and ``ground_truth/camera_pose``; the images themselves are streamed later
(:func:`iter_frames`), one pass, never all in memory.

The frames of a run (:attr:`Run.frames`): one per servo iteration, every image the servo
answered while enabled (its ``servo/state``, stamped as the image, says ``servoing``,
``converged``, ``target lost`` or ``no desired``: the images its ``iteration`` counts), or,
in a bag without servo states (or with ``every_image``), every image of the bag. A
re-published image (the lockstep arm_sim's idle re-publication: the same stamp) counts once.
The error norm of a frame is the servo's own (its state's ``error_norm``).

The desired measurement (:attr:`Run.desired`): the recorded ``detector/measurement`` of the
image the run taught last, found from the recorded ``features/<set>/desired`` messages
(:func:`sphere_servo.bag.desired.auto_desired`: their header is the taught image's); in a
bag without them, the last image the servo called converged; else none (the video then
says so).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
from pathlib import Path
import sys

import numpy as np
import pinocchio as pin

from sphere_servo.bag.bagio import (bag, BagError, decode_image, image_connections, iter_raw,
                                    on_topics, topic_name)
from sphere_servo.bag.desired import auto_desired
from sphere_servo.bag.offline import (desired_topic, features_topic, Frame, header_ns,
                                      IMAGE_TOPIC, INFO_TOPIC, JOINT_STATE, MEAS_TOPIC,
                                      Pipeline, recorded_types, Settings, STATE_TOPIC,
                                      TOPIC_TYPES, TWIST_TOPIC)
from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import camera_info_reduction, reduced_camera
from sphere_servo.core.features import FEATURE_SETS
from sphere_servo.pipeline.arm_sim import sim_scene
from sphere_servo.pipeline.common import stamp_text
from sphere_servo.pipeline.config import load_node_params, section
from sphere_servo.pipeline.detector import binning_roi
from sphere_servo.pipeline.params import ArmSimParams
from sphere_servo.pipeline.servo import ServoState
from sphere_servo.pipeline.vectors import Measurement
from sphere_servo.sim.scene import Scene

POSE_TOPIC, JOINTS_TOPIC = '/ground_truth/camera_pose', '/joint_states'
RUN_TYPES = {**TOPIC_TYPES, POSE_TOPIC: 'geometry_msgs/msg/PoseStamped',
             JOINTS_TOPIC: JOINT_STATE}
#: the servo's states of an iteration: it answered an image while enabled
ITERATION_STATES = tuple(s.value for s in (ServoState.SERVOING, ServoState.CONVERGED,
                                           ServoState.TARGET_LOST, ServoState.NO_DESIRED))
POSE_TOL = 1e-6   # m / rad: a bag's ground truth against the arm of the scene


@dataclass
class Desired:
    """The desired measurement drawn as the goal: its values, image stamp and origin."""

    values: dict
    stamp: int
    how: str      # 'taught' or 'last converged'
    note: str = ''


@dataclass
class Run:
    """
    The histories of one recorded run, by image stamp (ns).

    frames     image stamps the video and the replay show, in time order.
    camera     intrinsics of the recorded images: the first camera_info's, reduced by its
               binning and roi (None if the bag has none, or it is unusable).
    meas       recorded measurement values by stamp ({} when the sphere was not detected).
    error_norm the servo's ‖s − s*‖₂ of ``feature_set``; ``twists`` its twist (v, ω).
    states     the servo's state text; ``iterations`` its iteration count (its last state's).
    joints     joint positions by stamp (``joint_names`` order); ``oMc`` ground-truth poses.
    warnings   what the bag reader left out or found inconsistent (for the user to see).
    """

    path: Path
    frames: list
    camera: CameraIntrinsics | None = None
    meas: dict = field(default_factory=dict)
    feature_set: str = 's_n'
    error_norm: dict = field(default_factory=dict)
    twists: dict = field(default_factory=dict)
    states: dict = field(default_factory=dict)
    iterations: int | None = None
    joints: dict = field(default_factory=dict)
    joint_names: list = field(default_factory=list)
    oMc: dict = field(default_factory=dict)
    desired: Desired | None = None
    image_topic: str = IMAGE_TOPIC
    warnings: list = field(default_factory=list)

    def t(self, stamp: int) -> float:
        """Return the seconds from the first frame to the image stamped ``stamp``."""
        return (stamp - self.frames[0]) * 1e-9

    def series(self, table: dict, width: int) -> np.ndarray:
        """Return (len(frames), width) the values of ``table`` at each frame, NaN if none."""
        out = np.full((len(self.frames), width), np.nan)
        for k, st in enumerate(self.frames):
            if st in table:
                out[k] = table[st]
        return out

    def frame_rate(self) -> float:
        """Return the camera's rate: 1 / the median step between frames (30 Hz if unknown)."""
        if len(self.frames) < 2:
            return 30.0
        dt = float(np.median(np.diff(self.frames))) * 1e-9
        return 1.0 / dt if dt > 0 else 30.0


def output_path(bag_path, given: str | None, name: str) -> Path:
    """Return the output file: ``given``, else ``name`` beside the bag (in the run's folder)."""
    return Path(given) if given else Path(bag_path).resolve().parent / name


def print_warnings(prog: str, run: Run) -> None:
    """Print the bag reader's warnings of a run on stderr, one line each."""
    for w in run.warnings:
        print(f'{prog}: warning: {w}', file=sys.stderr, flush=True)


def cli_error(prog: str, err: BaseException) -> int:
    """Print why a command line tool did nothing, on one line of stderr; return exit code 1."""
    print(f'{prog}: error: {" ".join(str(err).split())}', file=sys.stderr)
    return 1


def _twist(msg) -> np.ndarray:
    t = msg.twist
    return np.array([t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y,
                     t.angular.z])


def _pose(msg) -> pin.SE3:
    p, o = msg.pose.position, msg.pose.orientation
    return pin.XYZQUATToSE3(np.array([p.x, p.y, p.z, o.x, o.y, o.z, o.w]))


def header_stamp(raw: bytes) -> int:
    """Return the header stamp (ns) of serialized CDR whose first field is a Header."""
    # 4-byte encapsulation header, then int32 sec and uint32 nanosec (CDR_LE or CDR_BE)
    if len(raw) < 12 or raw[1] not in (0, 1):
        raise BagError('an image message is too short or not CDR')
    order = 'little' if raw[1] == 1 else 'big'
    sec = int.from_bytes(raw[4:8], order, signed=True)
    return sec * 1_000_000_000 + int.from_bytes(raw[8:12], order)


def read_run(path, settings: Settings | None = None, image_topic: str = IMAGE_TOPIC,
             every_image: bool = False) -> Run:
    """
    Read the run recorded in the bag at ``path``.

    ``settings`` (the nodes' parameters, :func:`sphere_servo.bag.offline.load_settings`)
    give the target kind and the servo's feature set; the nodes' defaults when None.
    ``image_topic`` holds ``sensor_msgs/msg/Image`` or ``CompressedImage`` (only their
    headers are read here). Raises :class:`~sphere_servo.bag.bagio.BagError` when the bag
    cannot be read or has no image on ``image_topic`` (not in the bag: the message names
    ``image_topic/compressed`` if the bag has it; of another type).
    """
    settings = settings or Settings.from_params()
    image_topic = topic_name(image_topic)
    wanted = {INFO_TOPIC, MEAS_TOPIC, TWIST_TOPIC, STATE_TOPIC, POSE_TOPIC, JOINTS_TOPIC,
              *map(features_topic, FEATURE_SETS), *map(desired_topic, FEATURE_SETS)}
    msgs: dict[str, list] = {t: [] for t in wanted}
    images: list[tuple[int, int]] = []   # (bag ns, stamp), bag order
    with bag(path) as reader:
        warnings = list(reader.warnings)  # e.g. messages it does not read
        try:
            image_conns = image_connections(reader, image_topic)
        except BagError as err:
            raise BagError(f'{path}: no images: {err}') from None
        conns = recorded_types(on_topics(reader, wanted), RUN_TYPES)
        for conn, ts, raw in iter_raw(reader, conns + image_conns):
            topic = topic_name(conn.topic)
            if topic == image_topic:
                images.append((ts, header_stamp(raw)))  # decode only the header
                continue
            if topic == INFO_TOPIC and msgs[INFO_TOPIC]:
                continue  # the intrinsics do not change in a run
            try:
                msgs[topic].append((ts, reader.deserialize(raw, conn.msgtype)))
            except Exception as err:  # rosbags raises several types; all mean "corrupt"
                raise BagError(f'cannot decode a message on {conn.topic}: {err}') from None
    if not images:
        raise BagError(f'{path}: no images: topic {image_topic} has no message')
    run = Run(Path(path), [], feature_set=settings.servo.feature_set, image_topic=image_topic,
              warnings=warnings)
    if msgs[INFO_TOPIC]:
        info = msgs[INFO_TOPIC][0][1]
        try:
            run.camera = reduced_camera(
                CameraIntrinsics.from_camera_info_fields(info.width, info.height, info.k,
                                                         info.d),
                camera_info_reduction(info.width, info.height, **binning_roi(info)))
        except ValueError:
            run.camera = None
    run.meas = {header_ns(m.header): dict(zip(m.name, m.position))
                for _, m in msgs[MEAS_TOPIC] if len(m.name) == len(m.position)}
    run.twists = {header_ns(m.header): _twist(m) for _, m in msgs[TWIST_TOPIC]
                  if header_ns(m.header)}
    for _, m in msgs[STATE_TOPIC]:
        st = header_ns(m.header)
        if not st or not len(m.status):
            continue  # the watchdog's states answer no image
        values = {kv.key: kv.value for kv in m.status[0].values}
        run.states[st] = m.status[0].message
        if 'error_norm' in values:
            try:
                norm = float(values['error_norm'])
            except ValueError:
                norm = math.nan
            if not (math.isfinite(norm) and norm >= 0.0):
                raise BagError(f'{path}: /servo/state at {st} ns has error_norm '
                               f'{values["error_norm"]!r}, not a norm')
            run.error_norm[st] = norm
        if values.get('iteration', '').isdigit():
            run.iterations = int(values['iteration'])
    for _, m in msgs[JOINTS_TOPIC]:
        names, q = list(m.name), np.asarray(m.position, float)
        if not run.joint_names:
            run.joint_names = names
        elif names != run.joint_names:
            # a JointState is a named vector: its positions in the first message's order
            if sorted(names) != sorted(run.joint_names) or len(names) != len(q):
                raise BagError(f'{path}: joint_states at {header_ns(m.header)} ns name '
                               f'{names}, the first ones {run.joint_names}')
            q = q[[names.index(n) for n in run.joint_names]]
        run.joints[header_ns(m.header)] = q
    run.oMc = {header_ns(m.header): _pose(m) for _, m in msgs[POSE_TOPIC]}
    stamps = list(dict.fromkeys(st for _, st in images))  # re-publications once
    enabled = {st for st, msg in run.states.items() if msg in ITERATION_STATES}
    run.frames = sorted(stamps if every_image or not enabled
                        else [st for st in stamps if st in enabled])
    if not run.frames:
        raise BagError(f'{path}: no image of the servo run (no image the servo answered '
                       'while enabled is in the bag)')
    run.desired = _desired(run, settings, images, msgs)
    return run


def _desired(run: Run, settings: Settings, images, msgs) -> Desired | None:
    """See the module docstring: the image taught last, else the last converged one."""
    by_stamp = {header_ns(m.header): m for _, m in msgs[MEAS_TOPIC]}
    frames = [Frame(i, ts, st, by_stamp[st].header,
                    Measurement.of(by_stamp[st].name, by_stamp[st].position))
              for i, (ts, st) in enumerate(images) if st in by_stamp]
    features = {n: msgs[features_topic(n)] for n in FEATURE_SETS}
    desireds = {n: msgs[desired_topic(n)] for n in FEATURE_SETS}
    if not frames:
        note = 'the bag has no measurements to find the taught image'
    elif not any(desireds.values()):
        note = 'the bag has no features/<set>/desired messages to find the taught image'
    else:
        try:
            found = auto_desired(Pipeline(settings), frames, features, desireds)
        except BagError as err:
            note = f'no taught image found ({err})'
        else:
            d = found[-1].frame  # the desired in force at the end of the run
            return Desired(d.meas.as_dict(), d.stamp, 'taught', found[-1].note)
    converged = [st for st in run.frames if run.states.get(st) == ServoState.CONVERGED.value
                 and run.meas.get(st)]
    if converged:
        return Desired(run.meas[converged[-1]], converged[-1], 'last converged',
                       f'{note}; the last image the servo called converged')
    return None


def iter_frames(run: Run):
    """
    Yield ``(k, stamp, H×W×3 rgb8 image)`` for each frame of the run, in frame order.

    One pass over the bag; an image recorded out of stamp order waits until the frames
    before it are out. A CompressedImage is decoded in the colour order its format names
    (:func:`~sphere_servo.bag.bagio.decode_image`). An image that cannot be read (a bad
    buffer, corrupt or truncated compressed bytes, compressedDepth) or is not 8-bit
    (mono16, 32FC1) is a BagError: the video has no frame for it.
    """
    index = {st: k for k, st in enumerate(run.frames)}
    pending: dict[int, tuple] = {}
    nxt = 0
    with bag(run.path) as reader:
        for conn, _, raw in iter_raw(reader, on_topics(reader, [run.image_topic])):
            k = index.get(header_stamp(raw))
            if k is None or k < nxt or k in pending:
                continue  # not a frame, or a re-publication of one
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as err:  # rosbags raises several types; all mean "corrupt"
                raise BagError(f'cannot decode an image on {conn.topic}: {err}') from None
            try:
                img, encoding = decode_image(msg)
            except BagError as err:  # the video has no frame for it: say which image
                raise BagError(f'the image stamped {stamp_text(run.frames[k])} s on '
                               f'{conn.topic} cannot be read: {err}') from None
            if img.dtype != np.uint8:
                raise BagError(f'images on {conn.topic} are {encoding}: an 8-bit '
                               'encoding is needed')
            if encoding in ('bgr8', 'bgra8'):
                img = img[..., 2::-1]
            elif img.ndim == 2:
                img = np.repeat(img[..., None], 3, axis=2)
            pending[k] = (run.frames[k], np.ascontiguousarray(img[..., :3]))
            while nxt in pending:
                yield (nxt, *pending.pop(nxt))
                nxt += 1


def load_arm_params(spec: str | None) -> ArmSimParams:
    """Return the ``arm_sim`` parameters of a scenario or params file (the defaults if None)."""
    return ArmSimParams.from_mapping(section(load_node_params(spec), 'arm_sim') if spec
                                     else {})


def run_scene(run: Run, p: ArmSimParams) -> Scene:
    """
    Return the :class:`Scene` of a run recorded with the ``arm_sim`` parameters ``p``.

    The desired camera is the taught image's ground-truth pose, else ``p.desired_cMo``.
    Raises :class:`BagError` when the bag has no joint states, or its ground truth and the
    arm of ``p`` disagree by more than :data:`POSE_TOL` (another scene recorded it).
    """
    scene = sim_scene(p)
    if run.desired is not None and run.desired.stamp in run.oMc:
        scene.set_desired(run.oMc[run.desired.stamp].inverse())
    arm = scene.arm
    if not run.joints:
        raise BagError(f'{run.path}: no joint_states in the bag: nothing to replay')
    if run.joint_names and run.joint_names != arm.joint_names:
        raise BagError(f'{run.path}: joint_states name {run.joint_names}, the UR5 model has '
                       f'{arm.joint_names}')
    worst = 0.0
    for st, q in run.joints.items():
        if st in run.oMc:
            err = pin.log6((arm.wMo * run.oMc[st]).inverse() * scene.camera_pose(q)).vector
            worst = max(worst, float(np.max(np.abs(err))))
    if worst > POSE_TOL:
        raise BagError(f'{run.path}: the recorded ground-truth camera poses and the arm of '
                       f'this scenario disagree by up to {worst:.3g} (m, rad): give --config '
                       'the run was recorded with')
    return scene
