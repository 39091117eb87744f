"""
A recorded run, read back from its rosbag2: what the video and the 3-D replay show.

Everything is keyed by the *image stamp* (the header every message derived from an image
carries, README "Topics"), so the topics line up whatever order the recorder got them in.
Read: ``camera/camera_info`` (the first one), ``detector/measurement``, ``features/<set>``,
``camera/cmd_vel_stamped``, ``servo/state``, ``joint_states`` and
``ground_truth/camera_pose``; the images themselves are streamed later
(:func:`iter_frames`), one pass, never all in memory.

The frames of a run (:attr:`Run.frames`): one per servo iteration — every image the servo
answered while enabled (``servo/state`` ``servoing``, ``converged`` or ``target lost``,
whose value ``stamp`` names the image) — or, in a bag without servo states (or with
``every_image``), every image of the bag. A re-published image (the lockstep arm_sim's
idle re-publication: the same stamp) counts once.

The desired measurement (:attr:`Run.desired`): the recorded ``detector/measurement`` of the
image the run taught, found as ``refeatures`` finds it (the image whose features give the
s* of the recorded ``features/<set>`` messages); in a bag without features messages, the
last image the servo called converged; else none (the video then says so).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

from sphere_servo.bag import refeatures as rf
from sphere_servo.bag.bagio import bag, BagError, iter_raw, topic_name
from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.pipeline.servo import ServoState

POSE_TOPIC, JOINTS_TOPIC = '/ground_truth/camera_pose', '/joint_states'
#: the servo's states of an iteration (it answered an image while enabled)
ENABLED = tuple(s.value for s in (ServoState.SERVOING, ServoState.CONVERGED,
                                  ServoState.TARGET_LOST))


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

    frames    image stamps the video and the replay show, in time order.
    camera    intrinsics of the first camera_info (None if the bag has none).
    meas      recorded measurement values by stamp ({} when the sphere was not detected).
    errors    s − s* of ``features/<feature_set>`` by stamp; ``twists`` the servo's twist.
    states    the servo's state text by the stamp of the image it answered.
    joints    joint positions by stamp (``joint_names`` order); ``oMc`` ground-truth poses.
    """

    path: Path
    frames: list
    camera: CameraIntrinsics | None = None
    meas: dict = field(default_factory=dict)
    feature_set: str | None = None
    errors: dict = field(default_factory=dict)
    twists: dict = field(default_factory=dict)
    states: dict = field(default_factory=dict)
    joints: dict = field(default_factory=dict)
    joint_names: list = field(default_factory=list)
    oMc: dict = field(default_factory=dict)
    desired: Desired | None = None
    image_topic: str = rf.IMAGE_TOPIC

    def t(self, stamp: int) -> float:
        """Seconds from the first frame to the image stamped ``stamp``."""
        return (stamp - self.frames[0]) * 1e-9

    def series(self, table: dict, width: int) -> np.ndarray:
        """(len(frames), width) the values of ``table`` at each frame, NaN where it has none."""
        out = np.full((len(self.frames), width), np.nan)
        for k, st in enumerate(self.frames):
            if st in table:
                out[k] = table[st]
        return out


def output_path(bag, given: str | None, name: str) -> Path:
    """Give the output file: ``given``, else ``name`` beside the bag directory (the run's)."""
    return Path(given) if given else Path(bag).resolve().parent / name


def cli_error(prog: str, err: BaseException) -> int:
    """Print why a command line tool did nothing, on one line of stderr; return exit code 1."""
    import sys
    print(f'{prog}: error: {" ".join(str(err).split())}', file=sys.stderr)
    return 1


def _stamp(text: str) -> int | None:
    sec, _, frac = str(text).partition('.')
    try:
        return int(sec) * 1_000_000_000 + int((frac + '0' * 9)[:9] or 0)
    except ValueError:
        return None


def _twist(msg) -> np.ndarray:
    t = msg.twist
    return np.array([t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y,
                     t.angular.z])


def _pose(msg) -> pin.SE3:
    p, o = msg.pose.position, msg.pose.orientation
    return pin.XYZQUATToSE3(np.array([p.x, p.y, p.z, o.x, o.y, o.z, o.w]))


def read_run(path, settings: rf.Settings | None = None, image_topic: str = rf.IMAGE_TOPIC,
             every_image: bool = False) -> Run:
    """
    Read the run recorded in the bag at ``path``.

    ``settings`` (the nodes' parameters, ``refeatures.load_settings``) give the target kind
    and the servo's feature set; the nodes' defaults when None. Raises
    :class:`~sphere_servo.bag.bagio.BagError` when the bag cannot be read or has no image
    on ``image_topic``.
    """
    settings = settings or rf.Settings.from_config(None)
    image_topic = topic_name(image_topic)
    fset = settings.servo['feature_set']
    wanted = {rf.INFO_TOPIC, rf.MEAS_TOPIC, rf.TWIST_TOPIC, rf.STATE_TOPIC, POSE_TOPIC,
              JOINTS_TOPIC, *map(rf.features_topic, ('s_n', 's', 's_cc'))}
    msgs: dict[str, list] = {t: [] for t in wanted}
    images: list[tuple[int, int]] = []   # (bag ns, stamp)
    with bag(path) as reader:
        have = {c.topic for c in reader.connections}
        if image_topic not in have:
            raise BagError(f'{path}: no images: topic {image_topic} is not in the bag (it '
                           f'has {", ".join(sorted(have)) or "no topics"})')
        conns = [c for c in reader.connections if c.topic in wanted | {image_topic}]
        for conn, ts, raw in iter_raw(reader, conns):
            if conn.topic == image_topic:
                # the header is the first field of an Image: decode only that much
                images.append((ts, _header_stamp(raw)))
                continue
            if conn.topic == rf.INFO_TOPIC and msgs[rf.INFO_TOPIC]:
                continue  # the intrinsics do not change in a run
            try:
                msgs[conn.topic].append((ts, reader.deserialize(raw, conn.msgtype)))
            except Exception as err:  # rosbags raises several types; all mean "corrupt"
                raise BagError(f'cannot decode a message on {conn.topic}: {err}') from None
    if not images:
        raise BagError(f'{path}: no images: topic {image_topic} has no message')
    run = Run(Path(path), [], image_topic=image_topic)
    if msgs[rf.INFO_TOPIC]:
        info = msgs[rf.INFO_TOPIC][0][1]
        try:
            run.camera = CameraIntrinsics.from_camera_info_fields(info.width, info.height,
                                                                  info.k, info.d)
        except ValueError:
            run.camera = None
    run.meas = {rf.stamp_ns(m.header): dict(zip(m.name, m.position))
                for _, m in msgs[rf.MEAS_TOPIC] if len(m.name) == len(m.position)}
    have_sets = [n for n in (fset, 's_n', 's', 's_cc') if msgs[rf.features_topic(n)]]
    if have_sets:
        run.feature_set = have_sets[0]
        run.errors = {rf.stamp_ns(m.header): np.asarray(m.effort, float)
                      for _, m in msgs[rf.features_topic(run.feature_set)] if len(m.name)}
    run.twists = {rf.stamp_ns(m.header): _twist(m) for _, m in msgs[rf.TWIST_TOPIC]}
    for _, m in msgs[rf.STATE_TOPIC]:
        st = _stamp({kv.key: kv.value for kv in m.values}.get('stamp', ''))
        if st is not None:
            run.states[st] = m.message
    for _, m in msgs[JOINTS_TOPIC]:
        run.joint_names = list(m.name)
        run.joints[rf.stamp_ns(m.header)] = np.asarray(m.position, float)
    run.oMc = {rf.stamp_ns(m.header): _pose(m) for _, m in msgs[POSE_TOPIC]}
    stamps = list(dict.fromkeys(st for _, st in images))  # bag order, re-publications once
    enabled = {st for st, msg in run.states.items() if msg in ENABLED}
    run.frames = sorted(stamps if every_image or not enabled
                        else [st for st in stamps if st in enabled])
    if not run.frames:
        raise BagError(f'{path}: no image of the servo run (no image the servo answered '
                       'while enabled is in the bag)')
    run.desired = _desired(run, settings, images, msgs)
    return run


def _header_stamp(raw: bytes) -> int:
    """Read the header stamp (ns) of a CDR-serialized message whose first field is a Header."""
    # 4-byte encapsulation header, then int32 sec and uint32 nanosec, little-endian (CDR_LE)
    if len(raw) < 12 or raw[1] not in (0, 1):
        raise BagError('an image message is too short or not CDR')
    order = 'little' if raw[1] == 1 else 'big'
    sec = int.from_bytes(raw[4:8], order, signed=True)
    return sec * 1_000_000_000 + int.from_bytes(raw[8:12], order)


def _desired(run: Run, settings: rf.Settings, images, msgs) -> Desired | None:
    """See the module docstring: the taught image, else the last converged one."""
    recorded_meas = msgs[rf.MEAS_TOPIC]
    by_stamp = {rf.stamp_ns(m.header): m for _, m in recorded_meas}
    frames = [rf.Frame(i, ts, st, by_stamp[st]) for i, (ts, st) in enumerate(images)
              if st in by_stamp]
    sets = {n: msgs[rf.features_topic(n)] for n in ('s_n', 's_cc', 's')
            if msgs[rf.features_topic(n)]}
    if frames and sets:
        try:
            found = rf.find_desired(rf.Pipeline(settings), frames, 'auto', sets, None,
                                    list(sets), recorded_meas)
        except BagError as err:
            note = f'no taught image found ({err})'
        else:
            d = found[-1]  # the desired in force at the end of the run
            return Desired(run.meas[d.frame.stamp], d.frame.stamp, 'taught', d.note)
    else:
        note = 'the bag has no features messages to find the taught image'
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
    before it are out. An image that is not 8-bit (mono16, 32FC1) is a BagError.
    """
    from sphere_servo.bag.bagio import image_to_array
    index = {st: k for k, st in enumerate(run.frames)}
    pending: dict[int, tuple] = {}
    nxt = 0
    with bag(run.path) as reader:
        conns = [c for c in reader.connections if c.topic == run.image_topic]
        for conn, _, raw in iter_raw(reader, conns):
            k = index.get(_header_stamp(raw))
            if k is None or k < nxt or k in pending:
                continue  # not a frame, or a re-publication of one
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as err:  # rosbags raises several types; all mean "corrupt"
                raise BagError(f'cannot decode an image on {conn.topic}: {err}') from None
            img = image_to_array(msg)
            if img.dtype != np.uint8:
                raise BagError(f'images on {conn.topic} are {msg.encoding}: an 8-bit '
                               'encoding is needed')
            if msg.encoding in ('bgr8', 'bgra8'):
                img = img[..., 2::-1]
            elif img.ndim == 2:
                img = np.repeat(img[..., None], 3, axis=2)
            pending[k] = (run.frames[k], np.ascontiguousarray(img[..., :3]))
            while nxt in pending:
                yield (nxt, *pending.pop(nxt))
                nxt += 1
