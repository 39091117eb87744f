"""
Regenerate a bag's pipeline streams offline: images → measurements → features (→ twists).

:func:`regenerate` runs every recorded image through the nodes' cores
(:class:`~sphere_servo.bag.offline.Pipeline`) with the desired found in the bag
(:mod:`sphere_servo.bag.desired`). With auto/stamp one features message is made for every
image after the taught one (as live); with pose/image for every image. Each message carries
its image's header. The open-loop servo answers exactly the images the recorded servo
answered (its ``servo/state`` says which: it skips superseded or late ones), with the
servo core's own rule for a repeated image.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from sphere_servo.bag.bagio import bag, BagError, topic_name
from sphere_servo.bag.desired import Desired, find_desired
from sphere_servo.bag.offline import (Cameras, features_topic, header_ns, IMAGE_TOPIC,
                                      INFO_TOPIC, iter_image_msgs, MEAS_TOPIC, Pipeline,
                                      read_topic, Settings, STATE_TOPIC, TWIST_TOPIC)
from sphere_servo.core.features import FEATURE_SETS
from sphere_servo.core.geometry import GeometryError
from sphere_servo.pipeline.common import parse_stamp
from sphere_servo.pipeline.servo import ServoCommand, ServoState


@dataclass
class Result:
    """
    The regenerated streams: topic → [(bag ns, rclpy message)].

    ``frames``: all images; ``desired``: the desireds in the order they took effect.
    """

    frames: list
    desired: list
    streams: dict = field(default_factory=dict)
    recorded: dict = field(default_factory=dict)   # topic → [(bag ns, rosbags message)]
    sets: list = field(default_factory=list)
    pipeline: Pipeline | None = None


def recorded_sets(reader) -> list[str]:
    """Return the feature sets recorded in a bag."""
    have = {c.topic for c in reader.connections}
    return [n for n in FEATURE_SETS if features_topic(n) in have]


def regenerate(path, settings: Settings, sets: list[str] | None = None,
               desired: str = 'auto', servo: bool = False,
               image_topic: str = IMAGE_TOPIC, info_topic: str = INFO_TOPIC) -> Result:
    """Run the bag's images through detector → features (→ servo) offline."""
    from geometry_msgs.msg import TwistStamped

    from sphere_servo.ros.conversions import twist_from_array
    from sphere_servo.ros.vectors import features_msg, measurement_msg
    pipe = Pipeline(settings)
    with bag(path) as reader:
        if topic_name(info_topic) not in {c.topic for c in reader.connections}:
            raise BagError(f'topic {topic_name(info_topic)} (the intrinsics) not in bag')
        names = list(sets or recorded_sets(reader) or ['s_n'])
        recorded = {t: read_topic(reader, t) for t in
                    [MEAS_TOPIC, TWIST_TOPIC, STATE_TOPIC, *map(features_topic, names)]}
        cameras = Cameras(pipe, read_topic(reader, topic_name(info_topic)))
        frames = [pipe.frame(i, ts, img, cameras(ts, header_ns(img.header)))
                  for i, ts, img in iter_image_msgs(reader, topic_name(image_topic))]
    if not frames:
        raise BagError(f'no images on {topic_name(image_topic)}')
    rec_sets = {n: recorded[features_topic(n)] for n in names}
    law_set = settings.servo.feature_set
    want = list(dict.fromkeys([*names, law_set] if servo else names))
    ds = find_desired(pipe, frames, desired, rec_sets, cameras, want, recorded[MEAS_TOPIC])
    res = Result(frames, ds, recorded=recorded, sets=names, pipeline=pipe)
    res.streams[MEAS_TOPIC] = [(f.bag_ns, measurement_msg(f.meas, f.header)) for f in frames]
    streams = {features_topic(n): [] for n in want}
    twists = []
    disabled, answered = state_stamps(res.recorded.get(STATE_TOPIC) or [])
    for f, d in active(res):
        if pipe.desired_obs is not d.obs:
            _anchor(pipe, d, want)
        out = pipe.features_of(f)
        for n in want:
            fs = out.values.get(n)
            streams[features_topic(n)].append(
                (f.bag_ns, features_msg(n, f.header, *((fs.s, fs.s_star) if fs else ()))))
        if servo and (not answered or f.stamp in answered):
            cmd = pipe.twist(f.stamp, out.values.get(law_set), enabled=f.stamp not in disabled)
            if isinstance(cmd, ServoCommand):
                twists.append((f.bag_ns, TwistStamped(header=f.header,
                                                      twist=twist_from_array(cmd.twist))))
    res.streams.update({features_topic(n): streams[features_topic(n)] for n in names})
    if servo:
        res.streams[TWIST_TOPIC] = twists
    return res


def state_stamps(states: list) -> tuple[set[int], set[int]]:
    """
    Return the stamps the recorded servo answered while disabled, and of all it answered.

    From the recorded ``servo/state``: the servo's ``~/enable`` switch is not in the images
    (message ``disabled``); each answer carries the value ``stamp`` (both sets are empty
    when the bag has no servo states).
    """
    disabled, answered = set(), set()
    for _, m in states:
        vals = {kv.key: kv.value for kv in m.values}
        if 'stamp' not in vals:
            continue
        try:
            t = parse_stamp(vals['stamp'])
        except ValueError:
            continue
        answered.add(t)
        if m.message == ServoState.DISABLED.value:
            disabled.add(t)
    return disabled, answered


def active(res: Result):
    """Yield (frame, its desired) for every frame that gets features."""
    ds = res.desired
    k = -1
    for f in res.frames:
        while k + 1 < len(ds) and ds[k + 1].start <= f.index:
            k += 1
        if k >= 0:
            yield f, ds[k]


def _anchor(pipe: Pipeline, d: Desired, names: list[str]) -> None:
    try:
        pipe.set_desired(d.obs, names)
    except GeometryError as exc:
        raise BagError(f'the desired ({d.how}) cannot anchor {names}: {exc}') from None
