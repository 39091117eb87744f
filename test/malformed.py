"""
Helpers of the malformed-input suites over DDS (``test_malformed_*.py``).

One set of nodes per group of cases, a test rclpy node on their domain, and the checks every
case makes. A :class:`Group` holds its own ROS domain, the installed executables it started (the
``launch`` fixture's :class:`~conftest.Proc`) and an rclpy node with its own context; a
module-scoped fixture makes one per test module, so the nodes start once for all the cases
of a group. Every case then asserts the four things of issue 14: the node is alive, its
output is the safe one (measured on its topics), nothing non-finite was published, and its
log names the problem.
"""
from __future__ import annotations

import math
import os
import subprocess
import time

from conftest import _acquire_domain_id, executable_path, Proc
import numpy as np

WAIT = 20.0  # bound on one wait (a loaded machine); never asserted on


class Group:
    """Nodes for a group of cases and a test node on their own ROS domain."""

    def __init__(self, install_space: dict, tmp_path):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        self.domain, self._lock = _acquire_domain_id()
        self.env = dict(install_space, ROS_DOMAIN_ID=str(self.domain),
                        ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
        self.env.pop('ROS_LOCALHOST_ONLY', None)
        self.tmp = tmp_path
        self.procs: list[Proc] = []
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=self.domain)
        self.node = rclpy.create_node(f'malformed_{os.getpid()}', context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)

    def start(self, name: str, *args: str) -> Proc:
        """Start an installed executable (its log in the group's tmp dir)."""
        log_path = self.tmp / f'{name}-{len(self.procs)}.log'
        popen = subprocess.Popen([executable_path(self.env, name), *args], env=self.env,
                                 stdout=open(log_path, 'w'), stderr=subprocess.STDOUT)
        proc = Proc(name, popen, log_path)
        self.procs.append(proc)
        return proc

    def spin(self, seconds: float = 0.1, until=None):
        """Process callbacks for ``seconds`` or until ``until()`` is true (its value)."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)
            if until is not None and until():
                return True
        return until() if until is not None else None

    def close(self) -> dict[str, int]:
        """Stop every node (SIGINT, then SIGKILL) and the test node; the exit codes."""
        codes = {f'{p.name}-{i}': p.stop() for i, p in enumerate(self.procs)}
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.ctx)
        self._lock.close()
        return codes


def stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def at(msg, t: float) -> bool:
    """Tell whether ``msg`` carries the stamp ``t`` (s; to the nanosecond)."""
    return abs(stamp(msg) - t) < 1e-6


def values(status) -> dict[str, str]:
    """Return the key → value of a DiagnosticStatus."""
    return {kv.key: kv.value for kv in status.values}


def all_finite(msgs, *fields) -> bool:
    """Tell whether every number of ``fields`` of every message is finite."""
    for m in msgs:
        for f in fields:
            part = getattr(m, f)
            nums = [getattr(part, a) for a in ('x', 'y', 'z')] if hasattr(part, 'x') \
                else list(part)
            if not all(math.isfinite(v) for v in nums):
                return False
    return True


def twist_norm(tw) -> float:
    return float(np.linalg.norm([tw.linear.x, tw.linear.y, tw.linear.z,
                                 tw.angular.x, tw.angular.y, tw.angular.z]))


def alive(proc: Proc) -> bool:
    return proc.popen.poll() is None


def in_log(proc: Proc, *needles: str) -> bool:
    """Tell whether the node's log has a line with every one of ``needles``."""
    return any(all(n in line for n in needles) for line in proc.log().splitlines())
