"""
The launcher's contract without ROS: exit codes, a bad config refused, the nodes' niceness.

``Launcher.nice`` (``launcher --nice N``) is checked on a child that prints its niceness:
the launcher's own plus N, and so is its session's autogroup's, by which the kernel shares
the CPU between sessions (each node has one of its own); a refused ``os.nice`` (no
CAP_SYS_NICE) is a LaunchError naming the node, not a child at the wrong priority.
"""
from __future__ import annotations

import io
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import pytest

from sphere_servo.bringup import launcher
from sphere_servo.bringup.launcher import ExitCode
from sphere_servo.bringup.processes import AUTOGROUP, Launcher, LaunchError
from sphere_servo.experiments import demo
from sphere_servo.pipeline.config import scenario

REPO = Path(__file__).resolve().parents[1]


def test_exit_codes_are_the_documented_numbers():
    """README and the launcher's docstring promise these numbers to scripts."""
    assert [int(c) for c in (ExitCode.OK, ExitCode.TIMEOUT, ExitCode.BAD_CONFIG,
                             ExitCode.NODE_DIED, ExitCode.TEACH_FAILED,
                             ExitCode.INTERRUPTED)] == [0, 1, 2, 3, 4, 130]


def test_a_config_that_cannot_be_found_exits_2(capsys, tmp_path):
    assert launcher.main(['--config', 'no_such_config_anywhere']) == ExitCode.BAD_CONFIG
    assert 'no_such_config_anywhere' in capsys.readouterr().err
    assert demo.main(['--config', 'no_such_config_anywhere', '--out', str(tmp_path)]) == 2
    assert 'no_such_config_anywhere' in capsys.readouterr().err


def test_teach_with_an_enabled_servo_is_refused_before_any_process_starts(tmp_path):
    out = io.StringIO()
    (tmp_path / 'servo.yaml').write_text('servo:\n  ros__parameters:\n    start_enabled: true\n')
    (tmp_path / 'teach.yaml').write_text('nodes: [servo]\nparams: [servo.yaml]\nteach: true\n')
    config = scenario(str(tmp_path / 'teach.yaml'))
    code, sup, codes = launcher.run(config, until_converged=True, out=out)
    assert code is ExitCode.BAD_CONFIG and sup is None and codes == {}
    assert 'start_enabled: false' in out.getvalue()


PRINT_NICE = [sys.executable, '-c', 'import os; print(os.nice(0))']


@pytest.mark.parametrize('nice', [0, 3])
def test_the_launcher_starts_its_nodes_at_its_niceness_plus_nice(nice):
    out = io.StringIO()
    run = Launcher(scenario('special_sphere'), out=out, nice=nice)
    run._spawn('probe', PRINT_NICE)
    assert run.children['probe'].popen.wait(30) == 0
    run.stop()  # joins the thread that forwards its output
    assert out.getvalue() == f'[probe] {os.nice(0) + nice}\n'


def test_a_refused_priority_is_a_launch_error(monkeypatch):
    def refuse(increment):
        raise PermissionError(1, 'Operation not permitted')
    monkeypatch.setattr(os, 'nice', refuse)  # the forked child calls the same function
    run = Launcher(scenario('special_sphere'), out=io.StringIO(), nice=-10)
    with pytest.raises(LaunchError, match=r'cannot start probe at nice -10'):
        run._spawn('probe', PRINT_NICE)
    assert run.children == {}


PRINT_AUTOGROUP = [sys.executable, '-c', 'print(open("/proc/self/autogroup").read().split()[-1])']
no_autogroup = pytest.mark.skipif(not os.path.exists(AUTOGROUP),
                                  reason='this kernel has no autogroup scheduling')


@no_autogroup
def test_each_node_s_session_is_at_its_niceness():
    out = io.StringIO()
    run = Launcher(scenario('special_sphere'), out=out, nice=3)
    run._spawn('probe', PRINT_AUTOGROUP)
    assert run.children['probe'].popen.wait(30) == 0
    run.stop()
    assert out.getvalue() == f'[probe] {os.nice(0) + 3}\n'


BUSY_AT_NICE_5 = """
import os, signal
from benchmarks.bench_transport import busy_load
os.nice(5)
with busy_load(2, own_sessions=True) as procs:
    for p in procs:  # Popen returns once the child has run its preexec_fn and exec'd
        group = open(f'/proc/{p.pid}/autogroup').read().split()[-1]
        print(p.pid, os.getsid(p.pid) == p.pid, group, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)  # no clean-up: the loops must end all the same
"""


def _gone(pid: int, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with open(f'/proc/{pid}/stat') as f:
                if f.read().rsplit(')', 1)[1].split()[0] == 'Z':  # ended, not yet reaped
                    return True
        except FileNotFoundError:
            return True
        time.sleep(0.05)
    return False


@no_autogroup
def test_a_busy_load_of_its_own_runs_in_sessions_at_the_caller_s_niceness_and_dies_with_it(
        tmp_path):
    out = tmp_path / 'out'
    with open(out, 'w') as f:  # a file: a loop that outlives the caller holds no pipe open
        code = subprocess.run([sys.executable, '-c', BUSY_AT_NICE_5], stdout=f, timeout=60,
                              env=dict(os.environ, PYTHONPATH=str(REPO))).returncode
    rows = [line.split() for line in out.read_text().splitlines()]
    outlived = [int(row[0]) for row in rows if not _gone(int(row[0]))]
    for pid in outlived:
        os.kill(pid, signal.SIGKILL)
    assert code == -9
    assert [row[1:] for row in rows] == [['True', str(os.nice(0) + 5)]] * 2, rows
    assert not outlived, f'busy loops {outlived} outlived their caller'
