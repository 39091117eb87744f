"""
The desired features of a recorded run, found in its bag (``refeatures --desired``).

- ``auto``: the images the recorded run taught, one per recorded ``features/<set>/desired``
  message (a teach): its header stamp is the taught image's. The features node teaches the
  *latest* measurement and publishes features for every later one; the first recorded
  ``features/<set>`` message under a desired is the first one stamped after the taught
  image, or stamped as it (a re-publication of that image) with s = s*. If the taught image
  is not in the bag (recording began at the teach), it is the image before that message
  whose features reproduce the recorded s*.
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
from sphere_servo.core.features import make_feature_set
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.measurement import Observation, observe
from sphere_servo.pipeline.common import parse_stamp, Refusal, stamp_text
from sphere_servo.pipeline.detector import camera_from_msg
from sphere_servo.pipeline.features import observation_from_image, read_image
from sphere_servo.pipeline.params import ParameterError
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
    cam = camera_from_msg(info, pipe.features.params.intrinsics_error)
    try:
        if isinstance(cam, Refusal):
            raise ValueError(cam.reason)
        obs = observation_from_image(bgr, pipe.target, cam)
    except (ValueError, GeometryError) as exc:
        raise BagError(f'--desired image {str(path)!r} unusable: {exc}') from None
    return Desired('image', obs, note=str(path))


def find_desired(pipe: Pipeline, frames: list[Frame], spec: str, features: dict,
                 desireds: dict, cameras: Cameras) -> list[Desired]:
    """
    Return the desireds per ``--desired``, in the order they took effect (re-teaches).

    ``features``, ``desireds``: set → the recorded ``features/<set>`` and
    ``features/<set>/desired`` messages, [(bag ns, message)].
    """
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
    return auto_desired(pipe, frames, features, desireds)


def old_layout(features: dict) -> bool:
    """Tell whether recorded features carry s* in ``velocity`` (bags of the old layout)."""
    return any(len(m.velocity) for msgs in features.values() for _, m in msgs)


def _star_error(pipe: Pipeline, name: str, f: Frame, star: np.ndarray) -> float:
    """Return max |s* − the s* this frame would give| (inf if it cannot be taught)."""
    try:
        return float(np.max(np.abs(make_feature_set(name, pipe.observation(f.meas)).desired
                                   - star)))
    except GeometryError:
        return np.inf


def _first_under(msgs: list, lo: int, taught: int, star: np.ndarray, tol: float,
                 first: bool) -> int | None:
    """
    Return the index in ``msgs`` of the first features message under a desired.

    From ``lo`` on: the first stamped after the taught image ``taught``, or stamped as it
    with s = s* (for the first desired, any stamped as it: no features came before).
    """
    for k in range(lo, len(msgs)):
        m = msgs[k][1]
        st = header_ns(m.header)
        if st > taught:
            return k
        if st == taught and (first or (len(m.name) == len(star) and float(np.max(np.abs(
                np.asarray(m.position, float) - star))) <= tol)):
            return k
    return None


def auto_desired(pipe: Pipeline, frames: list[Frame], features: dict,
                 desireds: dict) -> list[Desired]:
    """Return the taught images, one per recorded desired (``auto``, module docstring)."""
    have = [n for n in ('s_n', 's_cc', 's') if desireds.get(n)]  # s's s* is 0: weakest
    if old_layout(features):
        raise BagError('this bag has the old features layout (s* in features/<set> velocity, '
                       'before features/<set>/desired existed), which refeatures no longer '
                       'reads: record the run again')
    if not have:
        raise BagError('the bag has no features/<set>/desired messages to find the taught '
                       'image: give --desired stamp:T, pose:X,Y,Z,ROLL,PITCH,YAW or image:FILE')
    name = have[0]
    msgs = features.get(name) or []
    out: list[Desired] = []
    lo_msg, lo = 0, 0  # positions in msgs and in frames
    for i, (_, dm) in enumerate(desireds[name]):
        taught, star = header_ns(dm.header), np.asarray(dm.position, float)
        tol = TOL * max(1.0, float(np.max(np.abs(star))))
        p = _first_under(msgs, lo_msg, taught, star, tol, i == 0)
        if p is None:  # no features under it recorded: from the image after the taught one
            start = next((j for j in range(lo, len(frames)) if frames[j].stamp > taught),
                         len(frames))
        else:
            # as many frames of that stamp get features as recorded messages have it
            st = header_ns(msgs[p][1].header)
            n = next((k for k in range(p, len(msgs)) if header_ns(msgs[k][1].header) != st),
                     len(msgs)) - p
            same = [j for j in range(lo, len(frames)) if frames[j].stamp == st]
            if not same:
                raise BagError(f'the features/{name} message stamped {stamp_text(st)} has no '
                               'image in the bag')
            start = same[-min(n, len(same))]
            lo_msg = p + n
        f, note = _taught_frame(pipe, frames[lo:start + 1], start - lo, taught, star, name)
        try:
            obs = pipe.observation(f.meas)
        except GeometryError as exc:
            raise BagError(f'cannot teach the image stamped {stamp_text(f.stamp)}: '
                           f'{exc}') from None
        first = frames[start].index if start < len(frames) else frames[-1].index + 1
        out.append(Desired('auto', obs, f, start=first, note=note))
        lo = start
    return out


def _taught_frame(pipe: Pipeline, upto: list[Frame], start: int, taught: int,
                  star: np.ndarray, name: str) -> tuple[Frame, str]:
    """
    Return the taught frame among ``upto`` (up to the first under it, position ``start``).

    The last stamped ``taught`` before ``start`` (or at it); if none, the frame whose
    features reproduce s* best. Returns it and a note.
    """
    same = [k for k, f in enumerate(upto) if f.stamp == taught]
    if same:
        before = [k for k in same if k < start]
        f = upto[(before or same)[-1]]
        return f, f'the image stamped {stamp_text(taught)} (features/{name}/desired)'
    # the latest of the best: the taught image is the last before the features under it
    err, k = min(((_star_error(pipe, name, f, star), -k) for k, f in enumerate(upto)),
                 default=(np.inf, 0))
    k = -k
    if not np.isfinite(err):
        raise BagError(f'the image stamped {stamp_text(taught)} that the recorded '
                       f'features/{name}/desired was taught from is not in the bag, and no '
                       'image before its first features reproduces it: give --desired '
                       'stamp:T, pose:... or image:FILE')
    f = upto[k]
    exact = err <= TOL * max(1.0, float(np.max(np.abs(star))))
    return f, (f'the image stamped {stamp_text(taught)} is not in the bag; the one stamped '
               f'{stamp_text(f.stamp)} reproduces its s*'
               + ('' if exact else f' only to {err:.3g} (the closest)'))
