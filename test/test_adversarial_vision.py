"""
Adversarial images for the detector core: a channel order that lies about the image.

An ``rgb8`` frame published as ``bgr8`` (a driver or a bridge that mislabels its buffer) is
a real failure of camera pipelines. The special sphere's marks are red (P1) and blue (P2),
so swapping the channels swaps which mark is which: the detector must not report P1 where
the image shows P2 (the partial pose ᶜR_o, hence θu, would be wrong with no sign of it).
"""
from __future__ import annotations

import numpy as np

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import special_sphere
from sphere_servo.pipeline.detector import DetectorCore, DetectStatus
from sphere_servo.pipeline.params import DetectorParams
from sphere_servo.sim.arm import pose_from_xyz_rpy
from sphere_servo.vision.renderer import Renderer

CAM = CameraIntrinsics()
INFO = CAM.to_camera_info_fields()
CMO = pose_from_xyz_rpy([0.02, -0.01, 0.45], [0.05, -0.1, 0.3])
TARGET = special_sphere()


def detect(img: np.ndarray, encoding: str) -> dict[str, float]:
    c = DetectorCore(DetectorParams.from_mapping({}))
    c.on_camera_info(INFO['width'], INFO['height'], INFO['k'], INFO['d'])
    h, w = img.shape[:2]
    out = c.on_image(height=h, width=w, step=w * 3, encoding=encoding,
                     data=np.ascontiguousarray(img).tobytes())
    assert out.status in (DetectStatus.FOUND, DetectStatus.NOT_FOUND), out.reason
    return out.measurement.as_dict()


def true_uv(name: str) -> np.ndarray:
    """Pixel of mark ``name``'s centre: the exact projection of the target's point."""
    p = CMO.act(TARGET.marks()[name])
    return CAM.project(p[None])[0]


def test_marks_are_found_where_the_target_puts_them():
    """The baseline: the rendered rgb8 frame, labelled rgb8, gives each mark at its place."""
    m = detect(Renderer(CAM, TARGET).render(CMO), 'rgb8')
    for name in ('P1', 'P2'):
        assert np.hypot(m[f'{name}_u'] - true_uv(name)[0],
                        m[f'{name}_v'] - true_uv(name)[1]) < 2.0, name
    assert np.hypot(*(true_uv('P1') - true_uv('P2'))) > 20.0  # far apart: a swap shows


def test_an_rgb_frame_labelled_bgr_does_not_swap_the_marks():
    """Either a mark is not reported (target lost, the servo stops) or it is at its place."""
    m = detect(Renderer(CAM, TARGET).render(CMO), 'bgr8')
    for name in ('P1', 'P2'):
        if f'{name}_u' in m:
            uv = np.array([m[f'{name}_u'], m[f'{name}_v']])
            assert np.hypot(*(uv - true_uv(name))) < 2.0, (name, uv, true_uv(name))
