"""
``check_whole``: sizes, counts and offsets from outside are whole numbers, or refused.

One rule for a raw image's height, width and step (``vision.image.image_from_buffer``), a
camera's image size (``CentralCamera``, through ``central.image_side``) and CameraInfo's
binning and roi (``camera_models.camera_info_reduction``): an int or a float equal to one,
numpy's too; never a bool (``True`` rows read as an image of one row), a str, or a fraction
that ``int()`` would truncate. Every refusal typed (the bound, the quantity, the value).
"""
from __future__ import annotations

from fractions import Fraction
import math

import numpy as np
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import camera_info_reduction
from sphere_servo.core.central import CameraError
from sphere_servo.core.validation import Bound, check_whole
from sphere_servo.vision.image import image_from_buffer


class Refused(ValueError):
    """A caller's error class: check_whole raises the one it is given."""


def _refused(value, lo=-math.inf, hi=math.inf, limit=''):
    with pytest.raises(Refused) as err:
        check_whole(Refused, 'image height', value, lo, hi, limit)
    return err.value.args[0]


@pytest.mark.parametrize('value', [480, 480.0, np.int64(480), np.uint32(480),
                                   np.float32(480.0), np.array(480), Fraction(960, 2)],
                         ids=repr)
def test_whole_numbers_of_any_real_type_are_read_as_ints(value):
    n = check_whole(Refused, 'image height', value, 0)
    assert n == 480 and type(n) is int


@pytest.mark.parametrize('value, bound', [
    (True, Bound.SHAPE), (False, Bound.SHAPE), (np.True_, Bound.SHAPE), ('480', Bound.SHAPE),
    (None, Bound.SHAPE), ([480], Bound.SHAPE), (np.array([480]), Bound.SHAPE),
    (480 + 0j, Bound.SHAPE), (object(), Bound.SHAPE),
    (math.inf, Bound.FINITE), (-math.inf, Bound.FINITE), (math.nan, Bound.FINITE),
    (np.float64('nan'), Bound.FINITE),
    (480.5, Bound.RANGE), (np.float32(479.9), Bound.RANGE), (480 + 1e-9, Bound.RANGE),
    (-1, Bound.RANGE)], ids=lambda v: 'object' if type(v) is object else repr(v))
def test_what_is_no_whole_number_is_refused_by_name(value, bound):
    v = _refused(value, 0)
    assert (v.quantity, v.bound) == ('image height', bound) and v.value is value


def test_a_bool_is_no_size():
    """``True`` as a height read as 1: a one-row buffer was decoded as the image."""
    assert image_from_buffer(1, 5, 15, 'rgb8', bytes(15)).shape == (1, 5, 3)
    for true in (True, np.True_):
        with pytest.raises(ValueError) as err:
            image_from_buffer(true, 5, 15, 'rgb8', bytes(15))
        v = err.value.args[0]
        assert (v.quantity, v.value, v.bound) == ('image height', true, Bound.SHAPE)
        assert str(err.value).startswith('image height = True ')
    with pytest.raises(CameraError) as err:
        CameraIntrinsics(width=True)
    assert (err.value.violation.quantity, err.value.violation.bound) == ('width', Bound.SHAPE)


def test_the_bounds_at_and_past():
    assert check_whole(Refused, 'n', 1, 1, 5) == 1 and check_whole(Refused, 'n', 5.0, 1, 5) == 5
    for value in (0, 6, 2 ** 70, 0.5):
        v = _refused(value, 1, 5)
        assert v.bound is Bound.RANGE and v.value == value
    # no bound: any whole number, exactly (an int beyond a float's 53 bits is not rounded)
    assert check_whole(Refused, 'n', -2 ** 70 - 1) == -2 ** 70 - 1
    assert check_whole(Refused, 'n', 1e300) == int(1e300)
    # the refusal states its bound; ``limit`` states it instead
    assert _refused(7, 0, 5).limit != _refused(7, 0, 5, '≤ width = 5').limit == '≤ width = 5'


# --- the call sites: one rule ----------------------------------------------------------------
#: site → (the quantity it names, a call with its value, what the call made of it); each
#: accepts 2
K = [600.0, 0.0, 1.0, 0.0, 600.0, 240.0, 0.0, 0.0, 1.0]
SITES = {
    'image height': ('image height', lambda v: image_from_buffer(v, 5, 15, 'rgb8', bytes(30)),
                     lambda out: out.shape[0]),
    'image step': ('image step', lambda v: image_from_buffer(2, 1, v, 'mono8', bytes(range(4))),
                   lambda out: int(out[1, 0])),  # the second row starts at byte ``step``
    'camera width': ('width', lambda v: CameraIntrinsics(width=v, u0=1.0),
                     lambda cam: cam.width),
    'CameraInfo width': ('width', lambda v: CameraIntrinsics.from_camera_info_fields(v, 480, K),
                         lambda cam: cam.width),
    'binning_x': ('CameraInfo.binning_x',
                  lambda v: camera_info_reduction(640, 480, binning_x=v),
                  lambda red: red.binning_x),
    'roi.width': ('CameraInfo.roi.width',
                  lambda v: camera_info_reduction(640, 480, roi=(0, 0, v, 2)),
                  lambda red: red.roi[2]),
}


@pytest.mark.parametrize('site', sorted(SITES))
def test_every_call_site_reads_and_refuses_alike(site):
    quantity, call, made = SITES[site]
    for two in (2, 2.0, np.uint8(2), np.float64(2.0)):
        assert made(call(two)) == 2, (site, two)
    for value in (True, np.True_, 2.5, '2', None, math.nan, math.inf):
        with pytest.raises(ValueError) as err:  # CameraError is one
            call(value)
        v = getattr(err.value, 'violation', None) or err.value.args[0]  # a CameraError's
        assert v.quantity == quantity and v.value is value, (site, v)
        assert str(err.value).startswith(f'{quantity} = '), str(err.value)
