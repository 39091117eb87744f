"""Gallery: ray-cast frames with the detection drawn on top, as PNGs.

``python -m sphere_servo.experiments.gallery [--out DIR]`` (``make gallery``) writes special, CC,
balloon, border-cut, noisy and cluttered frames to ``docs/gallery/`` by default. Drawn on
each: the fitted ellipse (green), the ground-truth silhouette (thin white, spheres only),
each detected mark centre (cross in the mark's colour) and the true mark position (circle).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import balloon, cc_target, special_sphere
from sphere_servo.vision.detector import Detection, Detector
from sphere_servo.vision.renderer import Renderer

DEFAULT_OUT = Path(__file__).resolve().parents[2] / 'docs' / 'gallery'


def draw_detection(img_rgb: np.ndarray, det: Detection, cam: CameraIntrinsics,
                   target=None, cMo=None) -> np.ndarray:
    """A copy of the rgb8 image with the detection (and the ground truth if given) drawn."""
    out = img_rgb.copy()
    if target is not None and cMo is not None:
        for oP in (target.oP1, target.oP2):
            cP = cMo.act(oP)
            if cP[2] > 0:
                uv = cam.project(cP[None])[0]
                cv2.circle(out, (int(round(uv[0])), int(round(uv[1]))), 6, (255, 255, 255), 1,
                           cv2.LINE_AA)
    if det.found:
        (cu, cv_), (a, b), ang = det.ellipse_px
        cv2.ellipse(out, ((cu, cv_), (a, b), ang), (0, 255, 0), 1, cv2.LINE_AA)
    for m in det.marks.values():
        if m.visible:
            u, v = (int(round(c)) for c in m.uv_px)
            cv2.drawMarker(out, (u, v), (255, 255, 0), cv2.MARKER_CROSS, 10, 1)
    text = (f'{"found" if det.found else "NOT FOUND: " + det.reason}'
            + (f'  q={det.quality:.1e}  rms={det.residual_px:.2f}px  '
               f'marks={",".join(k for k, m in det.marks.items() if m.visible)}'
               if det.found else ''))
    cv2.putText(out, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                cv2.LINE_AA)
    return out


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
    ]


def main(argv=None) -> list[Path]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--out', type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    cam = CameraIntrinsics()
    written = []
    for name, target, kw, cMo in scenes():
        img = Renderer(cam, target, seed=1, **kw).render(cMo)
        det = Detector.for_target(target).detect(img, 'rgb8', cam)
        out = draw_detection(img, det, cam, target, cMo)
        path = args.out / f'{name}.png'
        cv2.imwrite(str(path), out[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
        written.append(path)
        print(f'{path}: {"found" if det.found else det.reason}')
    return written


if __name__ == '__main__':
    main()
