"""The target's look (cap radius, colours) is part of its description, checked at the boundary."""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import (balloon, cc_target, DEFAULT_COLORS, make_target,
                                       special_sphere)
from sphere_servo.vision.detector import Detector
from sphere_servo.vision.renderer import Renderer

CAM = CameraIntrinsics()


@pytest.mark.parametrize('kind', ['special', 'cc', 'balloon'])
def test_factories_take_the_cap_radius_in_radians_or_degrees(kind):
    a = make_target(kind, mark_radius=math.radians(12.0))
    b = make_target(kind, mark_radius_deg=12.0)
    assert a.mark_radius == pytest.approx(math.radians(12.0)) == b.mark_radius
    assert make_target(kind).mark_radius == pytest.approx(math.radians(9.0))
    with pytest.raises(ValueError, match='not both'):
        make_target(kind, mark_radius=0.2, mark_radius_deg=12.0)


@pytest.mark.parametrize('bad', [0.0, -0.1, math.radians(31.0), float('nan'), 'x'])
def test_a_bad_cap_radius_is_refused(bad):
    with pytest.raises(ValueError, match='mark radius'):
        special_sphere(mark_radius=bad)


def test_overlapping_caps_are_refused():
    """The paper's marks are 41.4° apart: caps of 21° would overlap, 20° do not."""
    special_sphere(mark_radius_deg=20.0)
    with pytest.raises(ValueError, match='overlap'):
        special_sphere(mark_radius_deg=21.0)
    cc_target(mark_radius_deg=25.0)        # one surface cap only: nothing to overlap


@pytest.mark.parametrize('colors,match', [
    ({'body': (235, 235, 225), 'P1': (220, 30, 30)}, "lack 'P2'"),
    ({'body': (235, 235, 225), 'P1': (300, 30, 30), 'P2': (30, 60, 220)}, '0..255'),
    ({'body': (235, 235, 225), 'P1': (220, 30), 'P2': (30, 60, 220)}, '3 numbers'),
    ({'body': 'white', 'P1': (220, 30, 30), 'P2': (30, 60, 220)}, '3 numbers'),
    ([(235, 235, 225)], 'dict'),
])
def test_bad_colours_are_refused(colors, match):
    with pytest.raises(ValueError, match=match):
        special_sphere(colors=colors)


def test_colours_are_normalized_and_the_cc_tip_may_be_named_p3():
    t = cc_target(colors={'body': [250.0, 250, 240], 'P1': (200, 20, 20), 'P3': (20, 40, 210)})
    assert t.colors == {'body': (250, 250, 240), 'P1': (200, 20, 20), 'P2': (20, 40, 210)}
    assert special_sphere().colors == DEFAULT_COLORS
    assert special_sphere().colors is not DEFAULT_COLORS      # each target its own dict


def test_the_detector_refuses_marks_it_could_not_tell_from_the_body():
    greyish = special_sphere(colors={'body': (235, 235, 225), 'P1': (200, 200, 180),
                                     'P2': (30, 60, 220)})
    with pytest.raises(ValueError, match='P1.*too close to the body'):
        Detector.for_target(greyish)
    twins = special_sphere(colors={'body': (235, 235, 225), 'P1': (30, 60, 220),
                                   'P2': (35, 60, 215)})
    with pytest.raises(ValueError, match='too close colours'):
        Detector.for_target(twins)


def test_renderer_and_detector_take_the_look_from_the_target():
    """A green-and-yellow target with 14° caps is painted so, and found so."""
    look = {'body': (230, 230, 235), 'P1': (40, 190, 40), 'P2': (220, 200, 20)}
    t = special_sphere(colors=look, mark_radius_deg=14.0)
    cMo = pin.SE3(pin.Quaternion.FromTwoVectors(np.array([0.25, 0.25, -0.93]),
                                                np.array([0, 0, -1.0])).matrix(),
                  np.array([0.0, 0.0, 0.4]))
    img = Renderer(CAM, t, background='flat').render(cMo)
    det = Detector.for_target(t)
    assert det.marks.mark_radius == pytest.approx(math.radians(14.0))
    d = det.detect(img, 'rgb8', CAM)
    assert d.found and all(m.visible for m in d.marks.values()), d.reason
    green = np.all(np.abs(img.astype(int) - (40, 190, 40)) < 40, axis=2).sum()
    assert green > 100
    # a detector told the default colours finds no mark on it
    plain = Detector.for_target(special_sphere()).detect(img, 'rgb8', CAM)
    assert not any(m.visible for m in plain.marks.values())


def test_balloon_keeps_its_look_keywords():
    b = balloon(mark_radius_deg=7.0)
    assert b.mark_radius == pytest.approx(math.radians(7.0)) and b.axes is not None
