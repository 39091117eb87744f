"""
The nodes' shared ``run()``: SIGINT and SIGTERM stop the spin loop, they interrupt nothing.

An asynchronous ``KeyboardInterrupt`` lands wherever Python happens to be; inside rclpy's
``take_message`` (Python called from C++) pybind turned it into a ``RuntimeError`` and the
node exited with code 1. Here a node signals itself in the middle of a callback, which makes
the moment deterministic: the callback must run to its end, ``on_shutdown`` must follow, and
the process must exit 0. (With the old handler the callback stopped at the signal.)
"""
from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys

from conftest import _acquire_domain_id
import pytest

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


@pytest.mark.parametrize('sig', ['SIGINT', 'SIGTERM'])
def test_a_signal_stops_the_loop_without_interrupting_a_callback(sig, tmp_path):
    domain, lock = _acquire_domain_id()
    env = dict(os.environ, PYTHONPATH=str(REPO), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_DOMAIN_ID=str(domain))
    env.pop('ROS_LOCALHOST_ONLY', None)
    try:
        p = subprocess.run([sys.executable, '-c', NODE, sig], env=env, capture_output=True,
                           text=True, timeout=60, cwd=tmp_path)
    finally:
        lock.close()
    lines = p.stdout.splitlines()
    assert p.returncode == 0, p.stdout + p.stderr
    assert lines == ['callback 1 completed 4999950000', 'on_shutdown after 1 callback(s)',
                     'run returned'], p.stdout + p.stderr
    assert 'Traceback' not in p.stderr, p.stderr
