"""
Gallery: ray-cast frames with the detection drawn on top, as PNGs.

``python -m sphere_servo.experiments.gallery [--out DIR]`` (``make gallery``) writes special, CC,
balloon, border-cut, noisy and cluttered frames, a far sphere on a two-level checkerboard
(40/70 on max(R, G, B): levels on both sides of a global threshold) and the target among
white distractor spheres and a disc on a noise texture, and one frame per camera model
(``camera_pinhole``, ``camera_plumb_bob``, ``camera_fisheye``, ``camera_catadioptric``: the
configs' fisheye and catadioptric cameras, the sphere far off the optical axis) to
``docs/gallery/`` by default. Drawn on each
(:func:`~sphere_servo.vision.draw.draw_detection`): the fitted ellipse, or through a camera
model the detected silhouette (green), each detected mark centre (cyan cross), the true
mark positions (white circles) and a status line.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.central import CentralCamera
from sphere_servo.core.targets import balloon, cc_target, special_sphere
from sphere_servo.pipeline.config import scenario
from sphere_servo.pipeline.params import ArmSimParams
from sphere_servo.vision.backgrounds import Distractor
from sphere_servo.vision.detector import Detector
from sphere_servo.vision.draw import draw_detection
from sphere_servo.vision.renderer import Renderer

DEFAULT_OUT = Path(__file__).resolve().parents[2] / 'docs' / 'gallery'
CAM = CameraIntrinsics()


def true_marks_uv(cam: CentralCamera, target, cMo: pin.SE3) -> list:
    """Pixels of the target's marks P1 and P2 (or P3) in the camera's field at ``cMo``."""
    out = []
    for oP in (target.oP1, target.oP2):
        cP = cMo.act(oP)
        if cam.valid(cP[None])[0]:
            out.append(cam.project(cP[None])[0])
    return out


def off_axis(deg: float, az_deg: float, dist: float, R: np.ndarray) -> pin.SE3:
    """Return a pose with the sphere's centre ``deg`` off the optical axis at ``dist`` (m)."""
    t, a = np.radians(deg), np.radians(az_deg)
    return pin.SE3(R, dist * np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a),
                                       np.cos(t)]))


def camera_scenes():
    """(name, target, renderer kwargs, cMo, camera) of the frames of each camera model."""
    def cam(name):
        return ArmSimParams.from_mapping(scenario(name).node_params('arm_sim')).camera()
    R = pin.exp3(np.array([0.35, -0.45, 0.15]))
    kw = {'background': 'checker', 'levels': (40, 70), 'noise_sigma': 2.0}
    # the sphere turned so that both marks face the camera at each pose
    Rf = pin.exp3(np.array([0.0, 1.1, 0.0])) @ R
    return [
        ('camera_pinhole', special_sphere(), kw, off_axis(20.0, 30.0, 0.35, R), CAM),
        ('camera_plumb_bob', special_sphere(), kw, off_axis(25.0, 30.0, 0.35, R),
         CameraIntrinsics(dist=(-0.25, 0.08, 0.001, -0.0015, 0.0))),
        ('camera_fisheye', special_sphere(), kw, off_axis(88.0, 200.0, 0.3, Rf.T),
         cam('fisheye')),
        ('camera_catadioptric', special_sphere(), kw, off_axis(80.0, 190.0, 0.3, Rf.T),
         cam('catadioptric')),
    ]


def scenes():
    """(name, target, renderer kwargs, cMo) of the gallery frames."""
    R = pin.exp3(np.array([0.35, -0.45, 0.15]))
    return [
        ('special', special_sphere(), {}, pin.SE3(R, np.array([0.02, 0.01, 0.35]))),
        ('cc', cc_target(), {}, pin.SE3(pin.exp3(np.array([0.5, -0.3, 0.4])),
                                        np.array([-0.02, 0.0, 0.3]))),
        ('balloon', balloon(), {}, pin.SE3(R, np.array([0.0, 0.02, 0.4]))),
        ('border_cut', special_sphere(), {}, pin.SE3(R, np.array([0.23, 0.02, 0.5]))),
        ('noisy_blur', special_sphere(), {'noise_sigma': 3.0, 'blur_sigma': 0.8},
         pin.SE3(R, np.array([-0.05, -0.03, 0.7]))),
        ('clutter_dim', special_sphere(), {'background': 'clutter', 'gain': 0.7},
         pin.SE3(R, np.array([0.03, 0.04, 0.45]))),
        ('textured', special_sphere(), {'background': 'checker', 'levels': (40, 70),
                                        'texture_px': 22, 'noise_sigma': 2.0},
         pin.SE3(R, np.array([0.12, -0.05, 0.95]))),
        ('distractors', special_sphere(),
         {'background': 'noise', 'levels': (30, 80), 'texture_px': 30, 'noise_sigma': 2.0,
          'distractors': [Distractor('sphere', (-0.1, 0.04, 0.55), 0.05, (250, 250, 250)),
                          Distractor('sphere', (0.12, 0.1, 0.5), 0.07),
                          Distractor('disc', (-0.02, -0.12, 0.6), 0.05, (250, 250, 250))]},
         pin.SE3(R, np.array([0.06, -0.01, 0.7]))),
    ]


def main(argv=None) -> list[Path]:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('--out', type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, target, kw, cMo, cam in [(*sc, CAM) for sc in scenes()] + camera_scenes():
        img = Renderer(cam, target, seed=1, **kw).render(cMo)
        det = Detector.for_target(target).detect(img, 'rgb8', cam)
        out = draw_detection(img, det, marker_px=10, labels=False,
                             truth_uv=true_marks_uv(cam, target, cMo), status=True)
        path = args.out / f'{name}.png'
        cv2.imwrite(str(path), out[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
        written.append(path)
        print(f'{path}: {"found" if det.found else det.reason}')
    return written


if __name__ == '__main__':
    main()
