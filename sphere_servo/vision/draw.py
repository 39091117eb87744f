"""A detection drawn on its image (no ROS): the detector node's overlay, the gallery."""
from __future__ import annotations

import cv2
import numpy as np

from sphere_servo.core.types import Image
from sphere_servo.vision.cone import CONTOUR_SAMPLES
from sphere_servo.vision.detector import Detection

GREEN, CYAN, WHITE = (0, 255, 0), (255, 255, 0), (255, 255, 255)


def draw_detection(rgb: Image, det: Detection, *, marker_px: int = 12, labels: bool = True,
                   truth_uv=(), status: bool = False) -> Image:
    """
    Draw a detection on a copy of an rgb8 image.

    Drawn: each true mark position of ``truth_uv`` (pixels, circles, white), the fitted
    ellipse (green; through a camera model the detection's contour, its cone projected),
    each visible mark's centre (a cross of ``marker_px``, named if ``labels``) and, with
    ``status``, a line saying what was found (quality, residual, marks) or why not.
    """
    out = rgb.copy()
    for u, v in truth_uv:
        cv2.circle(out, (int(round(u)), int(round(v))), 6, WHITE, 1, cv2.LINE_AA)
    if det.found and det.contour_px is not None and len(det.contour_px) >= 2:
        # through a camera model the silhouette is its cone projected, not an ellipse
        pts = np.round(det.contour_px * 16).astype(np.int32)[:, None]
        closed = len(det.contour_px) == CONTOUR_SAMPLES
        cv2.polylines(out, [pts], closed, GREEN, 1, cv2.LINE_AA, shift=4)
    elif det.found and det.ellipse_px is not None:
        (uc, vc), (a1, a2), ang = det.ellipse_px
        cv2.ellipse(out, ((uc, vc), (a1, a2), ang), GREEN, 1, cv2.LINE_AA)
    for name, mark in det.marks.items():
        if mark.visible and mark.uv_px is not None:
            u, v = (int(round(c)) for c in mark.uv_px)
            cv2.drawMarker(out, (u, v), CYAN, cv2.MARKER_CROSS, marker_px, 1)
            if labels:
                cv2.putText(out, name, (u + 6, v - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4, CYAN, 1,
                            cv2.LINE_AA)
    if status:
        text = (f'found  q={det.quality:.1e}  rms={det.residual_px:.2f}px  '
                f'marks={",".join(k for k, m in det.marks.items() if m.visible)}'
                if det.found else f'NOT FOUND: {det.reason}')
        cv2.putText(out, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, WHITE, 1, cv2.LINE_AA)
    return out
