"""
Adversarial tests of the video and the replay page: inputs they cannot draw or tell apart.

Variants of a recorded UR5 run's bag (:mod:`watch_bags`, as in ``test_adversarial_watch``):
unstamped images, compressed images on the image topic, frame rates ffmpeg cannot write,
measurements OpenCV cannot draw, a servo state whose error norm is not a number. Each gives
a correct video or a refusal (exit 1, one line on stderr, no file).
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from run_bag import run_bag
from sphere_servo.bag.run import read_run
from sphere_servo.experiments import replay3d, video
from test_video import _decode
from watch_bags import chain, on, refused, rewrite, run_tool, stamp


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
    return run_bag(tmp_path_factory.getbasetemp())


def test_images_the_tools_cannot_tell_apart_or_show(recorded, tmp_path):
    """Unstamped images (no servo state), compressed depth images on the topic: refused."""
    def unstamped(m):
        m.header.stamp.sec, m.header.stamp.nanosec = 0, 0
        return m
    b = rewrite(recorded.bag, tmp_path / 'zero', chain(
        on('/camera/image_raw', unstamped), on('/servo/state', lambda m: None)))
    # before: a one-frame video of the 279 images, exit 0
    refused(video, [b, '--quiet'], tmp_path / 'v.mp4', 'stamped 0 s (unset)')
    refused(replay3d, [b], tmp_path / 'r.html', 'stamped 0 s (unset)')
    from rosbags.rosbag2 import StoragePlugin, Writer
    from sphere_servo.bag.bagio import typestore
    ts = typestore()
    c = tmp_path / 'compressed'
    with Writer(c, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection('/camera/image_raw', 'sensor_msgs/msg/CompressedImage',
                                typestore=ts)
        T, Hd = ts.types['builtin_interfaces/msg/Time'], ts.types['std_msgs/msg/Header']
        # image_transport's compressedDepth: a 12-byte header, then a 16-bit PNG
        png = cv2.imencode('.png', np.zeros((48, 64), np.uint16))[1].ravel()
        for i in range(3):
            msg = ts.types['sensor_msgs/msg/CompressedImage'](
                header=Hd(stamp=T(sec=1, nanosec=i * 33_333_333), frame_id='c'),
                format='16UC1; compressedDepth png',
                data=np.concatenate([np.zeros(12, np.uint8), png]))
            w.write(conn, i + 1, ts.serialize_cdr(msg, 'sensor_msgs/msg/CompressedImage'))
    # before: an AttributeError traceback; JPEG and PNG are shown now (test_bag_compressed)
    refused(video, [c, '--quiet'], tmp_path / 'c.mp4', 'compressedDepth')


@pytest.mark.parametrize('fps', ['1e-9', '0.001', '1e6', 'nan', '-30'])
def test_frame_rates_ffmpeg_cannot_write(recorded, tmp_path, fps):
    """Before: 1e-9 gave ffmpeg's multi-line error, 1e6 a video at a million frames a second."""
    refused(video, [recorded.bag, '--quiet', '--fps', fps], tmp_path / 'v.mp4', '--fps')


def test_a_servo_state_whose_error_norm_is_not_a_number(recorded, tmp_path):
    def garble(m):
        for kv in m.status[0].values:
            if kv.key == 'error_norm':
                kv.value = 'n/a'
        return m
    b = rewrite(recorded.bag, tmp_path / 'bag', on('/servo/state', garble))
    refused(video, [b, '--quiet'], tmp_path / 'v.mp4', 'servo/state')


def test_measurements_that_cannot_be_drawn(recorded, tmp_path):
    """A negative ellipse axis, marks 1e20 px away: those left out (before: cv2.error)."""
    run0 = read_run(recorded.bag)
    spoilt = {run0.frames[10]: {'ellipse_major': -10.0, 'ellipse_angle': 1e30},
              run0.frames[20]: {'P1_u': 1e20, 'P2_v': -5e9}}

    def spoil(m):
        m.position = np.array(m.position)
        for name, value in spoilt.get(stamp(m), {}).items():
            m.position[m.name.index(name)] = value
        return m
    b = rewrite(recorded.bag, tmp_path / 'bag', on('/detector/measurement', spoil))
    code, _, err = run_tool(video, [b, '-o', tmp_path / 'v.mp4', '--quiet'])
    assert code == 0, err
    assert len(_decode(tmp_path / 'v.mp4')) == recorded.iterations
