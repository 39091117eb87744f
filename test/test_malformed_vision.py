"""
Malformed inputs over DDS against the running detector and features nodes (issue 14).

One detector and one features node serve every case of their group (module fixtures);
a test publisher feeds them. Each case asserts: the node is alive, its answer to the bad
input is the safe one (an empty measurement or empty features, with the input's stamp),
nothing non-finite was published, and the log names the problem.
"""
from __future__ import annotations

import math

from malformed import alive, all_finite, at, Group, in_log, stamp, values, WAIT
import numpy as np
import pytest

pytest.importorskip('rclpy')
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402, I100
from sensor_msgs.msg import CameraInfo, Image, JointState, RegionOfInterest  # noqa: E402
from sphere_servo.core.camera import CameraIntrinsics  # noqa: E402
from sphere_servo.core.targets import special_sphere  # noqa: E402
from sphere_servo.experiments.scenarios import CMO_DESIRED  # noqa: E402
from sphere_servo.ros.conversions import header, image_from_array  # noqa: E402
from sphere_servo.ros.logs import ThrottledLog  # noqa: E402
from test_hardening_cores import BAD_MEASUREMENTS, exact  # noqa: E402

CAM = CameraIntrinsics()
INFO = CAM.to_camera_info_fields()


class Detector:
    """The detector, a publisher of images and camera_info, what it answers."""

    def __init__(self, g: Group):
        self.g = g
        self.meas, self.states = [], []
        g.node.create_subscription(JointState, 'detector/measurement', self.meas.append, 500)
        g.node.create_subscription(DiagnosticArray, 'detector/state',
                                   lambda m: self.states.append(m), 500)
        self.pub_img = g.node.create_publisher(Image, 'camera/image_raw', 10)
        self.pub_info = g.node.create_publisher(CameraInfo, 'camera/camera_info', 10)
        self.proc = g.start('detector')
        assert g.spin(WAIT, until=lambda: self.pub_img.get_subscription_count() > 0
                      and self.pub_info.get_subscription_count() > 0), self.proc.log()
        img = special_sphere()
        from sphere_servo.vision.renderer import Renderer
        self.rgb = Renderer(CAM, img).render(CMO_DESIRED)
        self.t = 10.0

    def image(self, **over) -> Image:
        self.t += 0.1
        msg = image_from_array(self.rgb, header(self.t, 'camera_optical_frame'))
        for k, v in over.items():
            setattr(msg, k, v)
        return msg

    def info(self, **over) -> CameraInfo:
        return CameraInfo(header=header(self.t, 'camera_optical_frame'), **{**INFO, **over})

    def answer(self, img: Image):
        """Publish ``img``; return its measurement and its state (same stamp)."""
        t = stamp(img)
        self.pub_img.publish(img)
        assert self.g.spin(WAIT, until=lambda: any(at(m, t) for m in self.meas)
                           and any(at(s, t) for s in self.states)), self.proc.log()[-2000:]
        return ([m for m in self.meas if at(m, t)][0],
                [s for s in self.states if at(s, t)][0].status[0])

    def until(self, info: CameraInfo, done, **img_over):
        """Publish ``info`` then images until an answer satisfies ``done(meas, state)``."""
        self.pub_info.publish(info)
        for _ in range(40):
            meas, st = self.answer(self.image(**img_over))
            if done(meas, st):
                return meas, st
            self.pub_info.publish(info)
        raise AssertionError(f'no answer as expected: {st.message} {values(st)}')


@pytest.fixture(scope='module')
def detector(install_space, tmp_path_factory):
    g = Group(install_space, tmp_path_factory.mktemp('detector'))
    d = Detector(g)
    yield d
    codes = g.close()
    assert all(c == 0 for c in codes.values()), codes


def _found(meas, st) -> bool:
    return st.message == 'found'


K = INFO['k']
DETECTOR_CASES = {  # kind: (camera_info fields, image fields, what the log line names)
    'camera_info size mismatch': ({'width': 320, 'height': 240,
                                   'k': [300.0, 0.0, 160.0, 0.0, 300.0, 120.0, 0.0, 0.0, 1.0]},
                                  {}, ['camera size = 320x240', '640x480']),
    'equidistant with 5 coefficients': ({'distortion_model': 'equidistant',
                                         'd': [0.1, 0.0, 0.0, 0.0, 0.0]}, {},
                                        ['CameraInfo.d', 'needs 4 coefficients']),
    'a fisheye distortion that folds': ({'distortion_model': 'equidistant',
                                         'd': [-2.0, 0.0, 0.0, 0.0]}, {},
                                        ['FisheyeCamera distortion', 'not invertible']),
    'unified with xi < 0': ({'distortion_model': 'unified', 'd': [-0.5, 0.0, 0.0, 0.0, 0.0]},
                            {}, ['xi = -0.5', 'xi >= 0']),
    'fx = 1e300': ({'k': [1e300] + K[1:]}, {}, ['px', 'focal lengths must be within']),
    'K of zeros (uncalibrated)': ({'k': [0.0] * 9}, {}, ['not calibrated']),
    'K with NaN': ({'k': K[:5] + [math.nan] + K[6:]}, {}, ['CameraInfo.k', 'finite']),
    'K with skew': ({'k': [K[0], 2.0] + K[2:]}, {}, ['no skew']),
    'NaN distortion': ({'d': [math.nan, 0.0, 0.0, 0.0, 0.0]}, {}, ['k1', 'finite']),
    'unknown distortion model': ({'distortion_model': 'rational_polynomial',
                                  'd': [0.0] * 8}, {}, ['unsupported distortion_model']),
    'roi outside the image': ({'roi': RegionOfInterest(x_offset=100, width=640, height=480)},
                              {}, ['CameraInfo.roi.x_offset + roi.width', '100 + 640 = 740']),
    'roi of zero width only': ({'roi': RegionOfInterest(height=480)}, {},
                               ['CameraInfo.roi (x_offset, y_offset, width, height)',
                                'both 0 (the full image) or both > 0']),
    'binning, the full image': ({'binning_x': 2, 'binning_y': 2}, {},
                                ['camera size = 320x240', 'binning_x = 2, binning_y = 2']),
    'bad encoding': (None, {'encoding': 'yuv422'}, ["unsupported image encoding 'yuv422'"]),
    'step and data mismatch': (None, {'data': bytes(1000)}, ['image data has 1000 bytes']),
    'zero size': (None, {'height': 0, 'data': b''}, ['zero size']),
    'step shorter than a row': (None, {'step': 100}, ['step 100 is smaller than a row']),
}


@pytest.mark.parametrize('kind', DETECTOR_CASES)
def test_detector_refuses(kind, detector):
    info_over, img_over, needles = DETECTOR_CASES[kind]
    d = detector
    d.until(d.info(), _found)  # a known good state first
    info = d.info() if info_over is None else d.info(**info_over)

    def refused(meas, st):
        text = ' '.join(values(st).values())
        return st.message == 'rejected' and all(n in text for n in needles)
    meas, st = d.until(info, refused, **img_over)
    assert len(meas.name) == 0 and len(meas.position) == 0  # empty: target lost
    assert st.level == b'\x02'  # ERROR
    assert alive(d.proc), d.proc.log()[-2000:]
    assert all_finite(d.meas, 'position')
    assert in_log(d.proc, *needles[:1]), d.proc.log()[-2000:]
    meas, st = d.until(d.info(), _found)  # and it works again
    assert 'b_x' in meas.name


def test_detector_reads_a_decimated_image_with_the_full_camera_info(detector):
    """crop_decimate's stream: the calibrated camera_info, binning 2 and an roi; found."""
    d = detector
    full, _ = d.until(d.info(), _found)
    x, y, w, h = 40, 20, 560, 440  # the sphere stays inside this crop
    small = np.ascontiguousarray(d.rgb[y:y + h:2, x:x + w:2])
    info = d.info(binning_x=2, binning_y=2,
                  roi=RegionOfInterest(x_offset=x, y_offset=y, width=w, height=h))
    meas, st = d.until(info, _found, height=h // 2, width=w // 2, step=3 * w // 2,
                       data=small.tobytes())
    got, want = dict(zip(meas.name, meas.position)), dict(zip(full.name, full.position))
    b, b_full = (np.array([v[f'b_{a}'] for a in 'xyz']) for v in (got, want))
    assert np.degrees(np.arccos(min(1.0, b @ b_full))) < 0.2, (b, b_full)
    assert abs(got['r_delta'] / want['r_delta'] - 1.0) < 0.02
    assert 'P2_qx' in meas.name and alive(d.proc)
    # the same image with the camera_info of the full image: refused, by size
    meas, st = d.until(d.info(), lambda m, s: s.message == 'rejected', height=h // 2,
                       width=w // 2, step=3 * w // 2, data=small.tobytes())
    assert len(meas.name) == 0 and 'camera size = 640x480' in values(st)['reason']
    assert 'b_x' in d.until(d.info(), _found)[0].name


@pytest.mark.parametrize('encoding', ['rgba8', 'bgra8'])
def test_detector_reads_images_with_alpha(encoding, detector):
    d = detector
    want, _ = d.until(d.info(), _found)     # the rgb8 frame
    colour = d.rgb if encoding == 'rgba8' else d.rgb[..., ::-1]
    h, w = colour.shape[:2]
    rows = np.zeros((h, w * 4 + 16), np.uint8)  # padded rows, a translucent alpha
    rows[:, :w * 4] = np.dstack([colour, np.full((h, w), 128, np.uint8)]).reshape(h, -1)
    meas, st = d.answer(d.image(encoding=encoding, step=w * 4 + 16, data=rows.tobytes()))
    assert st.message == 'found', values(st)
    assert list(meas.name) == list(want.name) and 'P2_qx' in meas.name
    assert np.array_equal(meas.position, want.position)
    assert alive(d.proc)


def test_detector_survives_a_flood(detector):
    """300 images as fast as they go, none usable (4×4): alive, empty answers, finite."""
    d = detector
    d.until(d.info(), _found)
    # a size mismatch is one kind of line for the throttled log (digits aside): let an
    # earlier case's line age past the period, so the flood's first line must be logged
    d.g.spin(ThrottledLog(None).period + 0.1)
    tiny = np.zeros((4, 4, 3), np.uint8)
    first = len(d.meas)
    for k in range(300):
        d.t += 0.001
        d.pub_img.publish(image_from_array(tiny, header(d.t, 'camera_optical_frame')))
        if k % 50 == 0:
            d.g.spin(0.01)
    d.g.spin(WAIT, until=lambda: any(at(m, d.t) for m in d.meas))
    flooded = d.meas[first:]
    assert flooded and all(len(m.name) == 0 for m in flooded)  # every answer empty
    assert alive(d.proc) and all_finite(d.meas, 'position')
    # the size, throttled, named (the log line may reach us after the answers do)
    assert d.g.spin(WAIT, until=lambda: in_log(d.proc, 'image rejected', '4x4')), \
        d.proc.log()[-2000:]
    assert 'b_x' in d.until(d.info(), _found)[0].name


# --- features ----------------------------------------------------------------------------------
class Features:
    """The features node (desired from a pose), a measurement publisher, its answers."""

    def __init__(self, g: Group):
        self.g = g
        self.feats, self.states = {'s_n': [], 's': []}, []
        for name, got in self.feats.items():
            g.node.create_subscription(JointState, f'features/{name}', got.append, 500)
        g.node.create_subscription(DiagnosticArray, 'features/state', self.states.append, 500)
        self.pub = g.node.create_publisher(JointState, 'detector/measurement', 10)
        self.proc = g.start('features', '--ros-args', '-p', 'desired_source:=pose',
                            '-p', "sets:=['s_n', 's']")
        assert g.spin(WAIT, until=lambda: self.pub.get_subscription_count() > 0), \
            self.proc.log()
        self.t = 20.0

    def answer(self, vals: dict):
        """Publish a measurement of ``vals``; return the features of each set and the state."""
        self.t += 0.1
        t = self.t
        self.pub.publish(JointState(header=header(t, 'camera_optical_frame'), name=list(vals),
                                    position=[float(v) for v in vals.values()]))
        assert self.g.spin(WAIT, until=lambda: all(any(at(m, t) for m in f)
                                                   for f in self.feats.values())
                           and any(at(s, t) for s in self.states)), self.proc.log()[-2000:]
        return ({n: [m for m in f if at(m, t)][0] for n, f in self.feats.items()},
                [s for s in self.states if at(s, t)][0].status[0])


@pytest.fixture(scope='module')
def features(install_space, tmp_path_factory):
    g = Group(install_space, tmp_path_factory.mktemp('features'))
    f = Features(g)
    yield f
    codes = g.close()
    assert all(c == 0 for c in codes.values()), codes


def _check_features(f: Features, vals: dict, state: str, needle: str, log: str):
    good, st = f.answer(exact())
    assert all(len(m.position) == 6 for m in good.values()) and st.message == 'tracking'
    out, st = f.answer(vals)
    assert all(len(m.name) == 0 and len(m.position) == 0 for m in out.values())  # empty
    assert st.message == state and needle in values(st)['reason'], values(st)
    assert alive(f.proc), f.proc.log()[-2000:]
    assert all(all_finite(m, 'position') for m in f.feats.values())
    assert in_log(f.proc, log, needle), f.proc.log()[-2000:]
    good, st = f.answer(exact())  # and it works again
    assert all(len(m.position) == 6 for m in good.values()) and st.message == 'tracking'


@pytest.mark.parametrize('kind', BAD_MEASUREMENTS)
def test_features_refuse_an_impossible_measurement(kind, features):
    vals, quantity = BAD_MEASUREMENTS[kind]
    _check_features(features, vals, 'refused', quantity, 'measurement refused')


def test_features_refuse_names_and_values_that_do_not_pair(features):
    vals = exact()
    f = features
    good, _ = f.answer(vals)
    f.t += 0.1
    t = f.t
    f.pub.publish(JointState(header=header(t, 'cam'), name=list(vals),
                             position=list(vals.values())[:-1]))
    assert f.g.spin(WAIT, until=lambda: any(at(s, t) for s in f.states))
    st = [s for s in f.states if at(s, t)][0].status[0]
    out = {n: [m for m in ms if at(m, t)][0] for n, ms in f.feats.items()}
    assert all(len(m.name) == 0 for m in out.values()) and st.message == 'target lost'
    assert 'names but' in values(st)['reason'] and in_log(f.proc, 'target lost', 'names but')
    assert alive(f.proc)


def test_features_survive_a_flood(features):
    """500 measurements at once, half of them impossible: every answer finite, alive."""
    f = features
    bad = exact(r_delta=0.0)
    for k in range(500):
        f.t += 0.001
        vals = bad if k % 2 else exact()
        f.pub.publish(JointState(header=header(f.t, 'cam'), name=list(vals),
                                 position=[float(v) for v in vals.values()]))
        if k % 50 == 0:
            f.g.spin(0.01)
    f.g.spin(WAIT, until=lambda: any(at(m, f.t) for m in f.feats['s_n']))
    assert alive(f.proc) and all(all_finite(m, 'position') for m in f.feats.values())
    good, st = f.answer(exact())
    assert all(len(m.position) == 6 for m in good.values())
