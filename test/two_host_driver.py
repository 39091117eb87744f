"""
The launcher's supervisor on one of two hosts: teach, servo, watch (``test_two_hosts``).

    python test/two_host_driver.py SCENARIO [--timeout 120]

Run inside a network namespace (``TwoHosts.popen``), where it reaches the nodes of both
hosts over DDS. It runs :meth:`Supervisor.teach <sphere_servo.bringup.supervisor.Supervisor.
teach>` (the launcher's sequence: desired pose, teach, start pose, enable), then watches
until the servo reports ``converged`` on a frame after the test said the link is back (a
line ``restored`` on stdin), or ``--timeout``. It prints JSON lines, flushed:

- ``{"event": "enabled", "wall": t}`` once the servo is enabled;
- ``{"event": "moving", "wall": t, "iteration": n}`` once a joint state after that shows the
  arm moving (the servo's twists reach it: the loop is closed across the link), with the
  servo's iteration count then;
- ``{"iteration": n, "wall": t}`` each time the servo's iteration count grows;
- at the end, ``{"result": ...}``: ``converged`` (bool), its ``wall`` time,
  ``iterations``, ``error_mm`` and ``error_deg`` against the taught pose, and what arrived
  here: ``joints`` [[wall, stamp, max |q̇|], …] from ``joint_states``, ``twists`` [[wall,
  stamp], …] (those that answer an image), ``arm_states`` [[wall, stamp, message], …] from
  ``/arm_sim/state``.
"""
from __future__ import annotations

import argparse
from itertools import takewhile
import json
from pathlib import Path
import select
import sys
import time

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from sphere_servo.bringup.supervisor import Supervisor  # noqa: E402
from sphere_servo.pipeline.config import scenario  # noqa: E402


def _say(**kw) -> None:
    print(json.dumps(kw), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('scenario')
    ap.add_argument('--timeout', type=float, default=120.0)
    args = ap.parse_args(argv)
    sc = scenario(args.scenario)
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import TwistStamped
    from sensor_msgs.msg import JointState
    from sphere_servo.ros.qos import COMMAND, MONITOR, observer
    sup = Supervisor(sc)
    joints, twists, arm_states = [], [], []

    def stamp(msg) -> float:
        return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9

    def on_joints(msg):
        joints.append([time.time(), stamp(msg), max(map(abs, msg.velocity), default=0.0)])

    def on_twist(msg):
        if stamp(msg) > 0:
            twists.append([time.time(), stamp(msg)])

    def on_arm(msg):
        if msg.status:
            arm_states.append([time.time(), stamp(msg), msg.status[0].message])
    sub = sup.node.create_subscription
    sub(JointState, 'joint_states', on_joints, observer(MONITOR, 5000))
    sub(TwistStamped, 'camera/cmd_vel', on_twist, observer(COMMAND, 5000))
    sub(DiagnosticArray, 'arm_sim/state', on_arm, observer(MONITOR, 5000))
    result = {'converged': False}
    try:
        sup.teach(lambda m: _say(log=m), lambda: True)
        enabled = time.time()
        _say(event='enabled', wall=enabled)
        restored_at, last_it, moving = None, -1, False
        end = time.monotonic() + args.timeout
        while time.monotonic() < end:
            sup.spin(0.05)
            it = int(sup.state_values.get('iteration', -1) or -1)
            if it > last_it:
                last_it = it
                _say(iteration=it, wall=time.time())
            since = takewhile(lambda j: j[0] > enabled, reversed(joints))
            if not moving and any(v > 0 for _, _, v in since):
                moving = True
                _say(event='moving', wall=time.time(), iteration=last_it)
            if restored_at is None and select.select([sys.stdin], [], [], 0)[0]:
                if sys.stdin.readline().strip() == 'restored':
                    restored_at = sup.state_stamp  # the newest frame the servo had answered
            if restored_at is not None and sup.converged() and sup.state_image is not None \
                    and sup.state_image > restored_at:
                sup.wait(lambda: sup.pose_at(sup.t_converged) is not None, 5.0)
                err = sup.final_pose_error()
                result.update(converged=True, wall=time.time(),
                              iterations=sup.iterations_converged,
                              error_mm=None if err is None else err[0] * 1e3,
                              error_deg=None if err is None else err[1])
                break
    finally:
        result.update(joints=joints, twists=twists, arm_states=arm_states)
        _say(result=result)
        sup.close()
    return 0 if result['converged'] else 1


if __name__ == '__main__':
    sys.exit(main())
