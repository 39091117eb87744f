"""
Regenerated streams against a bag: message for message, feature set against feature set.

- :func:`compare_recorded`: per topic, the regenerated stream against the recorded one,
  paired by image stamp (counts, names, max |difference|).
- :func:`write_bag`: the regenerated streams into a new rosbag2 (:func:`cdr`: exact CDR).
- :func:`compare_sets`, :func:`format_sets`, :func:`plot_sets`: each set's error and the
  law's twist on the same images (open loop).
- :func:`export_desired`: the taught image as a PNG the features node reads back.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.interfaces import Nodetype

from sphere_servo.bag.bagio import bag, BagError, decode_image, topic_name, typestore
from sphere_servo.bag.offline import (header_ns, IMAGE_TOPIC, iter_image_msgs, MEAS_TOPIC, TOL,
                                      TWIST_TOPIC)
from sphere_servo.bag.regenerate import active, Result
from sphere_servo.core.control import Controller
from sphere_servo.core.features import make_feature_set
from sphere_servo.core.geometry import GeometryError
from sphere_servo.pipeline.servo import law_options
from sphere_servo.pipeline.vectors import FEATURE_NAMES
from sphere_servo.vision.image import without_alpha


def _vec(msg, topic: str) -> np.ndarray:
    """Return the numbers of a message, for comparing (JointState: position, velocity, effort)."""
    if topic == TWIST_TOPIC:
        t = msg.twist
        return np.array([t.linear.x, t.linear.y, t.linear.z,
                         t.angular.x, t.angular.y, t.angular.z])
    return np.concatenate([np.asarray(msg.position, float), np.asarray(msg.velocity, float),
                           np.asarray(msg.effort, float)])


@dataclass
class Match:
    """Regenerated vs recorded messages of one topic, paired in order by image stamp."""

    topic: str
    regenerated: int
    recorded: int
    matched: int
    common: int       # how many could be paired: the stamps both streams have (multiset)
    same_names: bool
    max_diff: float
    no_image: int = 0  # recorded messages of an image the bag lacks (the recorder lost it)
    # leading empty recorded measurements (the live detector had no camera_info yet;
    # offline, the bag's camera_info is known at once)
    warmup: int = 0

    def ok(self, tol: float = TOL, partial: bool = False) -> bool:
        """
        Tell whether the streams agree message for message.

        The same count and stamps (``partial``: every message whose image stamp both streams
        have is paired, for topics whose recording starts or ends apart from the images'),
        the same names and values within ``tol``.
        """
        paired = self.matched == self.common if partial else \
            self.matched == self.recorded == self.regenerated
        return paired and self.same_names and self.max_diff <= tol

    @property
    def stamps(self) -> str:
        """Return 'same', 'common' (every common stamp paired) or 'DIFFER'."""
        if self.matched == self.recorded == self.regenerated:
            return 'same'
        return 'common' if self.matched == self.common else 'DIFFER'


def compare_recorded(res: Result, topic: str) -> Match | None:
    """
    Pair each recorded message with the next regenerated one of the same image stamp.

    None if the topic was not recorded.
    """
    rec = res.recorded.get(topic) or []
    gen = res.streams.get(topic) or []
    if not rec:
        return None
    warmup = 0
    if topic == MEAS_TOPIC:  # the live detector's start, before its first camera_info
        while warmup < len(rec) and not rec[warmup][1].name:
            warmup += 1
        rec = rec[warmup:]
    gen_st = [header_ns(m.header) for _, m in gen]
    rec_st = [header_ns(m.header) for _, m in rec]
    j, pairs = 0, []
    for (_, a), st in zip(rec, rec_st):
        k = next((k for k in range(j, len(gen)) if gen_st[k] == st), None)
        if k is not None:  # else: its image is not in the bag (recorded apart)
            pairs.append((a, gen[k][1]))
            j = k + 1
    names = all(list(getattr(a, 'name', [])) == list(getattr(b, 'name', []))
                for a, b in pairs)
    diff = 0.0
    for a, b in pairs:
        va, vb = _vec(a, topic), _vec(b, topic)
        if va.shape != vb.shape:
            diff = np.inf
            break
        if va.size:
            diff = max(diff, float(np.max(np.abs(va - vb))))
    common = sum((Counter(gen_st) & Counter(rec_st)).values())
    images = Counter(f.stamp for f in res.frames)
    no_image = sum(max(0, n - images[st]) for st, n in Counter(rec_st).items())
    return Match(topic, len(gen), len(rec), len(pairs), common, names, diff, no_image, warmup)


def _as_rosbags(value, spec, store):
    """Return ``value`` (a field of an rclpy message) as rosbags serializes it."""
    kind, detail = spec
    if kind == Nodetype.NAME:
        cls = store.types[detail]
        return cls(**{name: _as_rosbags(getattr(value, name), sub, store)
                      for name, sub in store.fielddefs[detail][1]})
    if kind == Nodetype.BASE:
        # rclpy gives a byte field (DiagnosticStatus.level) as one-byte bytes
        return value[0] if isinstance(value, bytes) and len(value) == 1 else value
    (sub_kind, sub_detail), _ = detail  # an array or a sequence
    if sub_kind == Nodetype.BASE and sub_detail[0] != 'string':
        return np.asarray(value, dtype=np.dtype(sub_detail[0]))
    return [_as_rosbags(v, (sub_kind, sub_detail), store) for v in value]


def cdr(msg, msgtype: str) -> bytes:
    """
    Serialize an rclpy message to CDR with rosbags (exactly its length).

    rclpy's ``serialize_message`` (rmw_fastrtps, Jazzy) leaves bytes after a message that ends
    with an empty sequence (a JointState without velocity and effort): rosbags refuses them.
    """
    store = typestore()
    return bytes(store.serialize_cdr(_as_rosbags(msg, (Nodetype.NAME, msgtype), store),
                                     msgtype))


def write_bag(res: Result, out: Path, storage: str = 'mcap') -> dict[str, int]:
    """Write the regenerated streams into a new rosbag2 (bag times = the images' bag times)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    types = {MEAS_TOPIC: 'sensor_msgs/msg/JointState',
             TWIST_TOPIC: 'geometry_msgs/msg/TwistStamped'}
    counts = {}
    with Writer(out, version=Writer.VERSION_LATEST,
                storage_plugin=StoragePlugin[storage.upper()]) as w:
        items = []
        for topic, msgs in res.streams.items():
            conn = w.add_connection(topic, types.get(topic, 'sensor_msgs/msg/JointState'),
                                    typestore=typestore())
            counts[topic] = len(msgs)
            items += [(ts, k, conn, m) for k, (ts, m) in enumerate(msgs)]
        for ts, _, conn, m in sorted(items, key=lambda x: (x[0], x[2].id, x[1])):
            w.write(conn, ts, cdr(m, conn.msgtype))
    return counts


@dataclass
class SetRun:
    """One feature set along the recorded images, open loop: t (N,), e (N, n), v (N, 6)."""

    name: str
    labels: tuple
    t: np.ndarray
    e: np.ndarray
    v: np.ndarray
    lost: int


def compare_sets(res: Result, names: list[str]) -> list[SetRun]:
    """
    Return each set's error and the law's twist, open loop.

    ``Controller`` on the observation, so s_cc too, for every image after the last teach
    (earlier desireds were discarded by the run).
    """
    pipe = res.pipeline
    runs = []
    options = law_options(pipe.settings.servo)
    for name in names:
        t, e, v, lost = [], [], [], 0
        last = res.desired[-1]
        law = Controller(make_feature_set(name, last.obs), **options)
        for f, d in active(res):
            if d is not last:
                continue
            try:
                out = law.compute(pipe.observation(f.meas))
            except GeometryError:
                lost += 1
                continue
            t.append(f.stamp / 1e9)
            e.append(out.error)
            v.append(np.zeros(6) if out.converged else out.v_c)
        runs.append(SetRun(name, FEATURE_NAMES[name], np.array(t), np.array(e).reshape(len(t), -1),
                           np.array(v).reshape(len(t), 6), lost))
    return runs


def format_sets(runs: list[SetRun], tol: float) -> str:
    """
    Format a table of the sets' runs.

    Images, lost, max and last ‖e‖, the time after which ‖e‖ stays below the servo's tol,
    twist peaks, and how far each set's twist is from the first set's.
    """
    ref = runs[0]
    lines = [f'{"set":5} {"images":>6} {"lost":>4} {"max|e|":>8} {"last|e|":>9} '
             f'{"settle(s)":>9} {"max|v|":>7} {"max|w|":>7}  twist - {ref.name} twist (RMS)']
    for r in runs:
        if not len(r.t):
            lines.append(f'{r.name:5} {0:6d} {r.lost:4d}')
            continue
        n = np.linalg.norm(r.e, axis=1)
        above = np.nonzero(n >= tol)[0]
        settle = ('-' if len(above) and above[-1] == len(n) - 1 else
                  f'{(r.t[above[-1] + 1] if len(above) else r.t[0]) - r.t[0]:.3f}')
        rms = '-'
        if np.array_equal(r.t, ref.t):
            d = r.v - ref.v
            rms = (f'{np.sqrt(np.mean(np.sum(d[:, :3]**2, 1))):.3g} m/s, '
                   f'{np.sqrt(np.mean(np.sum(d[:, 3:]**2, 1))):.3g} rad/s')
        lines.append(f'{r.name:5} {len(r.t):6d} {r.lost:4d} {n.max():8.4g} {n[-1]:9.3g} '
                     f'{settle:>9} {np.linalg.norm(r.v[:, :3], axis=1).max():7.4f} '
                     f'{np.linalg.norm(r.v[:, 3:], axis=1).max():7.4f}  {rms}')
    return '\n'.join(lines)


def plot_sets(runs: list[SetRun], path: Path, title: str = '') -> Path:
    """Plot errors (left) and open-loop twists (right), one row per set, same time axis."""
    import matplotlib.pyplot as plt
    from sphere_servo.sim.plots import plot_errors, plot_twist, save
    fig, axes = plt.subplots(len(runs), 2, figsize=(11, 3.2 * len(runs)), squeeze=False,
                             sharex=True)
    for (ax1, ax2), r in zip(axes, runs):
        t = r.t - (runs[0].t[0] if len(runs[0].t) else 0.0)
        plot_errors(ax1, t, r.e, r.labels, fontsize=7)
        ax1.set_ylabel(f'{r.name}: s − s*')
        ax2b = plot_twist(ax2, t, r.v, fontsize=7)
        ax2.set_ylabel(f'{r.name}: v (m/s)')
        ax2b.set_ylabel('ω (deg/s)')
    axes[0, 0].set_title('feature error (open loop on the recorded images)')
    axes[0, 1].set_title("the law's camera twist (not applied)")
    axes[-1, 0].set_xlabel('image time since the first servoed image (s)')
    axes[-1, 1].set_xlabel('image time since the first servoed image (s)')
    return save(fig, path, title, dpi=100)


def export_desired(path, res: Result, out: Path, image_topic: str = IMAGE_TOPIC) -> Path:
    """Write the taught image (auto/stamp) as a PNG the features node reads back."""
    import cv2
    f = res.desired[-1].frame
    if f is None:
        raise BagError('--export-desired needs a taught image from the bag (--desired auto '
                       'or stamp:T)')
    with bag(path) as reader:
        for i, _, img in iter_image_msgs(reader, topic_name(image_topic)):
            if i == f.index:
                arr, enc = without_alpha(*decode_image(img))
                bgr = arr[..., ::-1] if enc == 'rgb8' else arr
                if not cv2.imwrite(str(out), np.ascontiguousarray(bgr)):
                    raise BagError(f'cannot write {str(out)!r}')
                return out
    raise BagError('the taught image vanished from the bag')
