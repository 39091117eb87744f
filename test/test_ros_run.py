"""
The nodes' shared ``run()``: SIGINT and SIGTERM stop the spin loop, they interrupt nothing.

An asynchronous ``KeyboardInterrupt`` lands wherever Python happens to be; inside rclpy's
``take_message`` (Python called from C++) pybind turned it into a ``RuntimeError`` and the
node exited with code 1. Here a node signals itself in the middle of a callback, which makes
the moment deterministic: the callback must run to its end, ``on_shutdown`` must follow, and
the process must exit 0. (With the old handler the callback stopped at the signal.)

And it freezes what the start-up made before the first callback (``gc.freeze``), so that a
full collection, run inside whichever callback allocates, no longer walks it.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys

from conftest import _acquire_domain_id
import pytest
from test_allocator import FRAME

REPO = Path(__file__).resolve().parents[1]
NODE = r"""
import os, signal, sys
from rclpy.node import Node
from sphere_servo.ros.params import run

SIG = getattr(signal, sys.argv[1])


class Probe(Node):
    def __init__(self):
        super().__init__('stop_probe')
        self.calls = 0
        self.create_timer(0.05, self.tick)

    def tick(self):
        self.calls += 1
        os.kill(os.getpid(), SIG)
        total = sum(range(100000))  # Python work after the signal: not interrupted
        print(f'callback {self.calls} completed {total}', flush=True)

    def on_shutdown(self):
        print(f'on_shutdown after {self.calls} callback(s)', flush=True)


run(Probe, 'stop_probe')
print('run returned', flush=True)
"""


def _probe(script: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run a probe node's ``script`` in a process of its own, on a domain of its own."""
    domain, lock = _acquire_domain_id()
    env = dict(os.environ, PYTHONPATH=str(REPO), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_DOMAIN_ID=str(domain))
    env.pop('ROS_LOCALHOST_ONLY', None)
    try:
        return subprocess.run([sys.executable, '-c', script, *args], env=env,
                              capture_output=True, text=True, timeout=60, cwd=cwd)
    finally:
        lock.close()


@pytest.mark.parametrize('sig', ['SIGINT', 'SIGTERM'])
def test_a_signal_stops_the_loop_without_interrupting_a_callback(sig, tmp_path):
    p = _probe(NODE, sig, cwd=tmp_path)
    lines = p.stdout.splitlines()
    assert p.returncode == 0, p.stdout + p.stderr
    assert lines == ['callback 1 completed 4999950000', 'on_shutdown after 1 callback(s)',
                     'run returned'], p.stdout + p.stderr
    assert 'Traceback' not in p.stderr, p.stderr


GC_NODE = r"""
import gc, json, os, signal, weakref
from rclpy.node import Node
from sphere_servo.ros.params import run


class Garbage:
    pass


class Probe(Node):
    def __init__(self):
        super().__init__('gc_probe')
        # what a node's start-up leaves: long-lived containers (a model, caches), and garbage
        self.model = [{'link': [i]} for i in range(100000)]
        cycle = Garbage()
        cycle.self = cycle
        self.garbage = weakref.ref(cycle)
        del cycle
        self.create_timer(0.05, self.tick)

    def tick(self):
        walked = [o for g in range(3) for o in gc.get_objects(generation=g)]
        print(json.dumps({'frozen': gc.get_freeze_count(), 'walked': len(walked),
                          'model_walked': any(o is self.model for o in walked),
                          'garbage_left': self.garbage() is not None}), flush=True)
        os.kill(os.getpid(), signal.SIGINT)


run(Probe, 'gc_probe')
"""


def test_run_freezes_the_startup_objects_before_the_first_callback(tmp_path):
    """
    A full collection no longer walks what the start-up made, and its garbage is gone.

    The probe's start-up makes 200,000 long-lived containers (100,000 dicts and their
    lists) and a garbage reference cycle; in its first callback a full collection would walk
    (``gc.get_objects`` of the three generations) far fewer objects than were frozen, none of
    them the probe's model, and the cycle has been collected.
    """
    p = _probe(GC_NODE, cwd=tmp_path)
    assert p.returncode == 0, p.stdout + p.stderr
    got = json.loads(p.stdout.splitlines()[0])
    assert got['frozen'] >= 200000, got
    assert got['walked'] < 0.05 * got['frozen'], got
    assert not got['model_walked'], got
    assert not got['garbage_left'], got


HEAP_NODE = FRAME + r"""
import json, os, signal
from rclpy.node import Node
from sphere_servo.ros.params import run


class Probe(Node):
    def __init__(self):
        super().__init__('heap_probe')
        self.create_timer(0.05, self.tick)

    def tick(self):
        print(json.dumps({'faults_per_frame': faults_per_frame()}), flush=True)
        os.kill(os.getpid(), signal.SIGINT)


run(Probe, 'heap_probe')
"""


def test_run_keeps_image_sized_blocks_in_the_heap(tmp_path):
    """
    In a node process, a frame's 900 KB blocks are no fresh pages (``allocator.keep_heap``).

    Three 921,600-byte blocks allocated, filled and freed 50 times in a callback: glibc's
    defaults map or trim them anew each time (test_allocator: ~400 minor page faults a
    frame); under ``run`` they come back from the heap.
    """
    p = _probe(HEAP_NODE, cwd=tmp_path)
    assert p.returncode == 0, p.stdout + p.stderr
    got = json.loads(p.stdout.splitlines()[0])
    assert got['faults_per_frame'] < 5, got
