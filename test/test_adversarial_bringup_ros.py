"""
Adversarial bring-up over DDS: the installed ``launcher`` and its nodes as real processes.

- A node killed by SIGKILL mid-run, or one that exits 0 by itself: the launcher says which
  (its exit code, the signal's name), stops the others and exits 3, leaving no node behind.
- Ctrl-C twice: the second does not cut the ordered stop short (every node exits 0, no
  traceback); SIGTERM during ``--until-converged`` exits 130.
- Two pipelines on one ``ROS_DOMAIN_ID``: a second launcher is refused (exit 2, nothing
  started) while the first runs on untouched; a second ``servo`` joining a running pipeline
  (two servos driving one arm) ends the run with exit 3 and says so. The leftovers of a
  SIGKILLed node (Fast DDS keeps them in the graph for its 20 s lease) are waited for, not
  taken for another pipeline: the launcher then converges.
"""
from __future__ import annotations

import ast
import os
import re
import signal
import time

from conftest import wait_for
import pytest

pytest.importorskip('rclpy')
from test_loop import _node_pids  # noqa: E402, I100

NODES = ['arm_sim', 'detector', 'features', 'servo']


def _servoing(proc, timeout: float = 120.0) -> None:
    wait_for(lambda: 'servo servoing' in proc.log() or proc.popen.poll() is not None,
             timeout, what='the servo to servo')
    assert proc.popen.poll() is None, proc.log()[-3000:]


def _nodes_of(domain: str, launcher_pid: int, count: int = 4) -> dict[int, str]:
    def nodes():
        found = {p: n for p, n in _node_pids(domain).items() if p != launcher_pid}
        return found if len(found) == count else None
    return wait_for(nodes, 30.0, what=f'{count} node processes')


def _no_node_left(domain: str, keep=()) -> None:
    wait_for(lambda: not {p for p in _node_pids(domain) if p not in keep}, 30.0,
             what='every node to exit')


@pytest.mark.parametrize('victim, sig, said', [
    ('detector', signal.SIGKILL, 'detector exited with code -9 (SIGKILL)'),
    ('features', signal.SIGINT, 'features exited with code 0'),  # a clean exit of its own
])
def test_a_node_that_dies_mid_run_ends_the_run_with_exit_3(launch, ros_env, victim, sig, said):
    proc = launch('launcher', '--config', 'special_sphere')
    _servoing(proc)
    pids = _nodes_of(ros_env['ROS_DOMAIN_ID'], proc.popen.pid)
    os.kill(next(p for p, n in pids.items() if n == victim), sig)
    assert proc.popen.wait(60) == 3, proc.log()[-3000:]
    log = proc.log()
    assert 'node(s) exited' in log and said in log, log[-3000:]
    assert 'Traceback' not in log
    _no_node_left(ros_env['ROS_DOMAIN_ID'])


def test_ctrl_c_twice_does_not_cut_the_ordered_stop_short(launch, ros_env):
    proc = launch('launcher', '--config', 'special_sphere')
    _servoing(proc)
    proc.popen.send_signal(signal.SIGINT)
    wait_for(lambda: 'interrupted: stopping the nodes' in proc.log(), 30.0,
             what='the launcher to begin stopping')
    proc.popen.send_signal(signal.SIGINT)
    assert proc.popen.wait(90) == 0, proc.log()[-3000:]
    log = proc.log()
    assert 'Traceback' not in log and 'exit codes:' not in log, log[-3000:]  # all exited 0
    _no_node_left(ros_env['ROS_DOMAIN_ID'])


def test_sigterm_during_until_converged_exits_130(launch, ros_env):
    proc = launch('launcher', '--config', 'special_sphere', '--until-converged')
    _servoing(proc)
    proc.popen.send_signal(signal.SIGTERM)
    assert proc.popen.wait(90) == 130, proc.log()[-3000:]
    assert 'exit codes:' not in proc.log(), proc.log()[-3000:]
    _no_node_left(ros_env['ROS_DOMAIN_ID'])


def test_a_second_launcher_on_the_domain_is_refused_and_the_first_runs_on(launch, ros_env):
    first = launch('launcher', '--config', 'special_sphere')
    _servoing(first)
    pids = _nodes_of(ros_env['ROS_DOMAIN_ID'], first.popen.pid)
    second = launch('launcher', '--config', 'special_sphere', '--until-converged')
    assert second.popen.wait(120) == 2, second.log()[-3000:]
    log = second.log()
    assert 'already has the node(s)' in log and 'nothing started' in log, log[-3000:]
    # those it had discovered when one of them reported (all four, or fewer under load)
    listed = re.search(r'already has the node\(s\) (\[[^]]*\])', log).group(1)
    assert set(ast.literal_eval(listed)) <= {'arm_sim', 'detector', 'features', 'servo'}
    assert ast.literal_eval(listed), log
    assert 'waiting up to' not in log  # they report on /diagnostics: refused at once
    # the second started no node, and the first is untouched
    assert _nodes_of(ros_env['ROS_DOMAIN_ID'], first.popen.pid) == pids
    assert first.popen.poll() is None and 'another pipeline' not in first.log()
    assert first.stop(timeout=30.0) == 0, first.log()[-3000:]


def test_a_second_servo_joining_a_running_pipeline_ends_the_run(launch, ros_env):
    from conftest import REPO
    proc = launch('launcher', '--config', 'special_sphere')
    _servoing(proc)
    intruder = launch('servo', '--ros-args', '--params-file',
                      str(REPO / 'config' / 'params' / 'special_sphere.yaml'))
    assert proc.popen.wait(120) == 3, proc.log()[-3000:]
    log = proc.log()
    assert "two nodes named ['servo']" in log and 'another pipeline joined' in log, log[-3000:]
    assert 'Traceback' not in log
    assert intruder.stop() == 0, intruder.log()[-2000:]
    _no_node_left(ros_env['ROS_DOMAIN_ID'])


def test_the_leftovers_of_a_killed_node_are_waited_for_not_refused(launch, ros_env):
    from conftest import REPO
    ghost = launch('servo', '--ros-args', '--params-file',
                   str(REPO / 'config' / 'params' / 'special_sphere.yaml'))
    wait_for(lambda: _node_pids(ros_env['ROS_DOMAIN_ID']), 30.0, what='the servo process')
    time.sleep(3.0)  # its participant announced
    ghost.popen.kill()
    ghost.popen.wait(10)
    proc = launch('launcher', '--config', 'special_sphere', '--until-converged',
                  '--timeout', '150')
    assert proc.popen.wait(260) == 0, proc.log()[-3000:]
    assert 'converged after' in proc.log()
