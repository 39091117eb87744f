"""
Adversarial bags, written by ``rosbags`` (not by our writer): lies and unusable content.

- ``metadata.yaml`` that lists one storage file twice (every message would be read twice);
- an MCAP bag compressed per message, without ``metadata.yaml``: it must be read;
- ``refeatures`` on a bag whose images cannot be measured (a camera_info refused, missing or
  of another size): it must say so and exit non-zero, not print the table of a good run.

The images are rendered at known poses; the good bag's regenerated features are checked
against the exact projection, so the cases differ from it by the bag alone.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

pytest.importorskip('rclpy')
from sphere_servo.bag import bagio  # noqa: E402
from sphere_servo.bag.bagio import BagError  # noqa: E402
from sphere_servo.core.camera import CameraIntrinsics  # noqa: E402
from sphere_servo.core.measurement import observe  # noqa: E402
from sphere_servo.core.targets import special_sphere  # noqa: E402
from sphere_servo.sim.arm import pose_from_xyz_rpy  # noqa: E402
from sphere_servo.vision.renderer import Renderer  # noqa: E402
from test_refeatures import _run  # noqa: E402 (refeatures.main, its output)
import yaml  # noqa: E402

TS = bagio.typestore()
T = TS.types
CAM = CameraIntrinsics()
POSES = [pose_from_xyz_rpy([0.01 * i, 0.0, 0.5], [0.0, 0.0, 0.1 * i]) for i in range(3)]
SEC = 10**9


def _header(i: int):
    return T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](sec=1 + i, nanosec=0),
                                    frame_id='camera_optical_frame')


def _info(i: int, k=None, width: int = 640, height: int = 480):
    return T['sensor_msgs/msg/CameraInfo'](
        header=_header(i), height=height, width=width, distortion_model='plumb_bob',
        d=np.zeros(5), k=np.array(CAM.to_camera_info_fields()['k'] if k is None else k, float),
        r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
        roi=T['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0, width=0,
                                                  do_rectify=False))


def images_bag(path: Path, info=_info) -> Path:
    """Write rendered images and, unless ``info`` is None, one camera_info per image."""
    renderer = Renderer(CAM, special_sphere())
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection('/camera/camera_info', 'sensor_msgs/msg/CameraInfo', typestore=TS)
        im = w.add_connection('/camera/image_raw', 'sensor_msgs/msg/Image', typestore=TS)
        for i, cMo in enumerate(POSES):
            t = (1 + i) * SEC
            if info is not None:
                w.write(ci, t, TS.serialize_cdr(info(i), 'sensor_msgs/msg/CameraInfo'))
            img = T['sensor_msgs/msg/Image'](header=_header(i), height=480, width=640,
                                             encoding='rgb8', is_bigendian=0, step=1920,
                                             data=renderer.render(cMo).reshape(-1))
            w.write(im, t + 1, TS.serialize_cdr(img, 'sensor_msgs/msg/Image'))
    return path


DESIRED = ['--desired', 'pose:0,0,0.45,0,0,0']


def test_refeatures_of_a_good_bag_gives_the_poses_features(tmp_path):
    """The baseline: every image measured, s_n,t = O/r of each rendered pose."""
    path = images_bag(tmp_path / 'good')
    code, out, err = _run([str(path), *DESIRED, '-o', str(tmp_path / 'out')])
    assert code == 0 and err == '', err
    with bagio.bag(tmp_path / 'out') as r:
        conn = [c for c in r.connections if c.topic == '/features/s_n']
        got = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(conn)]
    assert len(got) == len(POSES)
    for msg, cMo in zip(got, POSES):
        s_nt = observe(cMo, special_sphere()).sphere.s_nt
        err = np.linalg.norm(np.array(msg.position[:3]) - s_nt)
        assert err < 3e-3 * np.linalg.norm(s_nt), (msg.position[:3], s_nt)


@pytest.mark.parametrize('info, needle', [
    (lambda i: _info(i, k=[0.0] * 9), 'not calibrated'),    # a driver before calibration
    (None, 'no valid camera_info'),                         # the topic, but no message on it
    (lambda i: _info(i, width=320, height=240, k=[300, 0, 160, 0, 300, 120, 0, 0, 1]),
     '320x240'),                                            # the intrinsics of another size
])
def test_refeatures_refuses_a_bag_whose_images_cannot_be_measured(tmp_path, info, needle):
    """
    Every image rejected by the detector: nothing was regenerated, so exit 1 and say why.

    Before, the run printed the same table as a good bag's (3 images, 3 features messages,
    all of them empty) and exited 0; with ``-o`` it wrote a bag of lost targets.
    """
    path = images_bag(tmp_path / 'bag', info)
    code, out, err = _run([str(path), *DESIRED, '-o', str(tmp_path / 'out')])
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 1, (out, err)
    assert len(lines) == 1 and 'error:' in lines[0] and needle in lines[0], err
    assert '3 of 3 images' in lines[0], err
    assert not (tmp_path / 'out').exists()


def test_refeatures_says_how_many_images_were_rejected(tmp_path):
    """One camera_info of three refused (its image is rejected): a warning, with the count."""
    path = images_bag(tmp_path / 'bag', lambda i: _info(i, k=[0.0] * 9) if i == 1 else _info(i))
    code, out, err = _run([str(path), *DESIRED])
    assert code == 0, err
    assert 'warning:' in err and '1 of 3 images' in err and 'not calibrated' in err, err


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_metadata_listing_a_storage_file_twice_is_refused(tmp_path, storage):
    """A metadata.yaml that lists one file twice would have every message read twice."""
    path = tmp_path / 'bag'
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conn = w.add_connection('/chatter', 'std_msgs/msg/String', typestore=TS)
        for t in (1, 2, 3):
            w.write(conn, t, TS.serialize_cdr(T['std_msgs/msg/String'](data=str(t)),
                                              'std_msgs/msg/String'))
    with bagio.bag(path) as r:
        assert [ts for _, ts, _ in r.messages()] == [1, 2, 3]
    meta = yaml.safe_load((path / 'metadata.yaml').read_text())
    info = meta['rosbag2_bagfile_information']
    name = info['relative_file_paths'][0]
    for paths in ([name, name], [name, f'sub/{name}']):  # the same file by its name
        info['relative_file_paths'] = paths
        (path / 'metadata.yaml').write_text(yaml.safe_dump(meta))
        with pytest.raises(BagError, match=f'{name}.*twice'):
            bagio.open_bag(path)


def test_message_compressed_mcap_without_metadata_is_read(tmp_path):
    """
    rosbag2 compresses per message in MCAP too (``-s mcap --compression-mode message``).

    Without ``metadata.yaml`` (a recorder killed) the zstd frames are recognised as for
    sqlite3, not handed to the CDR decoder (which refused every message).
    """
    from rosbags.rosbag2 import CompressionFormat, CompressionMode
    path = tmp_path / 'z'
    w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    w.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    with w:
        conn = w.add_connection('/chatter', 'std_msgs/msg/String', typestore=TS)
        for t in (1, 2, 3):
            w.write(conn, t, TS.serialize_cdr(T['std_msgs/msg/String'](data=f'z{t}'),
                                              'std_msgs/msg/String'))
    (path / 'metadata.yaml').unlink()
    with bagio.bag(path) as r:
        got = [(ts, r.deserialize(raw, c.msgtype).data) for c, ts, raw in r.messages()]
    assert got == [(1, 'z1'), (2, 'z2'), (3, 'z3')]


def test_refeatures_says_what_the_reader_left_out(tmp_path):
    """
    Pass on the reader's warning: a split file's images of another type are not read.

    The second file of the split bag carries the image topic as a String; the reader warns
    that those messages are not read, and refeatures must say it. Before, it ran on the
    first file's images alone without a word.
    """
    parts = [images_bag(tmp_path / 'part0')]
    with Writer(tmp_path / 'part1', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection('/camera/image_raw', 'std_msgs/msg/String', typestore=TS)
        w.write(conn, 10 * SEC, TS.serialize_cdr(T['std_msgs/msg/String'](data='x'),
                                                 'std_msgs/msg/String'))
    parts.append(tmp_path / 'part1')
    path = tmp_path / 'split'
    path.mkdir()
    for i, part in enumerate(parts):  # as rosbag2 names a split bag's files, no metadata
        next(part.glob('*.mcap')).rename(path / f'split_{i}.mcap')
    code, out, err = _run([str(path), *DESIRED])
    assert code == 0 and 'refeatures: 3 images' in out, (out, err)
    assert 'warning:' in err and 'not read' in err and 'std_msgs/msg/String' in err, err
