"""
Variants of a recorded run's bag, for the adversarial tests of the video and the replay page.

:func:`rewrite` copies a bag message for message with the ``rosbags`` writer (not this
package's), as rosbag2 writes them: sqlite3 or MCAP storage, ``metadata.yaml``, the QoS
profiles rosbag2 records for each topic (Jazzy's: reliable, volatile or transient-local,
keep last, durations 0 meaning infinite), each message passed through an edit that may
change, drop, duplicate or re-time it.
"""
from __future__ import annotations

from contextlib import redirect_stderr, redirect_stdout
import io
from pathlib import Path

import cv2
import numpy as np
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rosbags.rosbag2 import StoragePlugin, Writer
from sphere_servo.bag.bagio import bag, iter_raw, typestore

ZERO = QosTime(0, 0)
LATCHED = {'/arm_sim/markers', '/features/s_n/desired'}


def rosbag2_qos(topic: str) -> Qos:
    """Return the QoS profile ``ros2 bag record`` writes for a topic of the run."""
    durability = QosDurability.TRANSIENT_LOCAL if topic in LATCHED else QosDurability.VOLATILE
    return Qos(QosHistory.UNKNOWN, 0, QosReliability.RELIABLE, durability, ZERO, ZERO,
               QosLiveliness.AUTOMATIC, ZERO, False)


def stamp(msg) -> int:
    """Return a message's header stamp in ns."""
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def rewrite(src: Path, dst: Path, edit=None, storage: str = 'mcap', renamed=None) -> Path:
    """
    Copy the bag ``src`` to ``dst`` through ``edit(topic, bag ns, msg) -> [(ns, msg), ...]``.

    ``msg`` is the deserialized message (rosbags' dataclass), to change in place or replace;
    the list may be empty (the message dropped) or hold several (duplicated, re-timed).
    ``renamed``: topic → (new topic, new type): what ``edit`` returns for that topic is
    written there instead (a camera recorded as image_transport's compressed topic only).
    """
    ts = typestore()
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    renamed = renamed or {}
    with bag(src) as reader, Writer(dst, version=Writer.VERSION_LATEST,
                                    storage_plugin=plugin) as w:
        where = {c.topic: renamed.get(c.topic, (c.topic, c.msgtype)) for c in reader.connections}
        conns = {t: w.add_connection(name, ty, typestore=ts,
                                     offered_qos_profiles=[rosbag2_qos(name)])
                 for t, (name, ty) in where.items()}
        types = {t: ty for t, (_, ty) in where.items()}
        for c, t, raw in iter_raw(reader):
            if edit is None:
                w.write(conns[c.topic], t, raw)
                continue
            for t2, msg in edit(c.topic, t, reader.deserialize(raw, c.msgtype)):
                w.write(conns[c.topic], t2, bytes(ts.serialize_cdr(msg, types[c.topic])))
    return dst


def on(topic: str, fn):
    """Return an edit applying ``fn(msg) -> msg or None`` to ``topic`` (None: dropped)."""
    def edit(t_, t, msg):
        if t_ != topic:
            return [(t, msg)]
        out = fn(msg)
        return [] if out is None else [(t, out)]
    return edit


def chain(*edits):
    """Return the edit applying ``edits`` in turn."""
    def edit(topic, t, msg):
        out = [(t, msg)]
        for e in edits:
            out = [r for t2, m in out for r in e(topic, t2, m)]
        return out
    return edit


def pixels(msg) -> np.ndarray:
    return np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.width, -1)


def set_pixels(msg, img: np.ndarray, encoding: str):
    msg.height, msg.width = img.shape[:2]
    msg.step = img.shape[1] * (img.shape[2] if img.ndim == 3 else 1) * img.dtype.itemsize
    msg.encoding, msg.data = encoding, np.ascontiguousarray(img).view(np.uint8).ravel()
    return msg


def to_bgr8(msg):
    return set_pixels(msg, pixels(msg)[..., ::-1], 'bgr8')


def to_mono8(msg):
    return set_pixels(msg, cv2.cvtColor(pixels(msg), cv2.COLOR_RGB2GRAY), 'mono8')


def to_mono16(msg):
    gray = cv2.cvtColor(pixels(msg), cv2.COLOR_RGB2GRAY).astype('<u2') * 256
    return set_pixels(msg, gray, 'mono16')


def doubled(msg):
    """Return the image at twice its size (each pixel 2 × 2)."""
    img = pixels(msg)
    return set_pixels(msg, cv2.resize(img, (2 * img.shape[1], 2 * img.shape[0]),
                                      interpolation=cv2.INTER_NEAREST), msg.encoding)


def doubled_measurement(msg):
    """Scale a measurement's pixel values to twice the image size (its 1/2-pixel grid)."""
    pos = np.array(msg.position, dtype=float)
    for i, n in enumerate(msg.name):
        if n in ('ellipse_u', 'ellipse_v') or n.endswith(('_u', '_v')):
            pos[i] = 2 * pos[i] + 0.5
        elif n in ('ellipse_major', 'ellipse_minor'):
            pos[i] *= 2
    msg.position = pos
    return msg


def scenario(where: Path, name: str, arm_sim: str) -> Path:
    """Write the special-sphere scenario with ``arm_sim`` (its YAML, 4-space level) on top."""
    params = Path(__file__).resolve().parents[1] / 'config' / 'params'
    (where / f'{name}_arm.yaml').write_text(f'arm_sim:\n  ros__parameters:\n    {arm_sim}\n')
    files = [params / 'arm_sim.yaml', params / 'special_sphere.yaml', where / f'{name}_arm.yaml']
    cfg = where / f'{name}.yaml'
    cfg.write_text('nodes: [arm_sim, detector, features, servo]\n'
                   f'params: [{", ".join(map(str, files))}]\n')
    return cfg


def refused(mod, argv, out: Path, text: str) -> str:
    """Assert a tool refuses: exit 1, one line on stderr naming ``text``, no output file."""
    code, stdout, err = run_tool(mod, [*argv, '-o', out])
    lines = [ln for ln in err.splitlines() if ln.strip()]
    prog = mod.__name__.rpartition('.')[2]
    assert code == 1, f'exit {code}: {stdout} {err}'
    assert len(lines) == 1 and lines[0].startswith(f'{prog}: error:'), err
    assert text in lines[0], lines[0]
    assert not out.exists() and 'Traceback' not in stdout + err
    return lines[0]


def run_tool(mod, argv) -> tuple[int, str, str]:
    """Run a tool's ``main`` on ``argv``: (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code = mod.main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code
    return code, out.getvalue(), err.getvalue()
