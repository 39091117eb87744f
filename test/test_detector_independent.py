"""
The detector on images it did not make: the independent renderer (test/independent_render.py).

Seeded poses at 0.25–1.0 m, the sphere fully in view, the marks within 70° of the line of
sight; every frame on a checkerboard or noise texture whose two levels straddle the level a
global threshold would put between the background and the body (40/70, 30/80, 45/62,
20/95 on max(R, G, B)), a random light off the camera, sensor noise. The truth is the pose:
``s_n,t = O/r``, and ᶜR_o through the target's model (core.measurement).

A frame *publishes* when the detection gives both marks (``to_observation``); a published
frame is *wrong* when s_n,t is off by more than 1 % or θu by more than 3°. What must hold
(issue 15): no wrong frame, p99 s_n,t < 1 %, p99 θu < 1.5°, at most 5 % not published; a
distractor never wins; the caps' radius told through the target gives θu p99 < 1.5°.
"""
from __future__ import annotations

import math

from independent_render import Ball, Checker, Disc, Flat, Light, render
from independent_scenes import CAMERAS, scenes, silhouette_box, target_ball
import numpy as np
import pinocchio as pin
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.measurement import cRo_measured, MeasurementError, model_cRo_offset
from sphere_servo.core.targets import special_sphere
from sphere_servo.vision.detector import Detector
from sphere_servo.vision.reasons import Reason

TARGET = special_sphere()
# the reasons a frame without the target may give: about blobs, never the target's size
NO_SPHERE = (Reason.NO_BLOB, Reason.LOW_CONTRAST, Reason.EDGE_COVERAGE, Reason.NOT_ELLIPTICAL,
             Reason.FEW_EDGE_POINTS, Reason.RESIDUAL, Reason.NOT_A_SPHERE)


def intrinsics(cam) -> CameraIntrinsics:
    return CameraIntrinsics(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)


def measure(det, frames, cam, target=TARGET):
    """
    Errors of the published frames and the misses.

    Returns (e_s %, e_r deg) arrays over the published frames, the number of frames not
    published, and the published detections with their distractors.
    """
    ci = intrinsics(cam)
    e_s, e_r, missed, pub = [], [], 0, []
    for img, R, t, extra in frames:
        d = det.detect(img, 'rgb8', ci)
        try:
            obs = d.to_observation('special')
        except MeasurementError:
            missed += 1
            continue
        s = t / target.radius
        e_s.append(100 * np.linalg.norm(obs.sphere.s_nt - s) / np.linalg.norm(s))
        R_true = R @ model_cRo_offset(target)
        e_r.append(np.degrees(np.linalg.norm(pin.log3(cRo_measured(obs) @ R_true.T))))
        pub.append((d, extra))
    return np.array(e_s), np.array(e_r), missed, pub


def check_accuracy(e_s, e_r, missed, n):
    wrong = int(np.count_nonzero((e_s > 1.0) | (e_r > 3.0)))
    figures = (f'wrong {wrong}, not published {missed}/{n}, s_n,t median/p99 '
               f'{np.median(e_s):.3f}/{np.percentile(e_s, 99):.3f} %, θu median/p99 '
               f'{np.median(e_r):.3f}/{np.percentile(e_r, 99):.3f}°')
    assert wrong == 0, figures
    assert np.percentile(e_s, 99) < 1.0 and np.percentile(e_r, 99) < 1.5, figures
    assert missed <= 0.05 * n, figures
    return figures


@pytest.mark.slow
@pytest.mark.parametrize('name', sorted(CAMERAS))
def test_accuracy_on_textured_backgrounds(name):
    """200 frames per camera: 640×480 f 600, 1280×720 f 900, 640×480 px 450 py 480."""
    cam = CAMERAS[name]
    n = 200
    e_s, e_r, missed, _ = measure(Detector.for_target(TARGET), scenes(cam, TARGET, n, 101),
                                  cam)
    print(name, check_accuracy(e_s, e_r, missed, n))


def test_accuracy_on_textured_backgrounds_quick():
    """The inner loop's share: 30 frames at 640×480, px 450, py 480 (the hardest camera)."""
    cam = CAMERAS['vga_px450_py480']
    e_s, e_r, missed, _ = measure(Detector.for_target(TARGET), scenes(cam, TARGET, 30, 202),
                                  cam)
    check_accuracy(e_s, e_r, missed, 30)


def _on(obj, cam, u, v) -> bool:
    """Tell whether the pixel (u, v) lies in the image box of ``obj`` (a Ball or a Disc)."""
    box = silhouette_box(cam, np.asarray(obj.centre, float), obj.radius * 1.1)
    return box[0] <= u <= box[1] and box[2] <= v <= box[3]


@pytest.mark.slow
@pytest.mark.parametrize('kind', ['same', 'larger', 'closer', 'brighter', 'dimmer', 'disc'])
def test_a_distractor_never_wins(kind):
    """
    A white or body-coloured sphere or disc beside the target: the target or nothing.

    Every published frame is the target's (its features within the accuracy bounds, its
    ellipse on the target, not on the distractor); the test counts only frames that hold
    a distractor, and at most 10 % of those may be not published.
    """
    cam = CAMERAS['vga_f600']
    frames = [f for f in scenes(cam, TARGET, 50, 303, distractor_kind=kind)
              if f[3] is not None]
    assert len(frames) >= 40
    e_s, e_r, missed, pub = measure(Detector.for_target(TARGET), frames, cam)
    for d, extra in pub:
        (u, v), _, _ = d.ellipse_px
        assert not _on(extra, cam, u, v), 'the distractor was published'
    assert np.count_nonzero((e_s > 1.0) | (e_r > 3.0)) == 0, (e_s.max(), e_r.max())
    assert missed <= 0.1 * len(frames), missed


def test_a_distractor_alone_is_not_the_target():
    """The target facing away (no mark) and a white sphere: ambiguous, not published."""
    cam = CAMERAS['vga_f600']
    R = pin.exp3(np.array([math.pi, 0.0, 0.0]))                  # the marks face away
    t = np.array([0.06, 0.0, 0.6])
    white = Ball(np.array([-0.08, 0.02, 0.55]), 0.05, (250.0, 250.0, 250.0))
    objects = [target_ball(TARGET, R, t), white]
    img = render(cam, objects, Checker(40, 70, 20.0, 0.4), Light(),
                 rng=np.random.default_rng(1))
    d = Detector.for_target(TARGET).detect(img, 'rgb8', intrinsics(cam))
    assert not d.found and d.not_detected.reason is Reason.AMBIGUOUS, d.reason
    # alone, the same markless target is published as the sphere it is (marks not visible)
    img = render(cam, objects[:1], Checker(40, 70, 20.0, 0.4), Light(),
                 rng=np.random.default_rng(1))
    d = Detector.for_target(TARGET).detect(img, 'rgb8', intrinsics(cam))
    assert d.found and not any(m.visible for m in d.marks.values())
    assert np.linalg.norm(d.sphere.s_nt - t / TARGET.radius) < 0.01 * np.linalg.norm(t) / 0.05


@pytest.mark.slow
@pytest.mark.parametrize('deg', [5.0, 9.0, 12.0, 15.0])
def test_cap_radius_told_through_the_target(deg):
    """Caps of 5–15° painted, the same radius in the target the detector is built from."""
    cam = CAMERAS['vga_f600']
    target = special_sphere(mark_radius_deg=deg)
    n = 60
    e_s, e_r, missed, _ = measure(Detector.for_target(target),
                                  scenes(cam, target, n, 404 + int(deg)), cam, target)
    print(deg, check_accuracy(e_s, e_r, missed, n))


@pytest.mark.slow
def test_a_wrong_cap_radius_costs_accuracy():
    """12° caps measured as 9° ones are worse than told 12°: the radius is used."""
    cam = CAMERAS['vga_f600']
    painted = special_sphere(mark_radius_deg=12.0)
    frames = list(scenes(cam, painted, 60, 505))
    told = measure(Detector.for_target(painted), frames, cam, painted)[1]
    untold = measure(Detector.for_target(TARGET), frames, cam, painted)[1]
    assert np.percentile(untold, 99) > 2 * np.percentile(told, 99), (
        np.percentile(untold, 99), np.percentile(told, 99))


def test_backgrounds_brighter_than_the_shaded_side_never_publish_wrong():
    """
    Checkerboards up to 120 (the body's shaded side is ~106) and a disc touching the target.

    Nothing is promised about how often the target is found there; what is published is
    right.
    """
    cam = CAMERAS['vga_f600']
    det = Detector.for_target(TARGET)
    rng = np.random.default_rng(6)
    frames = []
    for k, (img, R, t, _) in enumerate(scenes(cam, TARGET, 24, 606,
                                              background=Checker(20, 120, 18.0, 0.5))):
        frames.append((img, R, t, None))
        if k % 3 == 0:                      # a white disc touching the target's silhouette
            box = silhouette_box(cam, t, TARGET.radius)
            d = np.linalg.norm(t)
            C = t + np.array([0.0, 1.9 * TARGET.radius, 0.0])
            disc = Disc(C * d / np.linalg.norm(C), -C / np.linalg.norm(C), TARGET.radius,
                        (250, 250, 250))
            frames.append((render(cam, [target_ball(TARGET, R, t), disc], Flat((40, 40, 40)),
                                  Light(), rng=rng), R, t, None))
            assert box is not None
    e_s, e_r, missed, pub = measure(det, frames, cam)
    assert len(pub) >= len(frames) // 3, (len(pub), len(frames))
    assert np.count_nonzero((e_s > 1.0) | (e_r > 3.0)) == 0, (e_s.max(), e_r.max())


def test_no_sphere_in_view_and_a_small_sphere_on_flat_grey_say_what_they_are():
    """No sphere on flat grey or a texture: no sphere-like blob (not 'too large')."""
    cam = CAMERAS['vga_f600']
    det = Detector.for_target(TARGET)
    ci = intrinsics(cam)
    for bg in (Flat((40, 40, 40)), Flat((120, 120, 118)), Checker(40, 70, 24.0, 0.2)):
        d = det.detect(render(cam, [], bg, rng=np.random.default_rng(2)), 'rgb8', ci)
        assert not d.found and d.not_detected.reason is not Reason.TOO_LARGE, (bg, d.reason)
        assert d.not_detected.reason in NO_SPHERE, d.reason
    R = pin.exp3(np.array([0.2, -0.1, 0.05]))
    t = np.array([0.15, -0.1, 1.0])                               # 30 px radius, off-centre
    img = render(cam, [target_ball(TARGET, R, t)], Flat((40, 40, 40)), Light(),
                 rng=np.random.default_rng(3))
    d = det.detect(img, 'rgb8', ci)
    assert d.found, d.reason
    assert np.linalg.norm(d.sphere.s_nt - t / 0.05) < 0.01 * np.linalg.norm(t / 0.05)


def _target_fits(det, img, intr, s_true, R_px, true_intr=None):
    """
    (quality, rms, coverage, sure, s_n,t error %) of every fit of every level on the target.

    ``intr`` the intrinsics the detector is given, ``true_intr`` those of the image (which
    fits lie on the target), by default the same.
    """
    from sphere_servo.core.conics import conic_pixels_to_normalized
    from sphere_servo.core.measurement import sphere_from_conic
    from sphere_servo.vision.reasons import NotDetected
    found = det.silhouette.candidates(img, img)
    if isinstance(found, NotDetected):
        return []
    ti = intr if true_intr is None else true_intr
    uv = np.array([ti[0] * s_true[0] / s_true[2] + ti[2],
                   ti[1] * s_true[1] / s_true[2] + ti[3]])
    out, todo = [], list(found.blobs[:10])
    while todo:
        blob = todo.pop(0)
        grown = found.grown(blob)
        if grown is not None:
            todo.append(grown)
        sil = det.silhouette.fit(blob, img, img, found.step)
        if isinstance(sil, NotDetected) \
                or np.hypot(*(np.array(sil.ellipse.centre) - uv)) > 0.8 * R_px:
            continue
        try:
            sph = sphere_from_conic(conic_pixels_to_normalized(sil.conic_px, *intr))
        except MeasurementError:
            continue
        e = 100 * np.linalg.norm(sph.s_nt - s_true) / np.linalg.norm(s_true)
        out.append((sph.quality, sil.rms_px, sil.coverage, det.bounds.sure(sil), e))
    return out


@pytest.mark.slow
def test_the_fit_bounds_keep_their_calibration():
    """
    The relations FitBounds' calibration rests on, re-measured on fresh seeds.

    Correct fits (s_n,t within 1 %) on the independent renderer: quality p99 below half
    the bound of a fit that is not sure, rms p99 below half its bound; the
    calibration-error experiment's fits are sure and within the loose quality bound; most
    wrong fits (there and on the project's renderer with dim light and clutter) are outside
    the bounds.
    """
    from sphere_servo.core.camera import CameraIntrinsics as CI
    from sphere_servo.vision.poses import random_poses as project_poses
    from sphere_servo.vision.renderer import Renderer
    det = Detector.for_target(TARGET)
    b = det.bounds
    fits = []
    for name, cam in sorted(CAMERAS.items()):
        intr = (cam.fx, cam.fy, cam.cx, cam.cy)
        for img, R, t, _ in scenes(cam, TARGET, 25, 707):
            fits += _target_fits(det, img, intr, t / 0.05, cam.fx * 0.05 / np.linalg.norm(t))
    n_ind = len(fits)
    # the project's renderer, clutter as bright as the dimmed body: many wrong levels
    cam = CI()
    ren = Renderer(cam, TARGET, background='clutter', gain=0.7, seed=5)
    for M in project_poses(TARGET, cam, 40, 709, 70.0):
        fits += _target_fits(det, ren.render(M), (600.0, 600.0, 320.0, 240.0),
                             M.translation / 0.05, 30.0 / np.linalg.norm(M.translation))
    F = np.array(fits)
    good = F[:n_ind][F[:n_ind, 4] < 1.0]          # the independent renderer's correct fits
    bad = F[F[:, 4] >= 1.0]
    assert len(good) > 100 and len(bad) > 15, (len(good), len(bad))
    q99, rms99 = np.percentile(good[:, 0], 99), np.percentile(good[:, 1], 99)
    assert q99 < 0.5 * b.unsure_max_quality and rms99 < 0.5 * b.max_rms_px, (q99, rms99)

    def passes(f):
        q, rms, cov, sure, _ = f
        return cov >= b.min_coverage and rms <= b.max_rms_px \
            and q <= (b.max_quality if sure else b.unsure_max_quality)
    assert sum(passes(f) for f in bad) <= 0.1 * len(bad), bad[[passes(f) for f in bad]]
    # the calibration-error experiment (pixels rendered right, intrinsics given wrong)
    wrong = cam.with_error(px=0.35, py=0.30, u0=-0.25, v0=0.27)
    ren = Renderer(cam, TARGET)
    q = []
    for M in project_poses(TARGET, cam, 30, 708, None):
        for f in _target_fits(det, ren.render(M), (wrong.px, wrong.py, wrong.u0, wrong.v0),
                              M.translation / 0.05, 30.0 / np.linalg.norm(M.translation),
                              (600.0, 600.0, 320.0, 240.0)):
            assert f[3], 'a calibration-error fit that is not sure'
            q.append(f[0])
    assert 0.05 < max(q) < b.max_quality, max(q)
