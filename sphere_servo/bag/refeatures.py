"""
refeatures: regenerate the pipeline's features from a recorded bag's images, offline.

    ros2 run sphere_servo refeatures BAG [--config NAME] [--sets SET ...] [--desired SPEC]
                                     [--check [TOL]] [--json FILE]
                                     [-o OUT [--storage S] [--servo]]
                                     [--compare SET ...] [--plot PNG] [--export-desired PNG]

No ROS graph: the bag's images and camera_info go through the code the nodes run, in the
nodes' order: the cores of :mod:`sphere_servo.pipeline` (``DetectorCore``, ``FeaturesCore``,
and ``ServoCore`` open loop: the twist is computed, nothing moves) and the nodes' message
codecs. Parameters are the nodes' defaults, or the ``detector`` / ``features`` / ``servo``
sections of a scenario's params files (``--config special_sphere`` for a bag of ``make
demo``) or of one params file (``--config config/params/x.yaml``), read into the nodes'
parameter dataclasses. The images (``--image-topic``, default ``/camera/image_raw``) are
``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` (JPEG or PNG, as image_transport's
compressed plugin records them: ``--image-topic /camera/image_raw/compressed``; detected as
the node does with ``image_transport: compressed``). An image the detector rejects (a bad
buffer, corrupt or truncated compressed bytes) gives an empty measurement and a warning that
counts them and says why the first was rejected; when every one is, nothing is regenerated
(exit 1: a compressedDepth topic, a refused camera_info). The work is done by
:mod:`sphere_servo.bag.regenerate`, :mod:`sphere_servo.bag.desired` and
:mod:`sphere_servo.bag.compare`.

Desired features (``--desired``):
  auto         (default) the images the recorded run taught: each recorded
               ``features/<set>/desired`` message is a teach, its header stamp the taught
               image's. Features are made from the first image under it on (the first
               recorded ``features/<set>`` message after the teach). A bag of the old
               layout (s* in ``features/<set>`` velocity) is refused.
  stamp:T      the image with header stamp T (seconds, e.g. ``stamp:1.133333333``)
  pose:X,Y,Z,ROLL,PITCH,YAW  exact projection of the target at cMo (``desired_source: pose``)
  image:FILE   an image file detected with the bag's intrinsics (``desired_source: image``)
With auto/stamp one features message is made for every image after the taught one (as live);
with pose/image for every image. Each message carries its image's header.

What it prints or writes:
  (always)     per topic, the regenerated stream against the recorded one, message for
               message by image stamp: counts, max |difference|; ``--check`` exits 1 unless
               they agree within TOL (default 1e-9): features/<set> the same stream;
               measurements and twists every message whose image stamp both have (twists
               with a zero stamp, the servo's watchdog, are left out).
  -o OUT       a new bag with ``detector/measurement``, ``features/<set>``,
               ``features/<set>/desired`` and, with ``--servo``, ``camera/cmd_vel``
               (TwistStamped; bag times = the images' bag times).
  --compare    sets A B ...: each set's error and the law's twist on the same images (open
               loop), as a table, and with ``--plot`` as a PNG (errors | twists, a row a set).
  --export-desired PNG  the taught image, so the live nodes reproduce it over ROS:
               ``replay BAG --topics /camera/image_raw /camera/camera_info`` into ``detector``
               and ``features --ros-args -p desired_source:=image -p desired_image:=PNG``.
"""
from __future__ import annotations

from __future__ import annotations

import argparse
from dataclasses import asdict
import json
from pathlib import Path
import sys

from sphere_servo.bag.bagio import BagError, check_new_output
from sphere_servo.bag.compare import (compare_recorded, compare_sets, export_desired,
                                      format_sets, plot_sets, write_bag)
from sphere_servo.bag.offline import IMAGE_TOPIC, INFO_TOPIC, load_settings, MEAS_TOPIC, TOL
from sphere_servo.bag.offline import TWIST_TOPIC
from sphere_servo.bag.regenerate import regenerate
from sphere_servo.core.features import FEATURE_SETS
from sphere_servo.pipeline.common import stamp_text
from sphere_servo.pipeline.config import ConfigError


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='refeatures', description=__doc__.strip().split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.strip().split('\n\n', 2)[2])
    p.add_argument('bag', help='rosbag2 directory with the images and camera_info')
    p.add_argument('--config', default=None,
                   help='scenario (name or path) or params file whose detector/features/'
                        "servo parameters to use (default: the nodes' defaults)")
    p.add_argument('--sets', nargs='+', default=None, metavar='SET',
                   help='feature sets to regenerate (default: those recorded, else s_n)')
    p.add_argument('--desired', default='auto', metavar='SPEC',
                   help='auto | stamp:SEC.NSEC | pose:X,Y,Z,ROLL,PITCH,YAW | image:FILE')
    p.add_argument('--image-topic', default=IMAGE_TOPIC,
                   help='sensor_msgs/Image or CompressedImage topic (default: %(default)s)')
    p.add_argument('--info-topic', default=INFO_TOPIC)
    p.add_argument('--check', nargs='?', type=float, const=TOL, default=None, metavar='TOL',
                   help=f'exit 1 unless every recorded features/measurement (and, with '
                        f'--servo, twist) topic is reproduced within TOL (default {TOL})')
    p.add_argument('--json', default=None, metavar='FILE',
                   help='also write the comparison (and the desireds found) as JSON')
    p.add_argument('-o', '--output', default=None, help='write the regenerated streams to '
                   'this new bag directory')
    p.add_argument('-s', '--storage', choices=['mcap', 'sqlite3'], default='mcap')
    p.add_argument('--servo', action='store_true',
                   help="also the servo's open-loop twist (camera/cmd_vel)")
    p.add_argument('--compare', nargs='+', default=None, metavar='SET',
                   help='compare these feature sets on the same images (errors, twists)')
    p.add_argument('--plot', default=None, metavar='PNG', help='with --compare: the figure')
    p.add_argument('--export-desired', default=None, metavar='PNG',
                   help='write the taught image as a PNG (for desired_source: image)')
    opts = p.parse_args(argv)
    for n in (opts.sets or []) + (opts.compare or []):
        if n not in FEATURE_SETS:
            p.error(f'unknown feature set {n!r}: use {" ".join(FEATURE_SETS)}')
    if opts.plot and not opts.compare:
        p.error('--plot needs --compare')
    return opts


def main(argv=None) -> int:
    opts = parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        return _main(opts)
    except BagError as err:
        print(f'refeatures: error: {err}', file=sys.stderr)
        return 1
    except (ValueError, OSError) as err:  # ParameterError, LaunchError, file errors
        print(f'refeatures: error: {" ".join(str(err).split())}', file=sys.stderr)
        return 1


def _main(opts) -> int:
    out = check_new_output(opts.output) if opts.output else None
    for f in (opts.plot, opts.export_desired, opts.json):
        if f and not Path(f).parent.is_dir():
            raise BagError(f'directory of {f!r} does not exist')
    try:
        settings = load_settings(opts.config)
    except ConfigError as err:
        raise BagError(str(err)) from None
    res = regenerate(opts.bag, settings, opts.sets, opts.desired, opts.servo,
                     opts.image_topic, opts.info_topic)
    print(f'refeatures: {len(res.frames)} images')
    for w in res.warnings:
        print(f'refeatures: warning: {w}', file=sys.stderr)
    for d in res.desired:
        print(f'  desired ({d.how}): {d.note}' if d.note else f'  desired ({d.how})')
        if d.frame is not None:
            print(f'    taught image #{d.frame.index} stamped {stamp_text(d.frame.stamp)}; '
                  f'features from image #{d.start} on')
    ok = True
    report = {'bag': str(opts.bag), 'images': len(res.frames), 'topics': {},
              'desired': [{'how': d.how, 'note': d.note, 'start': d.start,
                           'taught_index': d.frame.index if d.frame else None,
                           'taught_stamp_ns': d.frame.stamp if d.frame else None}
                          for d in res.desired]}
    print(f'  {"topic":28} {"regenerated":>11} {"recorded":>8}  stamps  max|diff|')
    for topic in res.streams:
        m = compare_recorded(res, topic)
        n = len(res.streams[topic])
        report['topics'][topic] = {'regenerated': n} if m is None else asdict(m)
        if m is None:
            print(f'  {topic:28} {n:11d} {"-":>8}')
            continue
        print(f'  {topic:28} {n:11d} {m.recorded:8d}  {m.stamps:6}  {m.max_diff:.3g}'
              + (f'  ({m.no_image} recorded of images not in the bag)' if m.no_image else '')
              + (f"  ({m.warmup} empty at the detector's start, not compared)"
                 if m.warmup else ''))
        # features: the same stream; the recorder may start on measurements before images,
        # and the servo is stopped before the last images
        if opts.check is not None:
            ok = ok and m.ok(opts.check, partial=topic in (MEAS_TOPIC, TWIST_TOPIC))
    if opts.json:
        report['ok'] = ok if opts.check is not None else None
        Path(opts.json).write_text(json.dumps(report, indent=1, default=float) + '\n')
    if out is not None:
        counts = write_bag(res, out, opts.storage)
        print(f'refeatures: wrote {sum(counts.values())} messages to {out}')
    if opts.export_desired:
        print(f'refeatures: taught image written to '
              f'{export_desired(opts.bag, res, Path(opts.export_desired), opts.image_topic)}')
    if opts.compare:
        runs = compare_sets(res, opts.compare)
        print(format_sets(runs, settings.servo.tol))
        if opts.plot:
            print(f'refeatures: plot written to '
                  f'{plot_sets(runs, Path(opts.plot), title=Path(opts.bag).name)}')
    if opts.check is not None and not ok:
        print('refeatures: error: regenerated streams differ from the recorded ones',
              file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
