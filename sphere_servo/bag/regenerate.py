"""
Regenerate a bag's pipeline streams offline: images → measurements → features (→ twists).

:func:`regenerate` runs every recorded image (``sensor_msgs/Image`` or ``CompressedImage``)
through the nodes' cores (:class:`~sphere_servo.bag.offline.Pipeline`) with the desired
found in the bag (:mod:`sphere_servo.bag.desired`). With auto/stamp one features message is
made for every image after the taught one (as live); with pose/image for every image. Each
message carries its image's header, and each desired the taught image's (a zero stamp for
pose/image). The open-loop servo answers exactly the images the recorded servo answered
(its ``servo/state`` says which: it skips superseded or late ones), with the servo core's
own rule for a repeated image. Recorded twists with a zero stamp (the servo's watchdog:
they answer no image) are not compared.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from sphere_servo.bag.bagio import bag, BagError, on_topics, topic_name
from sphere_servo.bag.desired import Desired, find_desired
from sphere_servo.bag.offline import (Cameras, desired_topic, features_topic, header_ns,
                                      IMAGE_TOPIC, INFO_TOPIC, iter_image_msgs, MEAS_TOPIC,
                                      Pipeline, read_topic, Settings, STATE_TOPIC,
                                      TWIST_TOPIC)
from sphere_servo.core.features import FEATURE_SETS
from sphere_servo.core.geometry import GeometryError
from sphere_servo.pipeline.servo import ServoCommand, ServoState


@dataclass
class Result:
    """
    The regenerated streams: topic → [(bag ns, rclpy message)].

    ``frames``: all images; ``desired``: the desireds in the order they took effect;
    ``warnings``: what a user must hear about the run (the reader's warnings on the bag,
    images the detector rejected).
    """

    frames: list
    desired: list
    warnings: list = field(default_factory=list)
    streams: dict = field(default_factory=dict)
    recorded: dict = field(default_factory=dict)   # topic → [(bag ns, rosbags message)]
    sets: list = field(default_factory=list)
    pipeline: Pipeline | None = None


def recorded_sets(reader) -> list[str]:
    """Return the feature sets recorded in a bag."""
    have = {topic_name(c.topic) for c in reader.connections}
    return [n for n in FEATURE_SETS if features_topic(n) in have]


def regenerate(path, settings: Settings, sets: list[str] | None = None,
               desired: str = 'auto', servo: bool = False,
               image_topic: str = IMAGE_TOPIC, info_topic: str = INFO_TOPIC) -> Result:
    """Run the bag's images through detector → features (→ servo) offline."""
    from geometry_msgs.msg import TwistStamped
    from std_msgs.msg import Header

    from sphere_servo.ros.conversions import twist_from_array
    from sphere_servo.ros.vectors import features_msg, measurement_msg
    from sphere_servo.sim.arm import CAMERA_FRAME
    pipe = Pipeline(settings)
    with bag(path) as reader:
        if not on_topics(reader, [info_topic]):
            raise BagError(f'topic {topic_name(info_topic)} (the intrinsics) not in bag')
        names = list(sets or recorded_sets(reader) or ['s_n'])
        recorded = {t: read_topic(reader, t) for t in
                    [MEAS_TOPIC, TWIST_TOPIC, STATE_TOPIC, *map(features_topic, names),
                     *map(desired_topic, FEATURE_SETS)]}
        cameras = Cameras(pipe, read_topic(reader, topic_name(info_topic)))
        frames = [pipe.frame(i, ts, img, cameras(ts, header_ns(img.header)))
                  for i, ts, img in iter_image_msgs(reader, topic_name(image_topic))]
        warnings = list(reader.warnings)  # e.g. messages it does not read: say so
    if not frames:
        raise BagError(f'no images on {topic_name(image_topic)}')
    rejected = rejections(frames, cameras, topic_name(image_topic))
    recorded[TWIST_TOPIC] = [(t, m) for t, m in recorded[TWIST_TOPIC] if header_ns(m.header)]
    rec_sets = {n: recorded[features_topic(n)] for n in names}
    rec_desired = {n: recorded[desired_topic(n)] for n in FEATURE_SETS}
    law_set = settings.servo.feature_set
    want = list(dict.fromkeys([*names, law_set] if servo else names))
    ds = find_desired(pipe, frames, desired, rec_sets, rec_desired, cameras)
    res = Result(frames, ds, recorded=recorded, sets=names, pipeline=pipe,
                 warnings=warnings + ([rejected] if rejected else []))
    res.streams[MEAS_TOPIC] = [(f.bag_ns, measurement_msg(f.meas, f.header)) for f in frames]
    streams = {features_topic(n): [] for n in want}
    streams.update({desired_topic(n): [] for n in want})
    twists = []
    disabled, answered = state_stamps(res.recorded.get(STATE_TOPIC) or [])
    for f, d in active(res):
        if pipe.desired_obs is not d.obs:
            _anchor(pipe, d, want)
            hdr = d.frame.header if d.frame is not None else Header(frame_id=CAMERA_FRAME)
            for n, s_star in pipe.features.desired_features().items():
                streams[desired_topic(n)].append((f.bag_ns, features_msg(n, hdr, s_star)))
        out = pipe.features_of(f)
        for n in want:
            fs = out.values.get(n)
            streams[features_topic(n)].append(
                (f.bag_ns, features_msg(n, f.header, None if fs is None else fs.s)))
        if servo and (not answered or f.stamp in answered):
            cmd = pipe.twist(f.stamp, out.values.get(law_set), enabled=f.stamp not in disabled)
            if isinstance(cmd, ServoCommand):
                twists.append((f.bag_ns, TwistStamped(header=f.header,
                                                      twist=twist_from_array(cmd.twist))))
    res.streams.update({t: streams[t] for n in names
                        for t in (desired_topic(n), features_topic(n))})
    if servo:
        res.streams[TWIST_TOPIC] = twists
    return res


def rejections(frames: list, cameras: Cameras, topic: str) -> str:
    """
    Say how many images the detector rejected, and why the first was ('' if none was).

    Raises BagError when it rejected every one: nothing could be regenerated (a camera_info
    refused, missing or of another size), and a table of empty features would hide it.
    """
    rejected = [f for f in frames if f.rejected]
    if not rejected:
        return ''
    why = rejected[0].rejected + (f' (camera_info refused: {cameras.refused[0]})'
                                  if cameras.refused else '')
    text = f'{len(rejected)} of {len(frames)} images on {topic} rejected by the detector: {why}'
    if len(rejected) == len(frames):
        raise BagError(text)
    return text


def state_stamps(states: list) -> tuple[set[int], set[int]]:
    """
    Return the stamps the recorded servo answered while disabled, and of all it answered.

    From the recorded ``servo/state``: the servo's ``~/enable`` switch is not in the images
    (message ``disabled``); each answer carries its image's header, the watchdog's states a
    zero stamp (both sets are empty when the bag has no servo states).
    """
    disabled, answered = set(), set()
    for _, m in states:
        t = header_ns(m.header)
        if not t or not len(m.status):
            continue
        answered.add(t)
        if m.status[0].message == ServoState.DISABLED.value:
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
        pipe.set_desired(d.obs, names, d.frame.stamp if d.frame is not None else 0)
    except GeometryError as exc:
        raise BagError(f'the desired ({d.how}) cannot anchor {names}: {exc}') from None
