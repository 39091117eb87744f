"""
The nodes' cores fed from a bag (no ROS graph): detector → features → servo, open loop.

:class:`Pipeline` runs a recorded image through :class:`~sphere_servo.pipeline.detector.
DetectorCore`, its measurement through :class:`~sphere_servo.pipeline.features.FeaturesCore`
and the features through :class:`~sphere_servo.pipeline.servo.ServoCore` (the twist is
computed, nothing moves), with the nodes' parameters (:class:`Settings`). The messages it
returns are the ones the nodes would publish, built by the same codecs.
"""
from __future__ import annotations

from dataclasses import dataclass

from sphere_servo.bag.bagio import (BagError, image_connections, is_compressed, iter_raw,
                                    on_topics, topic_name)
from sphere_servo.core.central import CentralCamera
from sphere_servo.core.measurement import Observation
from sphere_servo.pipeline.common import Refusal, stamp_ns
from sphere_servo.pipeline.config import load_node_params, section
from sphere_servo.pipeline.detector import camera_from_msg, DetectorCore, DetectStatus
from sphere_servo.pipeline.features import FeaturesCore, FeaturesOutput
from sphere_servo.pipeline.params import DetectorParams, FeaturesParams, ServoParams
from sphere_servo.pipeline.servo import ServoCommand, ServoCore, Unanswered
from sphere_servo.pipeline.vectors import Measurement, SetFeatures

IMAGE_TOPIC, INFO_TOPIC = '/camera/image_raw', '/camera/camera_info'
MEAS_TOPIC, TWIST_TOPIC = '/detector/measurement', '/camera/cmd_vel'
STATE_TOPIC = '/servo/state'
TOL = 1e-9
JOINT_STATE = 'sensor_msgs/msg/JointState'
#: the type the nodes publish on each topic of a run (``/features/...``: JointState)
TOPIC_TYPES = {INFO_TOPIC: 'sensor_msgs/msg/CameraInfo', MEAS_TOPIC: JOINT_STATE,
               TWIST_TOPIC: 'geometry_msgs/msg/TwistStamped',
               STATE_TOPIC: 'diagnostic_msgs/msg/DiagnosticArray'}


def features_topic(name: str) -> str:
    """Return the topic of a feature set, ``/features/<name>``."""
    return f'/features/{name}'


def desired_topic(name: str) -> str:
    """Return the topic of a feature set's desired features, ``/features/<name>/desired``."""
    return f'/features/{name}/desired'


def recorded_types(conns, types: dict[str, str]) -> list:
    """
    Return ``conns``; BagError if one is of another type than ``types`` (topic → type) says.

    The nodes publish each topic of a run as one type; a bag holding another type there (a
    different node, a different release) is not read as if it were the run's.
    """
    for c in conns:
        want = types.get(topic_name(c.topic))
        if want is None and topic_name(c.topic).startswith('/features/'):
            want = JOINT_STATE
        if want is not None and c.msgtype != want:
            raise BagError(f'topic {c.topic} holds {c.msgtype}, not the {want} the nodes '
                           'publish on it')
    return conns


def header_ns(h) -> int:
    """Return the stamp (ns) of a header (rclpy or rosbags)."""
    return stamp_ns(h.stamp.sec, h.stamp.nanosec)


@dataclass(frozen=True)
class Settings:
    """The ``detector``, ``features`` and ``servo`` parameters (validated as the nodes do)."""

    detector: DetectorParams
    features: FeaturesParams
    servo: ServoParams

    @classmethod
    def from_params(cls, params: dict | None = None) -> Settings:
        """
        Return the nodes' defaults, overridden by merged params files' sections.

        Checked as a node checks its params file (``strict``): a name the node does not
        have is refused, not ignored (the node would not start with it).
        """
        params = params or {}
        return cls(DetectorParams.from_mapping(section(params, 'detector'), strict=True),
                   FeaturesParams.from_mapping(section(params, 'features'), strict=True),
                   ServoParams.from_mapping(section(params, 'servo'), strict=True))


def load_settings(spec: str | None) -> Settings:
    """Return the settings of a scenario (name or path) or a params file, or the defaults."""
    return Settings.from_params(load_node_params(spec) if spec else None)


def ros_header(h):
    """Return a std_msgs/Header (rclpy) of a rosbags-deserialized header."""
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header
    return Header(stamp=Time(sec=int(h.stamp.sec), nanosec=int(h.stamp.nanosec)),
                  frame_id=str(h.frame_id))


@dataclass
class Frame:
    """
    One recorded image: index, bag time, header stamp (ns), header, its measurement.

    ``rejected``: why the detector rejected the image ('' if it did not).
    """

    index: int
    bag_ns: int
    stamp: int
    header: object
    meas: Measurement
    rejected: str = ''


class Pipeline:
    """``detector`` → ``features`` → ``servo``, the nodes' cores, one message at a time."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.detector = DetectorCore(settings.detector)
        # offline the desired comes from the bag (or --desired), never from the config
        self.features = FeaturesCore(settings.features.replace({'desired_source': 'teach'}))
        self.servo = ServoCore(settings.servo)
        self.target, self.kind = self.features.target, self.features.kind
        self.desired_obs: Observation | None = None

    def camera(self, info) -> CentralCamera | None:
        """Return the detector's camera of a (rosbags) CameraInfo, None if unusable."""
        cam = self.camera_or_refusal(info)
        return None if isinstance(cam, Refusal) else cam

    def camera_or_refusal(self, info) -> CentralCamera | Refusal:
        """Return the detector's camera of a (rosbags) CameraInfo, or why it has none."""
        return camera_from_msg(info, self.settings.detector.intrinsics_error)

    def frame(self, index: int, bag_ns: int, img, camera) -> Frame:
        """
        Return the :class:`Frame` of one recorded Image or CompressedImage.

        Detected as the node detects the message of its ``image_transport``: a buffer that
        cannot be read or decoded is a rejected frame, with the detector's reason.
        """
        if is_compressed(img):
            out = self.detector.detect_compressed(img.format, img.data, camera)
        else:
            out = self.detector.detect(img.height, img.width, img.step, img.encoding,
                                       img.data, camera)
        return Frame(index, bag_ns, header_ns(img.header), ros_header(img.header),
                     out.measurement,
                     out.reason if out.status is DetectStatus.REJECTED else '')

    def observation(self, meas: Measurement) -> Observation:
        """Return the features node's Observation of a measurement (MeasurementError if lost)."""
        return self.features.observation(meas)

    def set_desired(self, obs: Observation, names, stamp: int = 0) -> None:
        """
        Anchor the sets ``names`` on ``obs``, of the image stamped ``stamp``.

        The servo takes the desired of its set, if among ``names``. GeometryError if they
        cannot be anchored.
        """
        if tuple(names) != self.features.names:
            self.features = FeaturesCore(self.features.params.replace({'sets': list(names)}))
        self.features.set_desired(obs, stamp)
        self.desired_obs = obs
        s_star = self.features.desired_features().get(self.servo.feature_set)
        if s_star is not None:
            self.servo.set_desired(s_star, stamp)

    def features_of(self, f: Frame) -> FeaturesOutput:
        """Return the features of every anchored set for one frame (lost: empty)."""
        return self.features.on_measurement(f.stamp, f.meas)

    def twist(self, stamp: int, fs: SetFeatures | None,
              enabled: bool = True) -> ServoCommand | Unanswered:
        """
        Return the servo's answer to the features of the image stamped ``stamp``.

        Open loop, at the image's own time (age 0): a repeat of the image answered last is
        :class:`Unanswered`; otherwise a zero twist when disabled, lost, converged, or the
        law fails, the law's twist else.
        """
        self.servo.enable(enabled)
        return self.servo.on_features(stamp, None if fs is None else fs.s, stamp, 0.0)


def read_topic(reader, topic: str) -> list[tuple[int, object]]:
    """Return (bag ns, rosbags message) of every message on ``topic``; [] if not in the bag."""
    conns = recorded_types(on_topics(reader, [topic]), TOPIC_TYPES)
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
    """
    Yield (index, bag ns, rosbags Image or CompressedImage) in bag order.

    BagError when the topic is not in the bag or not of an image type
    (:func:`~sphere_servo.bag.bagio.image_connections`).
    """
    conns = image_connections(reader, topic)
    for i, (conn, ts, raw) in enumerate(iter_raw(reader, conns)):
        try:
            yield i, ts, reader.deserialize(raw, conn.msgtype)
        except Exception as err:
            raise BagError(f'cannot decode an image on {topic}: {err}') from None


class Cameras:
    """
    The detector's intrinsics for an image.

    The bag's camera_info with the image's stamp, else the latest one before it, else the
    first one (intrinsics do not change in a run). A refused camera_info gives no camera;
    ``refused`` keeps why, in bag order.
    """

    def __init__(self, pipeline: Pipeline, infos: list[tuple[int, object]]):
        self.infos = infos
        built = [(ts, header_ns(m.header), pipeline.camera_or_refusal(m)) for ts, m in infos]
        self.refused = [c.reason for *_, c in built if isinstance(c, Refusal)]
        built = [(ts, st, None if isinstance(c, Refusal) else c) for ts, st, c in built]
        self.by_stamp = {st: c for _, st, c in built}
        self.by_time = [(ts, c) for ts, _, c in built]

    def __call__(self, bag_ns: int, stamp: int) -> CentralCamera | None:
        """Return the camera of the image stamped ``stamp`` recorded at ``bag_ns``."""
        if stamp in self.by_stamp:
            return self.by_stamp[stamp]
        before = [c for ts, c in self.by_time if ts <= bag_ns]
        return before[-1] if before else (self.by_time[0][1] if self.by_time else None)
