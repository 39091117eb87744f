"""
The features' logic without ROS: measurements → the paper's feature sets and their errors.

:class:`FeaturesCore` anchors every published set (``sets``) on one desired observation and
turns each measurement into ``(s, s*)`` per set. Nothing is produced before a desired
exists; the desired of each set (:meth:`FeaturesCore.desired_features`) is published once
per teach, with the stamp of the image it came from (:attr:`FeaturesCore.desired_stamp_ns`;
0 for a pose or an image file, which are not images of the run). Desired features
(``desired_source``):

- ``teach``: :meth:`FeaturesCore.teach` makes the latest measurement the desired one
  (teach by showing);
- ``pose``: the exact projection of the target model at ``desired_cMo`` = [x y z roll pitch
  yaw] (m, rad; R = Rz Ry Rx); spherical targets only;
- ``image``: the image file ``desired_image``, detected with the intrinsics of the first
  usable camera_info (with ``intrinsics_error`` applied, as the detector does).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import cv2
import numpy as np

from sphere_servo.core.central import CentralCamera
from sphere_servo.core.features import FeatureSet, make_feature_set
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.measurement import Observation, observe
from sphere_servo.core.targets import make_target, Target
from sphere_servo.pipeline.common import Level, NodeStatus, Refusal, Reply, stamp_text
from sphere_servo.pipeline.detector import camera_from_info
from sphere_servo.pipeline.params import FeaturesParams, ParameterError
from sphere_servo.pipeline.vectors import Measurement, SetFeatures
from sphere_servo.sim.arm import pose_from_xyz_rpy
from sphere_servo.vision.detector import Detector


class DesiredSource(str, Enum):
    """Where the desired features come from (the ``desired_source`` values)."""

    TEACH = 'teach'
    POSE = 'pose'
    IMAGE = 'image'


class FeaturesState(str, Enum):
    """What the features node is doing (the value is the published status message)."""

    WAITING = 'waiting'          # no measurement yet
    NO_DESIRED = 'no desired'    # measurements come, no desired yet: nothing published
    TRACKING = 'tracking'        # features of every set published
    TARGET_LOST = 'target lost'  # the target or a mark is lost: empty features published


@dataclass(frozen=True)
class Taught(Reply):
    """The outcome of a teach, and the taught image's stamp (if it succeeded)."""

    stamp_ns: int | None = None


@dataclass(slots=True)
class FeaturesOutput:
    """
    The features of one measurement: set name → :class:`SetFeatures`.

    ``lost``: why the target counts as lost ('' when not); then ``values`` is empty and
    every set is published empty.
    """

    stamp_ns: int
    values: dict[str, SetFeatures] = field(default_factory=dict)
    lost: str = ''


def features_target(p: FeaturesParams) -> Target:
    """Return the target model of the features (a balloon is servoed as a special sphere)."""
    if p.target_kind == 'balloon':
        return make_target('balloon')
    return make_target(p.target_kind, radius=p.target_radius)


def observation_from_image(bgr: np.ndarray, target: Target, camera: CentralCamera,
                           ) -> Observation:
    """Detect ``target`` in a bgr8 image; raise ValueError or GeometryError if unusable."""
    return Detector.for_target(target).detect(bgr, 'bgr8', camera).to_observation(target.kind)


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as bgr8; ParameterError when it is not a readable image file."""
    path = Path(path)
    if not path.is_file():
        raise ParameterError(f'desired_image {str(path)!r} is not a file')
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ParameterError(f'desired_image {str(path)!r} is not a readable image')
    return bgr


class FeaturesCore:
    """The ``features`` node's logic (see the module docstring)."""

    def __init__(self, params: FeaturesParams):
        """Set the desired from a pose or load the desired image; ParameterError if unusable."""
        self.params = params
        self.source = DesiredSource(params.desired_source)
        self.target = features_target(params)
        self.kind = self.target.kind
        self.sets: dict[str, FeatureSet] = {}
        self.latest: tuple[int, Measurement] | None = None  # (stamp, measurement)
        self.desired_bgr: np.ndarray | None = None
        self.desired_stamp_ns: int | None = None  # the image the desired came from
        self.last: FeaturesOutput | None = None
        if self.source is DesiredSource.POSE:
            if not self.target.is_sphere:
                raise ParameterError("desired_source 'pose' needs a spherical target model")
            cMo = pose_from_xyz_rpy(params.desired_cMo[:3], params.desired_cMo[3:])
            try:
                self.set_desired(observe(cMo, self.target), 0)
            except GeometryError as exc:
                raise ParameterError(f'desired_cMo does not show the target: {exc}') from None
        elif self.source is DesiredSource.IMAGE:
            self.desired_bgr = read_image(params.desired_image)

    @property
    def names(self) -> tuple[str, ...]:
        """Return the names of the published sets."""
        return self.params.sets

    @property
    def has_desired(self) -> bool:
        """Whether a desired is set (features are produced only then)."""
        return bool(self.sets)

    def observation(self, meas: Measurement) -> Observation:
        """Return the observation of a measurement (MeasurementError if lost)."""
        return meas.observation(self.kind)

    def set_desired(self, obs: Observation, stamp_ns: int) -> None:
        """
        Anchor every published set on ``obs``, of the image stamped ``stamp_ns``.

        Raises GeometryError if it cannot be (the desired held stays).
        """
        self.sets = {name: make_feature_set(name, obs) for name in self.params.sets}
        self.desired_stamp_ns = int(stamp_ns)

    def desired_features(self) -> dict[str, np.ndarray]:
        """Return s* of every published set ({} before a desired is set)."""
        return {name: fs.desired for name, fs in self.sets.items()}

    def describe_desired(self) -> str:
        """Return a line on the desired features (for the log)."""
        s_n = self.sets.get('s_n')
        return 'desired features set' + (
            f': s*_n,t = {s_n.desired[:3].round(4).tolist()}' if s_n else '')

    def on_camera_info(self, width: int, height: int, k: Sequence[float],
                       d: Sequence[float] | None,
                       distortion_model: str = 'plumb_bob') -> Observation | Refusal | None:
        """
        Detect the desired image with this camera (``desired_source: image``).

        Returns the desired observation set, a refusal (the image is unusable with this
        camera), or None when there is nothing to do (another source, or already set).
        """
        if self.source is not DesiredSource.IMAGE or self.sets:
            return None
        cam = camera_from_info(width, height, k, d, self.params.intrinsics_error,
                               distortion_model)
        try:
            if isinstance(cam, Refusal):
                raise ValueError(cam.reason)
            obs = observation_from_image(self.desired_bgr, self.target, cam)
            self.set_desired(obs, 0)
        except (ValueError, GeometryError) as exc:
            return Refusal(f'desired image {self.params.desired_image!r} unusable: {exc}')
        return obs

    def teach(self) -> Taught:
        """Make the latest measurement the desired one (teach by showing)."""
        if self.latest is None:
            return Taught(False, 'no measurement received yet')
        stamp_ns, meas = self.latest
        try:
            self.set_desired(self.observation(meas), stamp_ns)
        except GeometryError as exc:
            return Taught(False, f'cannot teach this image: {exc}')
        return Taught(True, 'desired features taught from the image stamped '
                      f'{stamp_text(stamp_ns)}', stamp_ns)

    def on_measurement(self, stamp_ns: int, meas: Measurement) -> FeaturesOutput | None:
        """Return the features of every set (None before a desired is set)."""
        self.latest = (stamp_ns, meas)
        self.last = None
        if not self.sets:
            return None
        try:
            obs = self.observation(meas)
            values = {name: SetFeatures(fs.features(obs), fs.desired)
                      for name, fs in self.sets.items()}
        except GeometryError as exc:
            self.last = FeaturesOutput(stamp_ns, lost=str(exc))
        else:
            self.last = FeaturesOutput(stamp_ns, values)
        return self.last

    def status(self) -> NodeStatus:
        """
        Return the node's status after the latest measurement.

        Values: ``sets``, ``desired_source``, ``stamp`` (the latest measurement's image),
        ``desired_stamp`` (once a desired is set), ``reason`` (target lost).
        """
        values = {'sets': ','.join(self.names), 'desired_source': self.source.value}
        if self.latest is not None:
            values['stamp'] = stamp_text(self.latest[0])
        if self.desired_stamp_ns is not None:
            values['desired_stamp'] = stamp_text(self.desired_stamp_ns)
        if self.latest is None:
            state = FeaturesState.WAITING
        elif self.last is None:
            state = FeaturesState.NO_DESIRED
        elif self.last.lost:
            state, values['reason'] = FeaturesState.TARGET_LOST, self.last.lost
        else:
            state = FeaturesState.TRACKING
        level = Level.WARN if state is FeaturesState.TARGET_LOST else Level.OK
        return NodeStatus(state, level, values)
