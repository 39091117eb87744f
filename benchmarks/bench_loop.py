"""
Benchmark of the ROS pipeline (issue 5).

Image → twist latency across processes, keeping up with a 60 Hz camera, and resident memory
per node.

A feeder *process* publishes rendered 640×480 rgb8 images (and camera_info) stamped with the
wall clock at publish time, at a set rate; ``detector``, ``features`` and ``servo`` run as
separate processes (``python -m``), and this process listens. Figures:

- pipeline latency: image stamp → twist publication (the servo's ``image_age`` in
  ``/servo/state``, on its wall clock right after it published the twist: three processes,
  three DDS hops), median — the issue's figure; and, stricter, twist *arrival* in this
  (fourth) process − image stamp (four hops);
- baseline, measured beside it: the bare two-process Image latency, image arrival in this
  process − image stamp, median (the floor of any cross-process image pipeline);
- 60 Hz: frames the feeder published (by stamp, between the first and last twist) that got
  no twist;
- VmRSS of each node process.
"""
from __future__ import annotations

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import numpy as np

FEEDER = r"""
import signal, sys, time, rclpy
from rclpy.node import Node
from std_msgs.msg import Header
from sensor_msgs.msg import Image, CameraInfo
from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.experiments.scenarios import CMO_DESIRED, CMO_FAR_START
from sphere_servo.core.targets import special_sphere
from sphere_servo.ros.conversions import image_from_array, camera_info_from_intrinsics
from sphere_servo.vision.renderer import Renderer
rate = float(sys.argv[1])
rclpy.init()
node = Node('bench_feeder')
pi = node.create_publisher(Image, 'camera/image_raw', 10)
pc = node.create_publisher(CameraInfo, 'camera/camera_info', 10)
cam = CameraIntrinsics()
frames = [Renderer(cam, special_sphere()).render(p) for p in (CMO_DESIRED, CMO_FAR_START)]
# the desired pose until the bench has taught it (SIGUSR1), then the far pose; SIGINT stops
state = {'frame': 0, 'run': True}
signal.signal(signal.SIGUSR1, lambda *_: state.update(frame=1))
signal.signal(signal.SIGINT, lambda *_: state.update(run=False))
n, t0 = 0, time.monotonic()
while state['run']:
    h = Header(stamp=node.get_clock().now().to_msg(), frame_id='camera_optical_frame')
    pc.publish(camera_info_from_intrinsics(cam, h))
    pi.publish(image_from_array(frames[state['frame']], h))
    n += 1
    rclpy.spin_once(node, timeout_sec=0)
    time.sleep(max(0.0, t0 + n / rate - time.monotonic()))
print(f'published {n}', flush=True)
node.destroy_node()
rclpy.try_shutdown()
"""


def _rss_mb(pid: int) -> float:
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float('nan')


def _run(rate: float, seconds: float) -> dict:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import TwistStamped
    from rclpy.node import Node
    from sensor_msgs.msg import Image
    from std_srvs.srv import SetBool, Trigger

    env = dict(os.environ, ROS_DOMAIN_ID=str(1 + (os.getpid() * 13) % 100),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    extra = {'servo': ['-p', 'start_enabled:=false']}
    procs = {name: subprocess.Popen([sys.executable, '-m', f'sphere_servo.ros.{name}',
                                     '--ros-args', *extra.get(name, [])],
                                    env=env, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL)
             for name in ('detector', 'features', 'servo')}
    feeder = subprocess.Popen([sys.executable, '-c', FEEDER, str(rate)],
                              env=env, stdout=subprocess.PIPE, text=True)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(env['ROS_DOMAIN_ID']))
    node = Node('bench_loop', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    img_lat, tw_lat, tw_stamps, pub_lat = [], [], [], []

    def now() -> float:
        return time.time()

    def t_of(h) -> float:
        return h.stamp.sec + h.stamp.nanosec * 1e-9

    node.create_subscription(Image, 'camera/image_raw',
                             lambda m: img_lat.append(now() - t_of(m.header)), 10)

    def on_tw(m):
        if t_of(m.header) == 0.0:  # the watchdog's: it answers no image
            return
        tw_stamps.append(t_of(m.header))
        tw_lat.append(now() - t_of(m.header))
    node.create_subscription(TwistStamped, 'camera/cmd_vel', on_tw, 100)

    def on_state(m):
        st = m.status[0]
        age = {kv.key: kv.value for kv in st.values}.get('image_age')
        if st.message == 'servoing' and age is not None:
            pub_lat.append(float(age))
    node.create_subscription(DiagnosticArray, 'servo/state', on_state, 100)
    teach = node.create_client(Trigger, '/features/teach')
    enable = node.create_client(SetBool, '/servo/enable')
    rss = {}
    try:
        end = time.monotonic() + 30
        while not (teach.service_is_ready() and enable.service_is_ready()):
            ex.spin_once(timeout_sec=0.05)
            if time.monotonic() > end:
                raise RuntimeError('nodes did not come up')
        while not img_lat:  # the feeder is publishing the desired frame
            ex.spin_once(timeout_sec=0.05)
        t_end = time.monotonic() + 0.2
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.02)
        for cli, req in ((teach, Trigger.Request()), (enable, SetBool.Request(data=True))):
            fut = cli.call_async(req)
            while not fut.done():
                ex.spin_once(timeout_sec=0.02)
        feeder.send_signal(signal.SIGUSR1)  # taught: now the far pose
        for history in (img_lat, tw_lat, tw_stamps, pub_lat):
            history.clear()
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.01)
        rss = {name: _rss_mb(p.pid) for name, p in procs.items()}
        feeder.send_signal(signal.SIGINT)
        published = feeder.communicate(timeout=30)[0]
        if not (img_lat and tw_lat):
            raise RuntimeError(f'nothing measured in {seconds:.0f} s: {len(img_lat)} images, '
                               f'{len(tw_lat)} twists (feeder: {published.strip()!r})')
    finally:
        for p in [*procs.values(), feeder]:
            if p.poll() is None:
                p.send_signal(2)
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    st = np.sort(np.array(tw_stamps))
    # frames the feeder published between the first and the last twist's image
    expected = int(round((st[-1] - st[0]) * rate)) + 1 if st.size else 0
    return {'img': np.array(img_lat), 'tw': np.array(tw_lat), 'pub': np.array(pub_lat),
            'n_tw': len(set(tw_stamps)),
            'expected': expected, 'rss': rss, 'feeder': published}


def run(quick: bool = False) -> list[dict]:
    seconds = 5.0 if quick else 15.0
    r30 = _run(30.0, seconds)
    base = float(np.median(r30['img']) * 1e3)
    pub = float(np.median(r30['pub']) * 1e3) if r30['pub'].size else float('nan')
    lat = float(np.median(r30['tw']) * 1e3)
    rows = [{'name': 'loop: image stamp → twist publish (3 processes), median', 'value': pub,
             'unit': 'ms', 'baseline': base, 'baseline_name': 'bare 2-process Image latency',
             'ratio': pub / base, 'target': '≤ 1.5× baseline'},
            {'name': 'loop: image stamp → twist arrival (4th process), median', 'value': lat,
             'unit': 'ms', 'baseline': base, 'baseline_name': 'bare 2-process Image latency',
             'ratio': lat / base, 'target': 'information (one hop more)'},
            {'name': 'loop: image stamp → twist arrival, p95', 'value':
             float(np.percentile(r30['tw'], 95) * 1e3), 'unit': 'ms', 'baseline':
             float(np.percentile(r30['img'], 95) * 1e3), 'baseline_name': 'bare Image p95',
             'ratio': None, 'target': ''}]
    r60 = _run(60.0, seconds)
    rows.append({'name': 'loop at 60 Hz: frames without a twist', 'value':
                 float(r60['expected'] - r60['n_tw']), 'unit': 'frames', 'baseline':
                 float(r60['expected']), 'baseline_name': 'frames published', 'ratio':
                 r60['n_tw'] / max(1, r60['expected']), 'target': '0 (ratio 1.0)'})
    for name, mb in r60['rss'].items():
        rows.append({'name': f'RSS {name}', 'value': mb, 'unit': 'MiB', 'baseline': None,
                     'baseline_name': None, 'ratio': None, 'target': 'printed'})
    return rows


if __name__ == '__main__':
    for row in run(quick='--quick' in sys.argv):
        print(row)
