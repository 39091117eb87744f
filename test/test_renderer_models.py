"""
The renderer through the camera models (issue 18): exact fisheye and catadioptric images.

The truth is each model's projection written again here (test/independent_render.py's
:class:`Fisheye` and :class:`Unified`, which share no code with ``sphere_servo``): the
sphere's occluding circle projected through it bounds the rendered silhouette, to the
border of a 180°+ field; pixels outside a model's image circle are black; the marks are
where the model puts them; the rays of a camera are lifted once.
"""
from __future__ import annotations

import math

import cv2
from independent_render import Fisheye, Unified
from independent_scenes import ring_points
import numpy as np
import pinocchio as pin
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import FisheyeCamera, UnifiedCamera
from sphere_servo.core.targets import special_sphere
from sphere_servo.vision.backgrounds import Distractor
from sphere_servo.vision.rays import pixel_rays
from sphere_servo.vision.renderer import Renderer
from wide_cameras import twin, WIDE

BG = 40                                     # the 'flat' background level
UNIFORM = {'ambient': 1.0, 'diffuse': 0.0}  # the body at its albedo everywhere


def off_axis_pose(deg: float, az: float, dist: float, seed: int = 0) -> pin.SE3:
    """Return a pose with the sphere's centre ``deg`` off the optical axis, any orientation."""
    t = math.radians(deg)
    b = np.array([math.sin(t) * math.cos(az), math.sin(t) * math.sin(az), math.cos(t)])
    R = pin.exp3(np.random.default_rng(seed).normal(size=3))
    return pin.SE3(R, b * dist)


def polygon_area(uv: np.ndarray) -> float:
    """Area (px²) of the closed polygon ``uv`` (shoelace)."""
    x, y = uv[:, 0], uv[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


#: towards the image's bottom-right corner, where the field is widest (112° for the fisheye)
CORNER = math.atan2(240.0, 320.0)


@pytest.mark.parametrize('name', sorted(WIDE))
@pytest.mark.parametrize('deg, dist', [(0.0, 0.22), (45.0, 0.25), (86.0, 0.35), (92.0, 0.45)])
def test_silhouette_area_is_that_of_the_projected_occluding_circle(name, deg, dist):
    """
    The coverage the image shows equals the area inside the independent projection.

    Uniform shading, so that a pixel's coverage is ``(I − BG)/(albedo − BG)``; the sum over
    the image is the silhouette's area within 0.3 % (≈ 0.1 px along the edge of a 30 px
    sphere), off the axis and beyond 90° too.
    """
    cam = WIDE[name]
    target = special_sphere()
    cMo = off_axis_pose(deg, CORNER, dist)
    img = Renderer(cam, target, background='flat', **UNIFORM).render(cMo).astype(float)
    body = float(target.colors['body'][0])
    cover = np.clip((img[..., 0] - BG) / (body - BG), 0.0, 1.0)
    # the marks are painted darker in R: count the body channel where the marks are not
    marks = np.abs(img[..., 0] - img[..., 2]) > 40
    cover[marks] = 1.0
    ring = twin(cam).project(ring_points(np.asarray(cMo.translation), target.radius, 2000))
    assert ring.min() > 2 and ring[:, 0].max() < 637 and ring[:, 1].max() < 477  # in view
    want = polygon_area(ring)
    assert abs(cover.sum() / want - 1.0) < 3e-3, (cover.sum(), want)


@pytest.mark.parametrize('name', sorted(WIDE))
def test_each_pixel_inside_the_projected_circle_is_the_body(name):
    """Pixel centres inside the projected silhouette (by 1 px) are body, outside background."""
    cam = WIDE[name]
    target = special_sphere()
    cMo = off_axis_pose(88.0, math.pi - CORNER, 0.4, seed=1)
    img = Renderer(cam, target, background='flat', **UNIFORM).render(cMo)
    poly = twin(cam).project(ring_points(np.asarray(cMo.translation), target.radius, 720))
    contour = poly.astype(np.float32).reshape(-1, 1, 2)
    v, u = np.nonzero(np.ones((cam.height, cam.width), bool))
    box = (u > poly[:, 0].min() - 3) & (u < poly[:, 0].max() + 3) & \
        (v > poly[:, 1].min() - 3) & (v < poly[:, 1].max() + 3)
    d = np.array([cv2.pointPolygonTest(contour, (float(a), float(b)), True)
                  for a, b in zip(u[box], v[box])])
    val = img[v[box], u[box]].max(axis=1)
    assert np.all(val[d > 1.0] > BG + 100) and np.all(val[d < -1.0] == BG)


@pytest.mark.parametrize('name', sorted(WIDE))
def test_the_marks_are_where_the_model_projects_them(name):
    cam = WIDE[name]
    target = special_sphere()
    # the marked −z cap towards the camera, the sphere 70° off the axis
    t = math.radians(70.0)
    b = np.array([math.sin(t), 0.0, math.cos(t)])
    z = b
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    cMo = pin.SE3(np.column_stack([x, np.cross(z, x), z]), 0.2 * b)
    img = Renderer(cam, target, background='flat').render(cMo)
    for name_, oP in target.marks().items():
        u, v = np.rint(twin(cam).project(cMo.act(oP))[0]).astype(int)
        rgb = img[v, u].astype(float)
        want = np.asarray(target.colors[name_], float)
        chroma = rgb / rgb.sum() - want / want.sum()
        assert np.linalg.norm(chroma) < 0.05, (name_, rgb)


def test_pixels_outside_the_image_circle_are_black():
    # a fisheye whose whole sphere of directions (θ up to 180°) fits inside the image, and a
    # unified camera with ξ > 1, whose image ends at its limit circle
    for cam, indep in ((FisheyeCamera(px=100.0, py=100.0),
                        Fisheye(100.0, 100.0, 320.0, 240.0, 640, 480)),
                       (UnifiedCamera(px=200.0, py=200.0, xi=1.6),
                        Unified(200.0, 200.0, 320.0, 240.0, 640, 480, 1.6))):
        img = Renderer(cam, special_sphere(), background='flat').render(
            pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.4])))
        v, u = np.mgrid[0:480, 0:640]
        outside = np.isnan(indep.rays(u.astype(float), v.astype(float))[0])
        assert outside.mean() > 0.05
        assert np.all(img[outside] == 0) and np.all(img[~outside].max(axis=1) >= BG)


def test_the_rays_of_a_camera_are_lifted_once():
    cam = WIDE['fisheye']
    table = pixel_rays(cam)
    same = FisheyeCamera(px=cam.px, py=cam.py, u0=cam.u0, v0=cam.v0, dist=tuple(cam.dist))
    assert pixel_rays(same) is table
    assert Renderer(same, special_sphere())._rays is table
    # the table's rays are the model's lift, its solid angles the lift's Jacobian's
    uv = np.array([[0.0, 0.0], [318.0, 241.0], [639.0, 100.0]])
    q = cam.lift(uv)
    got = table.rays(uv[:, 0].astype(int), uv[:, 1].astype(int)).T
    assert np.abs(got - q).max() < 1e-6
    J = cam.lift_jacobian(uv)
    area = np.linalg.norm(np.cross(J[:, :, 0], J[:, :, 1]), axis=1)
    assert np.allclose(table.solid[uv[:, 1].astype(int), uv[:, 0].astype(int)], area,
                       rtol=1e-5)


def test_distortion_of_a_pinhole_is_rendered():
    # plumb_bob: the silhouette's area is that of the circle projected by OpenCV's model
    cam = CameraIntrinsics(px=420.0, py=420.0, dist=(-0.28, 0.09, 0.0008, -0.0005, -0.012))
    target = special_sphere()
    cMo = off_axis_pose(25.0, 0.4, 0.3)
    img = Renderer(cam, target, background='flat', **UNIFORM).render(cMo).astype(float)
    body = float(target.colors['body'][0])
    cover = np.clip((img[..., 0] - BG) / (body - BG), 0.0, 1.0)
    cover[np.abs(img[..., 0] - img[..., 2]) > 40] = 1.0
    P = ring_points(np.asarray(cMo.translation), target.radius, 2000)
    uv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), cam.K, np.array(cam.dist))
    want = polygon_area(uv.reshape(-1, 2))
    assert abs(cover.sum() / want - 1.0) < 3e-3


def test_distractors_need_a_pinhole_without_distortion():
    with pytest.raises(ValueError, match='pinhole'):
        Renderer(WIDE['fisheye'], special_sphere(),
                 distractors=[Distractor('sphere', (0.1, 0.0, 0.5), 0.05)])
