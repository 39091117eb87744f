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
  usable camera_info (with ``intrinsics_error`` applied and reduced by its binning and roi,
  as the detector does: the file is an image of the published stream).

Every measurement is checked before use (:func:`~sphere_servo.core.measurement.
validated_observation`, with the field of the latest usable camera_info; a pinhole's until
one comes): one that no camera can measure (``r_δ ∉ (0, 1)``, ``b`` or a mark ray not a unit
vector, a surface mark off the sphere, the silhouette outside the field) is *refused*: its
features are published empty (target lost: the servo stops) and the output carries the
typed :class:`~sphere_servo.core.validation.Violation`. A refused measurement is never
taught.

With ``desired_file`` (teach), each teach writes the taught measurement, its stamp and
frame to that file (JSON, atomically: a crash leaves the old file or the new one), and a
features node that starts reloads it: the desired survives a restart, with the stamp of the
image it was taught from.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
import json
import os
from pathlib import Path

import cv2
import numpy as np

from sphere_servo.core.central import CentralCamera
from sphere_servo.core.features import FeatureSet, make_feature_set
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.measurement import (Observation, observe, PINHOLE_FIELD,
                                           validated_observation)
from sphere_servo.core.targets import make_target, Target
from sphere_servo.core.validation import Violation
from sphere_servo.pipeline.common import (Level, NodeStatus, Refusal, Reply, STAMP_END_NS,
                                          stamp_text)
from sphere_servo.pipeline.detector import camera_from_info, detector_camera
from sphere_servo.pipeline.params import FeaturesParams, ParameterError
from sphere_servo.pipeline.vectors import Measurement, SetFeatures
from sphere_servo.sim.arm import CAMERA_FRAME, pose_from_xyz_rpy
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
    REFUSED = 'refused'          # a physically impossible measurement: empty features


@dataclass(frozen=True)
class Taught(Reply):
    """The outcome of a teach, and the taught image's stamp (if it succeeded)."""

    stamp_ns: int | None = None


@dataclass(slots=True)
class FeaturesOutput:
    """
    The features of one measurement: set name → :class:`SetFeatures`.

    ``lost``: why the target counts as lost ('' when not); then ``values`` is empty and
    every set is published empty. ``violation``: the bound the measurement broke, when it
    was refused as physically impossible (None when it was merely lost).
    """

    stamp_ns: int
    values: dict[str, SetFeatures] = field(default_factory=dict)
    lost: str = ''
    violation: Violation | None = None


def features_target(p: FeaturesParams) -> Target:
    """Return the target model of the features (a balloon is servoed as a special sphere)."""
    if p.target_kind == 'balloon':
        return make_target('balloon')
    return make_target(p.target_kind, radius=p.target_radius)


def observation_from_image(bgr: np.ndarray, target: Target, camera: CentralCamera,
                           ) -> Observation:
    """
    Detect ``target`` in a bgr8 image; raise ValueError or GeometryError if unusable.

    The camera must suit the image as the detector node's does (:func:`detector_camera`).
    """
    camera = detector_camera(camera, bgr.shape[1], bgr.shape[0])
    return Detector.for_target(target).detect(bgr, 'bgr8', camera).to_observation(target.kind)


DESIRED_FORMAT = 'sphere_servo desired 1'


@dataclass(frozen=True)
class KeptDesired:
    """A taught desired as ``desired_file`` keeps it: the measurement, its image's header."""

    meas: Measurement
    stamp_ns: int
    frame_id: str
    target_kind: str

    def write(self, path: str | Path) -> None:
        """Write the file atomically (a temporary file beside it, then renamed); OSError."""
        path = Path(path)
        text = json.dumps({'format': DESIRED_FORMAT, 'stamp': stamp_text(self.stamp_ns),
                           'stamp_ns': self.stamp_ns, 'frame_id': self.frame_id,
                           'target_kind': self.target_kind, 'names': list(self.meas.names),
                           'values': list(self.meas.values)}, indent=1)
        tmp = path.with_name(f'.{path.name}.{os.getpid()}.tmp')
        try:
            with open(tmp, 'w') as fh:
                fh.write(text + '\n')
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)

    @classmethod
    def read(cls, path: str | Path) -> KeptDesired:
        """Read a kept desired; ParameterError naming the file when it is not one."""
        try:
            data = json.loads(Path(path).read_text())
            if data.get('format') != DESIRED_FORMAT:
                raise ValueError(f'format {data.get("format")!r} is not {DESIRED_FORMAT!r}')
            names, values = data['names'], data['values']
            if not (isinstance(names, list) and all(isinstance(n, str) for n in names)
                    and isinstance(values, list) and all(
                        isinstance(v, (int, float)) and not isinstance(v, bool)
                        for v in values)):
                raise ValueError('names must be strings and values numbers')
            stamp = data['stamp_ns']
            if isinstance(stamp, bool) or not isinstance(stamp, int) \
                    or not 0 <= stamp < STAMP_END_NS:
                raise ValueError(f'stamp_ns must be a whole number in [0, {STAMP_END_NS}) '
                                 f'(a header stamp), got {stamp!r}')
            return cls(Measurement.of(names, [float(v) for v in values]), stamp,
                       str(data['frame_id']), str(data['target_kind']))
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ParameterError(f'desired_file {str(path)!r} is not a kept desired: '
                                 f'{type(exc).__name__}: {exc}') from None


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
        """
        Set the desired from a pose, load the desired image, or reload the desired file.

        ParameterError if one is unusable.
        """
        self.params = params
        self.source = DesiredSource(params.desired_source)
        self.target = features_target(params)
        self.kind = self.target.kind
        self.field = PINHOLE_FIELD  # of the latest usable camera_info
        self.sets: dict[str, FeatureSet] = {}
        self.latest: tuple[int, Measurement, str] | None = None  # (stamp, measurement, frame)
        self.desired_bgr: np.ndarray | None = None
        self.desired_stamp_ns: int | None = None  # the image the desired came from
        self.desired_frame_id = CAMERA_FRAME      # its frame (a teach: the image's)
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
        elif params.desired_file and Path(params.desired_file).exists():
            self._reload(params.desired_file)

    def _reload(self, path: str) -> None:
        """Set the desired kept in ``desired_file`` (ParameterError if it cannot be)."""
        kept = KeptDesired.read(path)
        if kept.target_kind != self.kind:
            raise ParameterError(f'desired_file {path!r} was taught on a {kept.target_kind!r} '
                                 f'target; this node observes a {self.kind!r} one')
        try:
            self.set_desired(self.observation(kept.meas), kept.stamp_ns)
        except GeometryError as exc:
            raise ParameterError(f'desired_file {path!r} holds an unusable measurement: '
                                 f'{exc}') from None
        self.desired_frame_id = kept.frame_id

    @property
    def names(self) -> tuple[str, ...]:
        """Return the names of the published sets."""
        return self.params.sets

    @property
    def has_desired(self) -> bool:
        """Whether a desired is set (features are produced only then)."""
        return bool(self.sets)

    def observation(self, meas: Measurement) -> Observation:
        """
        Return the observation of a measurement, checked (MeasurementError if unusable).

        Lost (a missing sphere or mark) or refused: physically impossible
        (:func:`~sphere_servo.core.measurement.validated_observation` with the camera's
        field; the error's ``violation`` then says which bound).
        """
        return validated_observation(meas.observation(self.kind), self.field)

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
                       d: Sequence[float] | None, distortion_model: str = 'plumb_bob', *,
                       binning_x: int = 0, binning_y: int = 0, roi: Sequence[int] | None = None,
                       ) -> Observation | Refusal | None:
        """
        Take the camera's field; detect the desired image with it (``desired_source: image``).

        The camera is the detector's: that of the published image, reduced by ``binning_x``,
        ``binning_y`` and ``roi`` (:func:`~sphere_servo.pipeline.detector.camera_from_info`).
        Returns the desired observation set, a refusal (the image is unusable with this
        camera), or None when there is nothing to do (another source, or already set). A
        camera_info that no camera has leaves the field as it was.
        """
        cam = camera_from_info(width, height, k, d, self.params.intrinsics_error,
                               distortion_model, binning_x=binning_x, binning_y=binning_y,
                               roi=roi)
        if not isinstance(cam, Refusal):
            self.field = cam.max_angle
        if self.source is not DesiredSource.IMAGE or self.sets:
            return None
        try:
            if isinstance(cam, Refusal):
                raise ValueError(cam.reason)
            obs = observation_from_image(self.desired_bgr, self.target, cam)
            self.set_desired(obs, 0)
        except (ValueError, GeometryError) as exc:
            return Refusal(f'desired image {self.params.desired_image!r} unusable: {exc}')
        return obs

    def teach(self) -> Taught:
        """
        Make the latest measurement the desired one (teach by showing).

        With ``desired_file`` the taught measurement is kept there; a teach whose file
        cannot be written still sets the desired, and its message says so.
        """
        if self.latest is None:
            return Taught(False, 'no measurement received yet')
        stamp_ns, meas, frame_id = self.latest
        try:
            self.set_desired(self.observation(meas), stamp_ns)
        except GeometryError as exc:
            return Taught(False, f'cannot teach this image: {exc}')
        self.desired_frame_id = frame_id
        message = f'desired features taught from the image stamped {stamp_text(stamp_ns)}'
        if self.params.desired_file:
            try:
                KeptDesired(meas, stamp_ns, frame_id, self.kind).write(self.params.desired_file)
                message += f', kept in {self.params.desired_file}'
            except OSError as exc:
                message += f', NOT kept: cannot write desired_file: {exc}'
        return Taught(True, message, stamp_ns)

    def on_measurement(self, stamp_ns: int, meas: Measurement,
                       frame_id: str = CAMERA_FRAME) -> FeaturesOutput | None:
        """Return the features of every set (None before a desired is set)."""
        self.latest = (stamp_ns, meas, frame_id)
        self.last = None
        if not self.sets:
            return None
        try:
            obs = self.observation(meas)
            values = {name: SetFeatures(fs.features(obs), fs.desired)
                      for name, fs in self.sets.items()}
        except GeometryError as exc:
            self.last = FeaturesOutput(stamp_ns, lost=str(exc),
                                       violation=getattr(exc, 'violation', None))
        else:
            self.last = FeaturesOutput(stamp_ns, values)
        return self.last

    def status(self) -> NodeStatus:
        """
        Return the node's status after the latest measurement.

        Values: ``sets``, ``desired_source``, ``stamp`` (the latest measurement's image),
        ``desired_stamp`` (once a desired is set), ``reason`` (target lost or refused).
        Levels: OK, WARN when the target is lost, ERROR for a refused measurement.
        """
        values = {'sets': ','.join(self.names), 'desired_source': self.source.value}
        if self.latest is not None:
            values['stamp'] = stamp_text(self.latest[0])
        if self.desired_stamp_ns is not None:
            values['desired_stamp'] = stamp_text(self.desired_stamp_ns)
        level = Level.OK
        if self.latest is None:
            state = FeaturesState.WAITING
        elif self.last is None:
            state = FeaturesState.NO_DESIRED
        elif self.last.violation is not None:
            state, level, values['reason'] = FeaturesState.REFUSED, Level.ERROR, self.last.lost
        elif self.last.lost:
            state, level, values['reason'] = FeaturesState.TARGET_LOST, Level.WARN, \
                self.last.lost
        else:
            state = FeaturesState.TRACKING
        return NodeStatus(state, level, values)
