"""refeatures: regenerate the pipeline's features from a recorded bag's images, offline.

    ros2 run sphere_servo refeatures BAG [--config NAME] [--sets SET ...] [--desired SPEC]
                                     [--check [TOL]] [--json FILE]
                                     [-o OUT [--storage S] [--servo]]
                                     [--compare SET ...] [--plot PNG] [--export-desired PNG]

No ROS graph: the bag's images and camera_info go through the code the nodes run, in the
nodes' order — ``Detector.detect`` and the ``detector/measurement`` codec (``detector``),
``observation_from_measurement`` and ``make_feature_set`` (``features``), and
``VectorController`` (``servo``, open loop: the twist is computed, nothing moves). Parameters
are the nodes' defaults, or the ``detector`` / ``features`` / ``servo`` sections of a
launcher config (``--config special_sphere`` for a bag of ``make demo``).

Desired features (``--desired``):
  auto         (default) the image the recorded run taught. The features node teaches the
               *latest* measurement and publishes features for every later one, so the
               taught image is the last image before the first recorded ``features/<set>``
               message whose features reproduce that message's s* (its ``velocity``) —
               judged on the recorded ``detector/measurement`` when there is one, so a
               changed detector still finds it. Each later change of s* is a re-teach.
  stamp:T      the image with header stamp T (seconds, e.g. ``stamp:1.133333333``)
  pose:X,Y,Z,ROLL,PITCH,YAW  exact projection of the target at cMo (``desired_source: pose``)
  image:FILE   an image file detected with the bag's intrinsics (``desired_source: image``)
With auto/stamp one features message is made for every image after the taught one (as live);
with pose/image for every image. Each message carries its image's header.

What it prints or writes:
  (always)     per topic, the regenerated stream against the recorded one, message for
               message by image stamp: counts, max |difference|; ``--check`` exits 1 unless
               they agree within TOL (default 1e-9): features/<set> the same stream;
               measurements and twists every message whose image stamp both have.
  -o OUT       a new bag with ``detector/measurement``, ``features/<set>`` and, with
               ``--servo``, ``camera/cmd_vel_stamped`` (bag times = the images' bag times).
  --compare    sets A B ...: each set's error and the law's twist on the same images (open
               loop), as a table, and with ``--plot`` as a PNG (errors | twists, a row a set).
  --export-desired PNG  the taught image, so the live nodes reproduce it over ROS:
               ``replay BAG --topics /camera/image_raw /camera/camera_info`` into ``detector``
               and ``features --ros-args -p desired_source:=image -p desired_image:=PNG``.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from sphere_servo.bag.bagio import (BagError, bag, check_new_output, iter_raw,
                                      select_connections, topic_name, typestore)

IMAGE_TOPIC, INFO_TOPIC = '/camera/image_raw', '/camera/camera_info'
MEAS_TOPIC, TWIST_TOPIC = '/detector/measurement', '/camera/cmd_vel_stamped'
STATE_TOPIC = '/servo/state'
TOL = 1e-9


def features_topic(name: str) -> str:
    return f'/features/{name}'


# --- the nodes' parameters -----------------------------------------------------------------
@dataclass
class Settings:
    """The ``detector``, ``features`` and ``servo`` parameters (validated as the nodes do)."""

    detector: dict
    features: dict
    servo: dict

    @classmethod
    def from_config(cls, config: dict | None = None) -> 'Settings':
        """The nodes' defaults, overridden by a merged launcher config's sections."""
        from sphere_servo.ros import detector, features, servo
        from sphere_servo.ros.params import check
        from sphere_servo.pipeline.config import node_params
        out = {}
        for name, table in (('detector', detector.PARAMS), ('features', features.PARAMS),
                            ('servo', servo.PARAMS)):
            given = node_params(config or {}, name)
            out[name] = {k: check(k, p, given.get(k, p.default)) for k, p in table.items()}
        return cls(**out)


def load_settings(config: str | None) -> Settings:
    if not config:
        return Settings.from_config(None)
    from sphere_servo.pipeline.config import find_config, load_config
    return Settings.from_config(load_config(find_config(config)))


# --- what the nodes do, one message at a time ----------------------------------------------
def ros_header(h):
    """A std_msgs/Header (rclpy) from a rosbags-deserialized header."""
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header
    return Header(stamp=Time(sec=int(h.stamp.sec), nanosec=int(h.stamp.nanosec)),
                  frame_id=str(h.frame_id))


def stamp_ns(h) -> int:
    return int(h.stamp.sec) * 1_000_000_000 + int(h.stamp.nanosec)


def stamp_text(ns: int) -> str:
    return f'{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}'


class Pipeline:
    """``detector`` → ``features`` → ``servo`` as functions of messages."""

    def __init__(self, settings: Settings):
        from sphere_servo.core.control import AdaptiveGain, VectorController
        from sphere_servo.core.targets import make_target
        from sphere_servo.vision.detector import Detector
        self.settings = s = settings
        self.detector = Detector.for_target(make_target(s.detector['target_kind']))
        f = s.features
        self.target = make_target(f['target_kind'], radius=f['target_radius']) \
            if f['target_kind'] != 'balloon' else make_target('balloon')
        self.kind = self.target.kind
        v = s.servo
        gain = AdaptiveGain(v['lambda_0'], v['lambda_inf'], v['slope_0']) \
            if v['adaptive'] else v['gain']
        self.law_kw = dict(gain=gain, interaction=v['interaction'], v_max=v['v_max'],
                           w_max=v['w_max'], tol=v['tol'])
        self.law = VectorController(v['feature_set'], v['r_hat'], **self.law_kw)
        self.sets: dict = {}
        self.desired_obs = None

    def camera(self, info):
        """The detector's intrinsics from a (rosbags) CameraInfo, or None if unusable."""
        from sphere_servo.core.camera import CameraIntrinsics
        try:
            cam = CameraIntrinsics.from_camera_info_fields(info.width, info.height, info.k,
                                                           info.d)
            ex, ey, eu, ev = self.settings.detector['intrinsics_error']
            return cam.with_error(px=ex, py=ey, u0=eu, v0=ev)
        except ValueError:
            return None

    def detect(self, img_msg, camera):
        """The :class:`Detection` of one (rosbags) Image, or None when the node would reject
        it (no camera_info yet, a bad buffer)."""
        from sphere_servo.vision.detector import image_from_buffer
        try:
            if camera is None:
                raise ValueError('no valid camera_info')
            img = image_from_buffer(img_msg.height, img_msg.width, img_msg.step,
                                    img_msg.encoding, img_msg.data)
            return self.detector.detect(img, img_msg.encoding, camera)
        except ValueError:
            return None

    def measure(self, img_msg, camera):
        """``detector/measurement`` for one image (empty when not detected)."""
        from sphere_servo.ros.vectors import measurement_msg
        return measurement_msg(self.detect(img_msg, camera), ros_header(img_msg.header))

    def observation(self, meas):
        """The features node's Observation of a measurement (MeasurementError if lost)."""
        from sphere_servo.ros.vectors import observation_from_measurement
        return observation_from_measurement(meas, self.kind)

    def set_desired(self, obs, names) -> None:
        from sphere_servo.core.features import make_feature_set
        self.desired_obs = obs
        self.sets = {name: make_feature_set(name, obs) for name in names}

    def features(self, meas) -> dict:
        """``features/<set>`` messages for one measurement (empty ones when lost)."""
        from sphere_servo.core.geometry import GeometryError
        from sphere_servo.ros.vectors import features_msg
        try:
            obs = self.observation(meas)
            out = {name: (fs.features(obs), fs.desired) for name, fs in self.sets.items()}
        except GeometryError:
            out = {name: (None, None) for name in self.sets}
        return {name: features_msg(name, meas.header, s, s_star)
                for name, (s, s_star) in out.items()}

    def twist(self, fmsg, enabled: bool = True):
        """The servo's ``camera/cmd_vel_stamped`` for one features message (zero when
        disabled, lost, converged, or the law fails)."""
        from geometry_msgs.msg import TwistStamped

        from sphere_servo.core.geometry import GeometryError
        from sphere_servo.ros.conversions import twist_from_array
        from sphere_servo.ros.vectors import features_from_msg
        v_c = np.zeros(6)
        try:
            fs = features_from_msg(fmsg, self.law.feature_set) if enabled else None
            if fs is not None:
                out = self.law.compute(*fs)
                v_c = np.zeros(6) if out.converged else out.v_c
        except GeometryError:
            pass
        return TwistStamped(header=fmsg.header, twist=twist_from_array(v_c))


# --- reading the bag -----------------------------------------------------------------------
@dataclass
class Frame:
    """One recorded image: bag time, header stamp (ns), and its measurement."""

    index: int
    bag_ns: int
    stamp: int
    meas: object


def read_topic(reader, topic: str) -> list[tuple[int, object]]:
    """(bag ns, rosbags message) of every message on ``topic``; [] if it is not in the bag."""
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        return []
    out = []
    for conn, ts, raw in iter_raw(reader, conns):
        try:
            out.append((ts, reader.deserialize(raw, conn.msgtype)))
        except Exception as err:
            raise BagError(f'cannot decode a message on {topic}: {err}') from None
    return out


def iter_image_msgs(reader, topic: str = IMAGE_TOPIC):
    """(index, bag ns, rosbags Image) in bag order."""
    conns = select_connections(reader, [topic])
    for c in conns:
        if c.msgtype != 'sensor_msgs/msg/Image':
            raise BagError(f'topic {c.topic} has type {c.msgtype}, not sensor_msgs/msg/Image')
    for i, (conn, ts, raw) in enumerate(iter_raw(reader, conns)):
        try:
            yield i, ts, reader.deserialize(raw, conn.msgtype)
        except Exception as err:
            raise BagError(f'cannot decode an image on {topic}: {err}') from None


class Cameras:
    """The detector's intrinsics for an image: the bag's camera_info with the image's stamp,
    else the latest one before it, else the first one (intrinsics do not change in a run)."""

    def __init__(self, pipeline: Pipeline, infos: list[tuple[int, object]]):
        self.infos = infos
        self.by_stamp = {stamp_ns(m.header): pipeline.camera(m) for _, m in infos}
        self.by_time = [(ts, pipeline.camera(m)) for ts, m in infos]

    def __call__(self, bag_ns: int, stamp: int):
        if stamp in self.by_stamp:
            return self.by_stamp[stamp]
        before = [c for ts, c in self.by_time if ts <= bag_ns]
        return before[-1] if before else (self.by_time[0][1] if self.by_time else None)


# --- the desired features ------------------------------------------------------------------
@dataclass
class Desired:
    """Where the desired features came from; ``frame``: the taught frame (auto/stamp)."""

    how: str
    obs: object
    frame: Frame | None = None
    start: int = 0            # first frame index that gets features
    note: str = ''


def parse_desired(spec: str) -> tuple[str, object]:
    kind, _, arg = spec.partition(':')
    if kind == 'auto' and not arg:
        return 'auto', None
    if kind == 'stamp' and arg:
        try:
            sec, _, frac = arg.strip().partition('.')
            return 'stamp', int(sec) * 1_000_000_000 + int((frac + '0' * 9)[:9] or 0)
        except ValueError:
            pass
    if kind == 'pose' and arg:
        try:
            vals = [float(x) for x in arg.split(',')]
        except ValueError:
            vals = []
        if len(vals) == 6 and all(np.isfinite(vals)):
            return 'pose', vals
    if kind == 'image' and arg:
        return 'image', Path(arg)
    raise BagError(f'bad --desired {spec!r}: use auto, stamp:SEC.NSEC, '
                   'pose:X,Y,Z,ROLL,PITCH,YAW or image:FILE')


def find_desired(pipe: Pipeline, frames: list[Frame], spec: str, recorded: dict,
                 cameras: Cameras, names: list[str],
                 recorded_meas: list | None = None) -> list[Desired]:
    """The desired observations per ``--desired`` (see the module docstring), in the order
    they took effect (several when the recorded run was re-taught)."""
    from sphere_servo.core.geometry import GeometryError
    kind, arg = parse_desired(spec)
    if kind == 'pose':
        from sphere_servo.core.measurement import observe
        from sphere_servo.sim.arm import pose_from_xyz_rpy
        if not pipe.target.is_sphere:
            raise BagError("--desired pose needs a spherical target model")
        try:
            obs = observe(pose_from_xyz_rpy(arg[:3], arg[3:]), pipe.target)
        except GeometryError as exc:
            raise BagError(f'--desired pose does not show the target: {exc}') from None
        return [Desired('pose', obs, note=f'pose {arg}')]
    if kind == 'image':
        import cv2
        bgr = cv2.imread(str(arg), cv2.IMREAD_COLOR) if arg.is_file() else None
        if bgr is None:
            raise BagError(f'--desired image {str(arg)!r} is not a readable image file')
        if not cameras.infos:
            raise BagError('--desired image needs a camera_info in the bag')
        # as the features node: the first camera_info, its own intrinsics_error, bgr8
        from sphere_servo.core.camera import CameraIntrinsics
        info = cameras.infos[0][1]
        try:
            cam = CameraIntrinsics.from_camera_info_fields(info.width, info.height, info.k,
                                                           info.d)
            cam = cam.with_error(*pipe.settings.features['intrinsics_error'])
            obs = pipe.detector.detect(bgr, 'bgr8', cam).to_observation(pipe.kind)
        except (ValueError, GeometryError) as exc:
            raise BagError(f'--desired image {str(arg)!r} unusable: {exc}') from None
        return [Desired('image', obs, note=str(arg))]
    if kind == 'stamp':
        for i, f in enumerate(frames):
            if f.stamp == arg:
                try:
                    obs = pipe.observation(f.meas)
                except GeometryError as exc:
                    raise BagError(f'cannot teach the image stamped {stamp_text(arg)}: '
                                   f'{exc}') from None
                return [Desired('stamp', obs, f, start=f.index + 1)]
        raise BagError(f'no image stamped {stamp_text(arg)} in the bag')
    return _auto_desired(pipe, frames, recorded, names, recorded_meas)


def _teach_events(msgs: list) -> list[tuple[int, np.ndarray]]:
    """(stamp of the first features message under a desired, that s*) for each desired the
    recorded stream shows: the first message, then each s* change (a re-teach)."""
    events, prev = [], None
    for _, m in msgs:
        if not len(m.name):
            continue  # target lost: no s* in the message
        star = np.asarray(m.velocity, float)
        if prev is None or not np.array_equal(star, prev):
            events.append((stamp_ns(m.header), star))
            prev = star
    if events:  # the first desired starts with the first message, even an empty one
        events[0] = (stamp_ns(msgs[0][1].header), events[0][1])
    return events


def _star_error(pipe: Pipeline, name: str, meas, star: np.ndarray) -> float:
    """max |s* − the s* this measurement would give| (inf when it cannot be taught)."""
    from sphere_servo.core.features import make_feature_set
    from sphere_servo.core.geometry import GeometryError
    try:
        return float(np.max(np.abs(make_feature_set(name, pipe.observation(meas)).desired
                                   - star)))
    except GeometryError:
        return np.inf


def _auto_desired(pipe: Pipeline, frames: list[Frame], recorded: dict, names: list[str],
                  recorded_meas: list | None = None) -> list[Desired]:
    """The taught images: see ``auto`` in the module docstring; one per teach. An image is
    recognised by what the live features node saw — the recorded ``detector/measurement``
    with its stamp when the bag has it — so a changed detector still finds the taught
    image; the desired is then that image's regenerated measurement."""
    seen: dict[int, list] = {}
    for _, m in recorded_meas or []:
        seen.setdefault(stamp_ns(m.header), []).append(m)
    have = [n for n in ('s_n', 's_cc', 's') if recorded.get(n)]  # s's s* is 0: weakest
    if not have:
        raise BagError('the bag has no features/<set> messages to find the taught image: '
                       'give --desired stamp:T, pose:X,Y,Z,ROLL,PITCH,YAW or image:FILE')
    name = have[0]
    events = _teach_events(recorded[name])
    if not events:
        raise BagError(f'every recorded features/{name} message is empty (target lost): '
                       'give --desired stamp:T, pose:... or image:FILE')
    out: list[Desired] = []
    lo = 0
    for first_stamp, star in events:
        # the first features message under this desired came from an image with its stamp
        # (the first one after lo, or a later re-publication of it when the image taught
        # is that very image); the taught image is the last image before it whose features
        # reproduce s* — or that image itself (teaching on the bag's very first frame)
        starts = [k for k in range(lo, len(frames)) if frames[k].stamp == first_stamp]
        if not starts:
            raise BagError(f'the features/{name} message stamped {stamp_text(first_stamp)} '
                           'has no image in the bag')
        tol = TOL * max(1.0, float(np.max(np.abs(star))))
        errs: dict[int, float] = {}
        for start in starts:
            for k in range(start + 1):
                if k not in errs:
                    errs[k] = min(_star_error(pipe, name, m, star) for m in
                                  seen.get(frames[k].stamp, [frames[k].meas]))
            # an image before the first message under s* is the taught one; that message's
            # own image only when none before it is (teaching on the bag's first frame)
            exact = [k for k in range(start) if errs[k] <= tol] or \
                [k for k in (start,) if errs[k] <= tol]
            if exact:
                best, best_err = exact[-1], 0.0
                break
        else:
            start = starts[0]
            best_err, best = min((errs[k], k) for k in range(start + 1))
            if not np.isfinite(best_err):
                raise BagError(f'no image before the features/{name} message stamped '
                               f'{stamp_text(first_stamp)} is usable as the taught one: give '
                               '--desired stamp:T, pose:... or image:FILE')
        f = frames[best]
        note = (f'image stamped {stamp_text(f.stamp)} reproduces the recorded s* of '
                f'features/{name}' + ('' if best_err == 0.0 else
                                      f' only to {best_err:.3g} (the closest)'))
        out.append(Desired('auto', pipe.observation(f.meas), f, start=frames[start].index,
                           note=note))
        lo = start + 1
    return out


# --- regenerate, compare, write --------------------------------------------------------------
@dataclass
class Result:
    """The regenerated streams: topic → [(bag ns, rclpy message)]; ``frames`` all images;
    ``desired`` the desireds in the order they took effect."""

    frames: list
    desired: list
    streams: dict = field(default_factory=dict)
    recorded: dict = field(default_factory=dict)   # topic → [(bag ns, rosbags message)]
    sets: list = field(default_factory=list)
    pipeline: Pipeline | None = None


def recorded_sets(reader) -> list[str]:
    from sphere_servo.core.features import FEATURE_SETS
    have = {c.topic for c in reader.connections}
    return [n for n in FEATURE_SETS if features_topic(n) in have]


def regenerate(path, settings: Settings, sets: list[str] | None = None,
               desired: str = 'auto', servo: bool = False,
               image_topic: str = IMAGE_TOPIC, info_topic: str = INFO_TOPIC) -> Result:
    """Run the bag's images through detector → features (→ servo) offline."""
    pipe = Pipeline(settings)
    with bag(path) as reader:
        if topic_name(info_topic) not in {c.topic for c in reader.connections}:
            raise BagError(f'topic {topic_name(info_topic)} (the intrinsics) not in bag')
        names = list(sets or recorded_sets(reader) or ['s_n'])
        recorded = {t: read_topic(reader, t) for t in
                    [MEAS_TOPIC, TWIST_TOPIC, STATE_TOPIC, *map(features_topic, names)]}
        cameras = Cameras(pipe, read_topic(reader, topic_name(info_topic)))
        frames = []
        for i, ts, img in iter_image_msgs(reader, topic_name(image_topic)):
            st = stamp_ns(img.header)
            frames.append(Frame(i, ts, st, pipe.measure(img, cameras(ts, st))))
    if not frames:
        raise BagError(f'no images on {topic_name(image_topic)}')
    rec_sets = {n: recorded[features_topic(n)] for n in names}
    want = list(dict.fromkeys([*names, settings.servo['feature_set']] if servo else names))
    ds = find_desired(pipe, frames, desired, rec_sets, cameras, want, recorded[MEAS_TOPIC])
    res = Result(frames, ds, recorded=recorded, sets=names, pipeline=pipe)
    res.streams[MEAS_TOPIC] = [(f.bag_ns, f.meas) for f in frames]
    streams = {features_topic(n): [] for n in want}
    twists = []
    disabled, answered = state_stamps(res.recorded.get(STATE_TOPIC) or [])
    for f, d in active(res):
        if pipe.desired_obs is not d.obs:
            _anchor(pipe, d, want)
        out = pipe.features(f.meas)
        for n, msg in out.items():
            streams[features_topic(n)].append((f.bag_ns, msg))
        # the recorded servo said which images it answered: it skips superseded or late
        # ones (max_image_age), so those get no twist offline either
        if servo and (not answered or f.stamp in answered):
            twists.append((f.bag_ns, pipe.twist(out[settings.servo['feature_set']],
                                                enabled=f.stamp not in disabled)))
    res.streams.update({features_topic(n): streams[features_topic(n)] for n in names})
    if servo:
        res.streams[TWIST_TOPIC] = twists
    return res


def state_stamps(states: list) -> tuple[set[int], set[int]]:
    """From the recorded ``servo/state``: the stamps of the images the servo answered while
    disabled (its ``~/enable`` switch is not in the images; message ``disabled``), and of
    every image it answered at all (each answer carries the value ``stamp``; empty when the
    bag has no servo states)."""
    disabled, answered = set(), set()
    for _, m in states:
        vals = {kv.key: kv.value for kv in m.values}
        if 'stamp' not in vals:
            continue
        sec, _, frac = vals['stamp'].partition('.')
        try:
            t = int(sec) * 1_000_000_000 + int((frac + '0' * 9)[:9] or 0)
        except ValueError:
            continue
        answered.add(t)
        if m.message == 'disabled':
            disabled.add(t)
    return disabled, answered


def active(res: Result):
    """(frame, its desired) for every frame that gets features."""
    ds = res.desired
    k = -1
    for f in res.frames:
        while k + 1 < len(ds) and ds[k + 1].start <= f.index:
            k += 1
        if k >= 0:
            yield f, ds[k]


def _anchor(pipe: Pipeline, d: Desired, names: list[str]) -> None:
    from sphere_servo.core.geometry import GeometryError
    try:
        pipe.set_desired(d.obs, names)
    except GeometryError as exc:
        raise BagError(f'the desired ({d.how}) cannot anchor {names}: {exc}') from None


def _vec(msg, topic: str) -> np.ndarray:
    """The numbers of a message, for comparing (JointState: position, velocity, effort)."""
    if topic == TWIST_TOPIC:
        t = msg.twist
        return np.array([t.linear.x, t.linear.y, t.linear.z,
                         t.angular.x, t.angular.y, t.angular.z])
    return np.concatenate([np.asarray(msg.position, float), np.asarray(msg.velocity, float),
                           np.asarray(msg.effort, float)])


@dataclass
class Match:
    """Regenerated vs recorded messages of one topic, paired in order by image stamp."""

    topic: str
    regenerated: int
    recorded: int
    matched: int
    common: int       # how many could be paired: the stamps both streams have (multiset)
    same_names: bool
    max_diff: float
    no_image: int = 0  # recorded messages of an image the bag lacks (the recorder lost it)
    warmup: int = 0    # leading empty recorded measurements (the live detector had no
                       # camera_info yet; offline, the bag's camera_info is known at once)

    def ok(self, tol: float = TOL, partial: bool = False) -> bool:
        """Message for message: the same count and stamps (``partial``: every message whose
        image stamp both streams have is paired — for topics whose recording starts or ends
        apart from the images'), the same names and values within ``tol``."""
        paired = self.matched == self.common if partial else \
            self.matched == self.recorded == self.regenerated
        return paired and self.same_names and self.max_diff <= tol

    @property
    def stamps(self) -> str:
        if self.matched == self.recorded == self.regenerated:
            return 'same'
        return 'common' if self.matched == self.common else 'DIFFER'


def compare_recorded(res: Result, topic: str) -> Match | None:
    """Pair each recorded message with the next regenerated one of the same image stamp;
    None if the topic was not recorded."""
    rec = res.recorded.get(topic) or []
    gen = res.streams.get(topic) or []
    if not rec:
        return None
    warmup = 0
    if topic == MEAS_TOPIC:  # the live detector's start, before its first camera_info
        while warmup < len(rec) and not rec[warmup][1].name:
            warmup += 1
        rec = rec[warmup:]
    from collections import Counter
    gen_st = [stamp_ns(m.header) for _, m in gen]
    rec_st = [stamp_ns(m.header) for _, m in rec]
    j, pairs = 0, []
    for (_, a), st in zip(rec, rec_st):
        k = next((k for k in range(j, len(gen)) if gen_st[k] == st), None)
        if k is not None:  # else: its image is not in the bag (recorded apart)
            pairs.append((a, gen[k][1]))
            j = k + 1
    names = all(list(getattr(a, 'name', [])) == list(getattr(b, 'name', []))
                for a, b in pairs)
    diff = 0.0
    for a, b in pairs:
        va, vb = _vec(a, topic), _vec(b, topic)
        if va.shape != vb.shape:
            diff = np.inf
            break
        if va.size:
            diff = max(diff, float(np.max(np.abs(va - vb))))
    common = sum((Counter(gen_st) & Counter(rec_st)).values())
    images = Counter(f.stamp for f in res.frames)
    no_image = sum(max(0, n - images[st]) for st, n in Counter(rec_st).items())
    return Match(topic, len(gen), len(rec), len(pairs), common, names, diff, no_image, warmup)


def write_bag(res: Result, out: Path, storage: str = 'mcap') -> dict[str, int]:
    """The regenerated streams into a new rosbag2 (bag times = the images' bag times)."""
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer
    types = {MEAS_TOPIC: 'sensor_msgs/msg/JointState',
             TWIST_TOPIC: 'geometry_msgs/msg/TwistStamped'}
    counts = {}
    with Writer(out, version=Writer.VERSION_LATEST,
                storage_plugin=StoragePlugin[storage.upper()]) as w:
        items = []
        for topic, msgs in res.streams.items():
            conn = w.add_connection(topic, types.get(topic, 'sensor_msgs/msg/JointState'),
                                    typestore=typestore())
            counts[topic] = len(msgs)
            items += [(ts, k, conn, m) for k, (ts, m) in enumerate(msgs)]
        for ts, _, conn, m in sorted(items, key=lambda x: (x[0], x[2].id, x[1])):
            w.write(conn, ts, serialize_message(m))
    return counts


# --- comparing feature sets on the same images ---------------------------------------------
@dataclass
class SetRun:
    """One feature set along the recorded images, open loop: t (N,), e (N, n), v (N, 6)."""

    name: str
    labels: tuple
    t: np.ndarray
    e: np.ndarray
    v: np.ndarray
    lost: int


def compare_sets(res: Result, names: list[str]) -> list[SetRun]:
    """Each set's error and the law's twist (``Controller`` on the observation, so s_cc too)
    for every image after the last teach (earlier desireds were discarded by the run)."""
    from sphere_servo.core.control import Controller
    from sphere_servo.core.features import make_feature_set
    from sphere_servo.core.geometry import GeometryError
    from sphere_servo.ros.vectors import FEATURE_NAMES as FEATURE_LABELS
    pipe = res.pipeline
    runs = []
    r_hat = pipe.settings.servo['r_hat']
    for name in names:
        t, e, v, lost = [], [], [], 0
        last = res.desired[-1]
        law = Controller(make_feature_set(name, last.obs), r_hat, **pipe.law_kw)
        for f, d in active(res):
            if d is not last:
                continue
            try:
                out = law.compute(pipe.observation(f.meas))
            except GeometryError:
                lost += 1
                continue
            t.append(f.stamp / 1e9)
            e.append(out.error)
            v.append(np.zeros(6) if out.converged else out.v_c)
        runs.append(SetRun(name, FEATURE_LABELS[name], np.array(t), np.array(e).reshape(len(t), -1),
                           np.array(v).reshape(len(t), 6), lost))
    return runs


def format_sets(runs: list[SetRun], tol: float) -> str:
    """A table: images, lost, max and last ‖e‖, the time after which ‖e‖ stays below the
    servo's tol, twist peaks, and how far each set's twist is from the first set's."""
    ref = runs[0]
    lines = [f'{"set":5} {"images":>6} {"lost":>4} {"max|e|":>8} {"last|e|":>9} '
             f'{"settle(s)":>9} {"max|v|":>7} {"max|w|":>7}  twist - {ref.name} twist (RMS)']
    for r in runs:
        if not len(r.t):
            lines.append(f'{r.name:5} {0:6d} {r.lost:4d}')
            continue
        n = np.linalg.norm(r.e, axis=1)
        above = np.nonzero(n >= tol)[0]
        settle = ('-' if len(above) and above[-1] == len(n) - 1 else
                  f'{(r.t[above[-1] + 1] if len(above) else r.t[0]) - r.t[0]:.3f}')
        rms = '-'
        if np.array_equal(r.t, ref.t):
            d = r.v - ref.v
            rms = (f'{np.sqrt(np.mean(np.sum(d[:, :3]**2, 1))):.3g} m/s, '
                   f'{np.sqrt(np.mean(np.sum(d[:, 3:]**2, 1))):.3g} rad/s')
        lines.append(f'{r.name:5} {len(r.t):6d} {r.lost:4d} {n.max():8.4g} {n[-1]:9.3g} '
                     f'{settle:>9} {np.linalg.norm(r.v[:, :3], axis=1).max():7.4f} '
                     f'{np.linalg.norm(r.v[:, 3:], axis=1).max():7.4f}  {rms}')
    return '\n'.join(lines)


def plot_sets(runs: list[SetRun], path: Path, title: str = '') -> Path:
    """Errors (left) and open-loop twists (right), one row per set, same time axis."""
    import matplotlib.pyplot as plt

    from sphere_servo.sim.plots import plot_errors, plot_twist, save
    fig, axes = plt.subplots(len(runs), 2, figsize=(11, 3.2 * len(runs)), squeeze=False,
                             sharex=True)
    for (ax1, ax2), r in zip(axes, runs):
        t = r.t - (runs[0].t[0] if len(runs[0].t) else 0.0)
        plot_errors(ax1, t, r.e, r.labels, fontsize=7)
        ax1.set_ylabel(f'{r.name}: s − s*')
        ax2b = plot_twist(ax2, t, r.v, fontsize=7)
        ax2.set_ylabel(f'{r.name}: v (m/s)')
        ax2b.set_ylabel('ω (deg/s)')
    axes[0, 0].set_title('feature error (open loop on the recorded images)')
    axes[0, 1].set_title('the law\'s camera twist (not applied)')
    axes[-1, 0].set_xlabel('image time since the first servoed image (s)')
    axes[-1, 1].set_xlabel('image time since the first servoed image (s)')
    return save(fig, path, title, dpi=100)


def export_desired(path, res: Result, out: Path, image_topic: str = IMAGE_TOPIC) -> Path:
    """Write the taught image (auto/stamp) as a PNG the features node reads back."""
    import cv2

    from sphere_servo.vision.detector import image_from_buffer
    f = res.desired[-1].frame
    if f is None:
        raise BagError('--export-desired needs a taught image from the bag (--desired auto '
                       'or stamp:T)')
    with bag(path) as reader:
        for i, _, img in iter_image_msgs(reader, topic_name(image_topic)):
            if i == f.index:
                arr = image_from_buffer(img.height, img.width, img.step, img.encoding,
                                        img.data)
                bgr = arr[..., ::-1] if img.encoding == 'rgb8' else arr
                if not cv2.imwrite(str(out), np.ascontiguousarray(bgr)):
                    raise BagError(f'cannot write {str(out)!r}')
                return out
    raise BagError('the taught image vanished from the bag')


# --- command line ----------------------------------------------------------------------------
def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='refeatures', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.split('\n\n', 2)[2])
    p.add_argument('bag', help='rosbag2 directory with the images and camera_info')
    p.add_argument('--config', default=None,
                   help='launcher config (name or path) whose detector/features/servo '
                        'parameters to use (default: the nodes\' defaults)')
    p.add_argument('--sets', nargs='+', default=None, metavar='SET',
                   help='feature sets to regenerate (default: those recorded, else s_n)')
    p.add_argument('--desired', default='auto', metavar='SPEC',
                   help='auto | stamp:SEC.NSEC | pose:X,Y,Z,ROLL,PITCH,YAW | image:FILE')
    p.add_argument('--image-topic', default=IMAGE_TOPIC)
    p.add_argument('--info-topic', default=INFO_TOPIC)
    p.add_argument('--check', nargs='?', type=float, const=TOL, default=None, metavar='TOL',
                   help=f'exit 1 unless every recorded features/measurement (and, with '
                        f'--servo, twist) topic is reproduced within TOL (default {TOL})')
    p.add_argument('--json', default=None, metavar='FILE',
                   help='also write the comparison (and the desireds found) as JSON')
    p.add_argument('-o', '--output', default=None, help='write the regenerated streams to '
                   'this new bag directory')
    p.add_argument('-s', '--storage', choices=['mcap', 'sqlite3'], default='mcap')
    p.add_argument('--servo', action='store_true',
                   help='also the servo\'s open-loop twist (camera/cmd_vel_stamped)')
    p.add_argument('--compare', nargs='+', default=None, metavar='SET',
                   help='compare these feature sets on the same images (errors, twists)')
    p.add_argument('--plot', default=None, metavar='PNG', help='with --compare: the figure')
    p.add_argument('--export-desired', default=None, metavar='PNG',
                   help='write the taught image as a PNG (for desired_source: image)')
    opts = p.parse_args(argv)
    from sphere_servo.core.features import FEATURE_SETS
    for n in (opts.sets or []) + (opts.compare or []):
        if n not in FEATURE_SETS:
            p.error(f'unknown feature set {n!r}: use {" ".join(FEATURE_SETS)}')
    if opts.plot and not opts.compare:
        p.error('--plot needs --compare')
    return opts


def main(argv=None) -> int:
    opts = parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        return _main(opts)
    except BagError as err:
        print(f'refeatures: error: {err}', file=sys.stderr)
        return 1
    except (ValueError, OSError) as err:  # ParameterError, LaunchError, file errors
        print(f'refeatures: error: {" ".join(str(err).split())}', file=sys.stderr)
        return 1


def _main(opts) -> int:
    from sphere_servo.pipeline.config import ConfigError
    out = check_new_output(opts.output) if opts.output else None
    for f in (opts.plot, opts.export_desired, opts.json):
        if f and not Path(f).parent.is_dir():
            raise BagError(f'directory of {f!r} does not exist')
    try:
        settings = load_settings(opts.config)
    except ConfigError as err:
        raise BagError(str(err)) from None
    res = regenerate(opts.bag, settings, opts.sets, opts.desired, opts.servo,
                     opts.image_topic, opts.info_topic)
    print(f'refeatures: {len(res.frames)} images')
    for d in res.desired:
        print(f'  desired ({d.how}): {d.note}' if d.note else f'  desired ({d.how})')
        if d.frame is not None:
            print(f'    taught image #{d.frame.index} stamped {stamp_text(d.frame.stamp)}; '
                  f'features from image #{d.start} on')
    ok = True
    report = {'bag': str(opts.bag), 'images': len(res.frames), 'topics': {},
              'desired': [{'how': d.how, 'note': d.note, 'start': d.start,
                           'taught_index': d.frame.index if d.frame else None,
                           'taught_stamp_ns': d.frame.stamp if d.frame else None}
                          for d in res.desired]}
    print(f'  {"topic":28} {"regenerated":>11} {"recorded":>8}  stamps  max|diff|')
    for topic in res.streams:
        m = compare_recorded(res, topic)
        n = len(res.streams[topic])
        report['topics'][topic] = {'regenerated': n} if m is None else asdict(m)
        if m is None:
            print(f'  {topic:28} {n:11d} {"-":>8}')
            continue
        print(f'  {topic:28} {n:11d} {m.recorded:8d}  {m.stamps:6}  {m.max_diff:.3g}'
              + (f'  ({m.no_image} recorded of images not in the bag)' if m.no_image else '')
              + (f'  ({m.warmup} empty at the detector\'s start, not compared)'
                 if m.warmup else ''))
        # features: the same stream; the recorder may start on measurements before images,
        # and the servo is stopped before the last images
        if opts.check is not None:
            ok = ok and m.ok(opts.check, partial=topic in (MEAS_TOPIC, TWIST_TOPIC))
    if opts.json:
        report['ok'] = ok if opts.check is not None else None
        Path(opts.json).write_text(json.dumps(report, indent=1, default=float) + '\n')
    if out is not None:
        counts = write_bag(res, out, opts.storage)
        print(f'refeatures: wrote {sum(counts.values())} messages to {out}')
    if opts.export_desired:
        print(f'refeatures: taught image written to '
              f'{export_desired(opts.bag, res, Path(opts.export_desired), opts.image_topic)}')
    if opts.compare:
        runs = compare_sets(res, opts.compare)
        print(format_sets(runs, settings.servo['tol']))
        if opts.plot:
            print(f'refeatures: plot written to '
                  f'{plot_sets(runs, Path(opts.plot), title=Path(opts.bag).name)}')
    if opts.check is not None and not ok:
        print('refeatures: error: regenerated streams differ from the recorded ones',
              file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
