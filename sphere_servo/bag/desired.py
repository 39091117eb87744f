"""
The desired features of a recorded run, found in its bag (``refeatures --desired``).

- ``auto``: the image the recorded run taught. The features node teaches the *latest*
  measurement and publishes features for every later one, so the taught image is the last
  image before the first recorded ``features/<set>`` message whose features reproduce that
  message's s* (its ``velocity``), judged on the recorded ``detector/measurement`` when
  there is one, so a changed detector still finds it. Each later change of s* is a re-teach.
- ``stamp:T``: the image with header stamp T (seconds, e.g. ``stamp:1.133333333``).
- ``pose:X,Y,Z,ROLL,PITCH,YAW``: the exact projection of the target at cMo.
- ``image:FILE``: an image file detected with the bag's first intrinsics.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sphere_servo.bag.bagio import BagError
from sphere_servo.bag.offline import Cameras, Frame, header_ns, Pipeline, TOL
from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.features import make_feature_set
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.measurement import Observation, observe
from sphere_servo.pipeline.common import parse_stamp, stamp_text
from sphere_servo.pipeline.detector import camera_from_info
from sphere_servo.pipeline.features import observation_from_image, read_image
from sphere_servo.pipeline.params import ParameterError
from sphere_servo.pipeline.vectors import Measurement
from sphere_servo.sim.arm import pose_from_xyz_rpy


@dataclass
class Desired:
    """Where the desired features came from; ``frame``: the taught frame (auto/stamp)."""

    how: str
    obs: Observation
    frame: Frame | None = None
    start: int = 0            # first frame index that gets features
    note: str = ''


def parse_desired(spec: str) -> tuple[str, object]:
    """Return (kind, argument) of a ``--desired`` spec; BagError if it is not one."""
    kind, _, arg = spec.partition(':')
    if kind == 'auto' and not arg:
        return 'auto', None
    if kind == 'stamp' and arg:
        try:
            return 'stamp', parse_stamp(arg)
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


def _from_image(pipe: Pipeline, path: Path, cameras: Cameras) -> Desired:
    """As the features node: the first camera_info, its own intrinsics_error, bgr8."""
    try:
        bgr = read_image(path)
    except ParameterError:
        raise BagError(f'--desired image {str(path)!r} is not a readable image file') from None
    if not cameras.infos:
        raise BagError('--desired image needs a camera_info in the bag')
    info = cameras.infos[0][1]
    cam = camera_from_info(info.width, info.height, info.k, info.d,
                           pipe.features.params.intrinsics_error)
    try:
        if not isinstance(cam, CameraIntrinsics):
            raise ValueError(cam.reason)
        obs = observation_from_image(bgr, pipe.target, cam)
    except (ValueError, GeometryError) as exc:
        raise BagError(f'--desired image {str(path)!r} unusable: {exc}') from None
    return Desired('image', obs, note=str(path))


def find_desired(pipe: Pipeline, frames: list[Frame], spec: str, recorded: dict,
                 cameras: Cameras, names: list[str],
                 recorded_meas: list | None = None) -> list[Desired]:
    """Return the desireds per ``--desired``, in the order they took effect (re-teaches)."""
    kind, arg = parse_desired(spec)
    if kind == 'pose':
        if not pipe.target.is_sphere:
            raise BagError('--desired pose needs a spherical target model')
        try:
            obs = observe(pose_from_xyz_rpy(arg[:3], arg[3:]), pipe.target)
        except GeometryError as exc:
            raise BagError(f'--desired pose does not show the target: {exc}') from None
        return [Desired('pose', obs, note=f'pose {arg}')]
    if kind == 'image':
        return [_from_image(pipe, arg, cameras)]
    if kind == 'stamp':
        for f in frames:
            if f.stamp == arg:
                try:
                    obs = pipe.observation(f.meas)
                except GeometryError as exc:
                    raise BagError(f'cannot teach the image stamped {stamp_text(arg)}: '
                                   f'{exc}') from None
                return [Desired('stamp', obs, f, start=f.index + 1)]
        raise BagError(f'no image stamped {stamp_text(arg)} in the bag')
    return auto_desired(pipe, frames, recorded, names, recorded_meas)


def _teach_events(msgs: list) -> list[tuple[int, np.ndarray]]:
    """
    Return (stamp of the first features message under a desired, that s*) per desired.

    For each desired the recorded stream shows: the first message, then each s* change (a
    re-teach).
    """
    events, prev = [], None
    for _, m in msgs:
        if not len(m.name):
            continue  # target lost: no s* in the message
        star = np.asarray(m.velocity, float)
        if prev is None or not np.array_equal(star, prev):
            events.append((header_ns(m.header), star))
            prev = star
    if events:  # the first desired starts with the first message, even an empty one
        events[0] = (header_ns(msgs[0][1].header), events[0][1])
    return events


def _star_error(pipe: Pipeline, name: str, meas: Measurement, star: np.ndarray) -> float:
    """Return max |s* − the s* this measurement would give| (inf if it cannot be taught)."""
    try:
        return float(np.max(np.abs(make_feature_set(name, pipe.observation(meas)).desired
                                   - star)))
    except GeometryError:
        return np.inf


def auto_desired(pipe: Pipeline, frames: list[Frame], recorded: dict, names: list[str],
                 recorded_meas: list | None = None) -> list[Desired]:
    """
    Return the taught images, one per teach (``auto`` in the module docstring).

    An image is recognised by what the live features node saw, the recorded
    ``detector/measurement`` with its stamp when the bag has it, so a changed detector
    still finds the taught image; the desired is then that image's regenerated measurement.
    """
    seen: dict[int, list] = {}
    for _, m in recorded_meas or []:
        seen.setdefault(header_ns(m.header), []).append(Measurement.of(m.name, m.position))
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
        # reproduce s*, or that image itself (teaching on the bag's very first frame)
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
