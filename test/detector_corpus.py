"""
A fixed corpus of detector inputs and a flat record of a Detection (not a test).

The corpus pins the detector's results (``test_detector_reference``): speed work on the
detector must not change any of them. Seeded frames of the project's renderer and of the
independent one (test/independent_render.py): clean, noisy, dim, cluttered, checkerboard and
noise textures straddling the body threshold, distractor spheres and discs, far and tiny,
grazing and cut by the border, too close, no target; the special sphere, the CC target and
the balloon; plumb_bob, fisheye and unified cameras, HD; bgr8 and mono8; wrong intrinsics;
the small-circle path on a pinhole.

``python test/detector_corpus.py`` (from the repository root, ``PYTHONPATH=$PWD``) writes
the reference file with the detector of the checked-out code: run it only with a detector
whose results are the ones to keep.
"""
from __future__ import annotations

import gzip
import hashlib
import json
import math
from pathlib import Path
import sys

from camera_cases import MODELS
from independent_scenes import CAMERAS, scenes, wide_scenes
import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import balloon, cc_target, special_sphere
from sphere_servo.vision.backgrounds import Distractor
from sphere_servo.vision.detector import Detector
from sphere_servo.vision.poses import random_poses
from sphere_servo.vision.renderer import Renderer
from wide_cameras import twin, WIDE

REFERENCE = Path(__file__).resolve().parent / 'data' / 'detector_reference.json.gz'
CAM = CameraIntrinsics()
HD = CameraIntrinsics(px=900.0, py=900.0, u0=640.0, v0=360.0, width=1280, height=720)
# the paper's calibration error: px +35 %, py +30 %, u0 −25 %, v0 +27 %
WRONG = CameraIntrinsics(px=600.0 * 1.35, py=600.0 * 1.30, u0=320.0 * 0.75, v0=240.0 * 1.27)


def _at(x: float, y: float, z: float, seed: int) -> pin.SE3:
    """Return a seeded random orientation at the camera-frame position (x, y, z)."""
    rng = np.random.default_rng(seed)
    return pin.SE3(pin.exp3(rng.normal(size=3) * 2.0), np.array([x, y, z]))


def _field_pose(cam, k: int) -> pin.SE3:
    """Return a seeded pose 0.2–0.6 m away, up to 0.8 of the camera's field off its axis."""
    rng = np.random.default_rng(500 + k)
    field = min(getattr(cam, 'max_angle', 0.6), 1.6)
    th, az = rng.uniform(0.0, 0.8 * field), rng.uniform(0.0, 2 * math.pi)
    b = np.array([math.sin(th) * math.cos(az), math.sin(th) * math.sin(az), math.cos(th)])
    return pin.SE3(pin.exp3(rng.normal(size=3) * 2.0), b * rng.uniform(0.2, 0.6))


def cases():
    """
    Yield ``(name, detector_factory, image, encoding, camera)`` for every corpus frame.

    ``detector_factory`` is a zero-argument callable (the detectors are built per case
    group, so a detector's per-camera state carries over between its frames as in a node).
    """
    sp, cc, bal = special_sphere(), cc_target(), balloon()
    dets = {}

    def det(key, target, **kw):
        if key not in dets:
            dets[key] = Detector.for_target(target, **kw)
        return lambda: dets[key]

    # the project's renderer, pinhole VGA: backgrounds, noise, light, distractors
    looks = [('gradient', {}), ('clutter', {'seed': 9}), ('flat', {}),
             ('checker', {'levels': (40, 70), 'seed': 1}),
             ('noise', {'levels': (30, 80), 'seed': 2}),
             ('gradient', {'noise_sigma': 3.0, 'seed': 3}),
             ('clutter', {'gain': 0.7, 'seed': 1}),
             ('gradient', {'blur_sigma': 0.8, 'noise_sigma': 2.0, 'seed': 5}),
             ('checker', {'levels': (45, 62), 'seed': 4, 'distractors': [
                 Distractor('sphere', (-0.1, 0.07, 0.6), 0.05, (250, 250, 250))]}),
             ('noise', {'levels': (20, 95), 'seed': 6, 'distractors': [
                 Distractor('disc', (0.12, -0.05, 0.7), 0.04, (235, 235, 225)),
                 Distractor('sphere', (-0.15, -0.08, 0.9), 0.05, (200, 190, 180))]})]
    for tname, target, n in (('special', sp, 3), ('cc', cc, 2), ('balloon', bal, 1)):
        for li, (bg, kw) in enumerate(looks):
            ren = Renderer(CAM, target, background=bg, **kw)
            poses = random_poses(target, CAM, n, 10 * li + 1, max_incidence=None)
            for k, M in enumerate(poses):
                yield (f'{tname}/{bg}{li}/{k}', det(tname, target), ren.render(M), 'rgb8', CAM)
    # far and tiny, grazing and cut by the border, too close, behind the camera
    ren = Renderer(CAM, sp, background='clutter', seed=11)
    odd = [(0.0, 0.0, 2.5), (0.3, -0.2, 3.5), (0.0, 0.0, 6.0), (0.27, 0.0, 0.5),
           (-0.27, 0.17, 0.5), (0.0, 0.22, 0.55), (0.3, 0.22, 0.5), (0.0, 0.0, 0.07),
           (0.0, 0.0, 0.12), (0.0, 0.0, -0.5), (0.55, 0.0, 0.6)]
    for k, p in enumerate(odd):
        yield f'special/odd/{k}', det('special', sp), ren.render(_at(*p, k)), 'rgb8', CAM
    for bg in ('gradient', 'noise'):
        ren = Renderer(CAM, sp, background=bg, levels=(40, 70), noise_sigma=2.0, seed=13)
        for k, z in enumerate((1.2, 1.6, 2.2, 3.0)):
            yield (f'special/far_{bg}/{k}', det('special', sp),
                   ren.render(_at(0.04 * z, -0.03 * z, z, 20 + k)), 'rgb8', CAM)
    # encodings and intrinsics: bgr8, mono8, wrong intrinsics, the small-circle path
    ren = Renderer(CAM, sp, background='checker', levels=(40, 70), seed=7)
    for k, M in enumerate(random_poses(sp, CAM, 4, 77)):
        img = ren.render(M)
        yield f'special/bgr8/{k}', det('special', sp), np.ascontiguousarray(img[..., ::-1]), \
            'bgr8', CAM
        yield (f'special/mono8/{k}', det('special', sp),
               np.ascontiguousarray(img.max(axis=2)), 'mono8', CAM)
        yield f'special/wrong_K/{k}', det('special', sp), img, 'rgb8', WRONG
        yield (f'special/small_circle/{k}', det('special/sc', sp, conic_path=False), img,
               'rgb8', CAM)
    # HD
    ren = Renderer(HD, sp, background='noise', levels=(40, 70), seed=8)
    for k, M in enumerate(random_poses(sp, HD, 3, 88, max_incidence=None)):
        yield f'special/hd/{k}', det('special', sp), ren.render(M), 'rgb8', HD
    # camera models through the project's renderer, poses over the field
    for mname, cam in MODELS.items():
        if mname == 'pinhole':
            continue
        ren = Renderer(cam, sp, background='gradient', noise_sigma=2.0, seed=12)
        for k in range(3):
            yield (f'models/{mname}/{k}', det(f'model/{mname}', sp),
                   ren.render(_field_pose(cam, 3 * len(mname) + k)), 'rgb8', cam)
    # the independent renderer: textures, distractors, lights; wide cameras
    for kind, seed in ((None, 31), ('sphere', 32), ('disc', 33)):
        for k, (img, _, _, _) in enumerate(scenes(CAMERAS['vga_f600'], sp, 5, seed,
                                                  distractor_kind=kind)):
            yield f'independent/{kind}/{k}', det('special', sp), img, 'rgb8', CAM
    for wname, cam in WIDE.items():
        for k, (img, _, _) in enumerate(wide_scenes(twin(cam), sp, 5, 41, bank=4)):
            yield f'independent/{wname}/{k}', det(f'wide/{wname}', sp), img, 'rgb8', cam


def _f(x) -> float | None:
    """Return a float as JSON keeps it exactly (None for NaN, strings for infinities)."""
    x = float(x)
    return None if math.isnan(x) else (x if math.isfinite(x) else str(x))


def _arr(a) -> list | None:
    return None if a is None else [_f(x) for x in np.asarray(a, float).ravel()]


def record(d) -> dict:
    """Return the flat, JSON-able record of a Detection: every field, every mark."""
    nd = d.not_detected
    rec = {'found': bool(d.found), 'reason': d.reason, 'conic': _arr(d.conic),
           'quality': _f(d.quality), 'residual_px': _f(d.residual_px),
           'cut_by_border': bool(d.cut_by_border), 'n_edge_points': int(d.n_edge_points),
           'coverage': _f(d.coverage), 'contour_px': _arr(d.contour_px),
           'not_detected': None if nd is None else [nd.reason.name, str(nd)],
           'sphere': None if d.sphere is None else
           {'b': _arr(d.sphere.b), 'r_delta': _f(d.sphere.r_delta),
            'quality': _f(d.sphere.quality)},
           'ellipse_px': None if d.ellipse_px is None else
           {'centre': _arr(d.ellipse_px[0]), 'axes': _arr(d.ellipse_px[1]),
            'angle_deg': _f(d.ellipse_px[2])}}
    rec['marks'] = {n: {'uv_px': _arr(m.uv_px), 'ray': _arr(m.ray), 'visible': bool(m.visible),
                        'area_px': _f(m.area_px), 'partial': bool(m.partial),
                        'missing': None if m.missing is None else str(m.missing)}
                    for n, m in sorted(d.marks.items())}
    return rec


def image_hash(img: np.ndarray) -> str:
    """Return a digest of an image's shape and pixels (the corpus must not change)."""
    h = hashlib.sha256(str(img.shape).encode())
    h.update(np.ascontiguousarray(img).tobytes())
    return h.hexdigest()[:16]


def differences(want, got, path: str = '', rel: float = 1e-9) -> list[str]:
    """
    List where two records differ: any str/bool/int/None, or a float beyond ``rel``.

    A float list (an array) is compared as a whole: ``max |a − b| ≤ rel · max |a|``, so
    that a component near zero of a unit vector is held to the vector's scale.
    """
    if isinstance(want, dict) and isinstance(got, dict):
        if set(want) != set(got):
            return [f'{path}: keys {sorted(want)} != {sorted(got)}']
        return [d for k in want for d in differences(want[k], got[k], f'{path}.{k}', rel)]
    if isinstance(want, list) and isinstance(got, list) and len(want) == len(got) \
            and all(isinstance(x, float) for x in want + got):
        a, b = np.array(want), np.array(got)
        scale = max(float(np.abs(a).max(initial=0.0)), 1e-300)
        if float(np.abs(a - b).max(initial=0.0)) <= rel * scale:
            return []
        return [f'{path}: {want} != {got}']
    if isinstance(want, float) and isinstance(got, float):
        return [] if abs(want - got) <= rel * max(abs(want), abs(got)) else \
            [f'{path}: {want!r} != {got!r}']
    return [] if want == got else [f'{path}: {want!r} != {got!r}']


def load_reference() -> dict:
    """Return the recorded reference: case name → ``{'image': digest, 'detection': record}``."""
    with gzip.open(REFERENCE, 'rt') as f:
        return json.load(f)


def main() -> int:
    """Write the reference file with the detector of the checked-out code."""
    out = {}
    for name, make, img, enc, cam in cases():
        if name in out:
            raise SystemExit(f'duplicate case name {name}')
        out[name] = {'image': image_hash(img), 'detection': record(make().detect(img, enc, cam))}
    REFERENCE.parent.mkdir(exist_ok=True)
    with gzip.open(REFERENCE, 'wt') as f:
        json.dump(out, f, indent=0, sort_keys=True)
    found = sum(r['detection']['found'] for r in out.values())
    print(f'{REFERENCE}: {len(out)} frames, {found} found')
    return 0


if __name__ == '__main__':
    sys.exit(main())
