"""
Adversarial bring-up: what the launcher, its processes and ``pipeline`` do with bad input.

Each bad input must end in a clear line and a non-zero exit before anything starts, never a
launcher that runs with nothing working:

- the environment: a ``ROS_DOMAIN_ID`` that is not a decimal 0…232 (rcl reads ``010`` as
  octal 8 where Python reads 10, and exits at the first node above 232: both shown on a real
  rclpy context), a Fast DDS profile that is not XML or not a profile (Fast DDS logs an
  error and runs on its defaults), an ``RMW_IMPLEMENTATION`` that is not installed (rcl
  ends the process that loads it with 102), a ``ROS_STATIC_PEERS`` rcl cannot resolve;
- the command line: a ``--timeout`` that is nan (a run that never times out), ≤ 0 or inf;
- the scenario and its params files: missing, empty, not YAML, of the wrong shape, a
  section for a node that does not exist (``sevro:``, a wildcard the launcher does not
  read), no node, a node named twice (two processes of one name); ``pipeline`` given a
  node twice;
- the launch file (no ``launch`` package here: it is loaded over stand-ins of the four
  names it imports) refuses what the launcher refuses before starting anything;
- the processes: a node that ignores SIGINT is killed after the timeout and the others are
  still stopped, servo first; a node killed by a signal is reported with the signal's name;
  a launcher killed by SIGKILL or SIGHUP takes its nodes with it.

The ROS tests are in ``test_adversarial_bringup_ros.py``.
"""
from __future__ import annotations

import importlib.util
import io
import os
from pathlib import Path
import signal
import subprocess
import sys
import time
import types

import pytest

from sphere_servo.bringup import launcher, single
from sphere_servo.bringup.launcher import check_scenario, ExitCode
from sphere_servo.bringup.processes import check_environment, Launcher, LaunchError
from sphere_servo.pipeline.config import ConfigError, load_scenario, scenario

REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'config' / 'params'
PY = sys.executable


def _run(sc, **kw):
    out = io.StringIO()
    code, sup, codes = launcher.run(sc, until_converged=True, out=out, **kw)
    return code, sup, codes, out.getvalue()


def _domain_rcl_reads(value: str) -> subprocess.CompletedProcess:
    code = 'import rclpy; c = rclpy.Context(); rclpy.init(context=c); print(c.get_domain_id())'
    return subprocess.run([PY, '-c', code], env=dict(os.environ, ROS_DOMAIN_ID=value),
                          capture_output=True, text=True, timeout=60)


# --- the environment ------------------------------------------------------------------------
def test_rcl_reads_a_leading_zero_as_octal_where_python_reads_decimal():
    """Ground truth for refusing '010': the supervisor (int()) and the nodes would differ."""
    assert int('010') == 10
    assert _domain_rcl_reads('010').stdout.split()[-1] == '8'
    assert _domain_rcl_reads('0x10').stdout.split()[-1] == '16'


@pytest.mark.parametrize('domain', ['x', '-1', '300', '233', '010', '0x10', ' 5', '5 ', '1e2'])
def test_a_domain_id_no_node_could_use_is_refused_before_anything_starts(domain):
    env = dict(os.environ, ROS_DOMAIN_ID=domain)
    code, sup, codes, out = _run(scenario('special_sphere'), env=env)
    assert (code, sup, codes) == (ExitCode.BAD_CONFIG, None, {}), out
    assert f'ROS_DOMAIN_ID={domain!r}' in out and 'nothing started' in out


@pytest.mark.parametrize('domain', ['', '0', '7', '232'])
def test_a_valid_domain_id_passes(domain):
    check_environment({'ROS_DOMAIN_ID': domain})


def test_the_cli_refuses_a_bad_domain_with_exit_2():
    env = dict(os.environ, ROS_DOMAIN_ID='300', PYTHONPATH=str(REPO))
    p = subprocess.run([PY, '-m', 'sphere_servo.bringup.launcher', '--until-converged'],
                       env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == ExitCode.BAD_CONFIG, p.stdout + p.stderr
    assert "ROS_DOMAIN_ID='300'" in p.stdout and 'Traceback' not in p.stderr


@pytest.mark.parametrize('var, value, needle', [
    ('ROS_DOMAIN_ID', '300', "ROS_DOMAIN_ID='300'"),
    ('ROS_DOMAIN_ID', '010', "ROS_DOMAIN_ID='010'"),
    ('FASTRTPS_DEFAULT_PROFILES_FILE', str(REPO / 'README.md'), 'not a readable XML file')])
def test_a_node_started_alone_refuses_that_environment_with_exit_2(var, value, needle):
    """As ``ros2 run sphere_servo servo`` would start it: exit 2, one line, no traceback."""
    env = dict(os.environ, PYTHONPATH=str(REPO), RMW_IMPLEMENTATION='rmw_fastrtps_cpp')
    env[var] = value
    p = subprocess.run([PY, '-m', 'sphere_servo.ros.servo'], env=env, capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 2, p.stdout + p.stderr
    assert needle in p.stderr and 'refused to start' in p.stderr, p.stderr
    assert 'Traceback' not in p.stderr


@pytest.mark.parametrize('body, needle', [
    ('<?xml version="1.0"?><profiles><broken', 'not a readable XML file'),
    ('', 'not a readable XML file'),
    ('<html><body/></html>', 'not a Fast DDS profile'),
])
def test_a_fast_dds_profile_that_is_not_one_is_refused(tmp_path, body, needle):
    bad = tmp_path / 'profile.xml'
    bad.write_text(body)
    env = dict(os.environ, FASTRTPS_DEFAULT_PROFILES_FILE=str(bad),
               FASTDDS_DEFAULT_PROFILES_FILE=str(bad), RMW_IMPLEMENTATION='rmw_fastrtps_cpp')
    code, sup, codes, out = _run(scenario('special_sphere'), env=env)
    assert (code, sup, codes) == (ExitCode.BAD_CONFIG, None, {}), out
    assert needle in out and str(bad) in out


def test_the_shipped_profile_passes():
    check_environment({'FASTRTPS_DEFAULT_PROFILES_FILE': str(REPO / 'config' / 'fastdds.xml'),
                       'RMW_IMPLEMENTATION': 'rmw_fastrtps_cpp'})


def test_a_missing_profile_exits_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv('FASTRTPS_DEFAULT_PROFILES_FILE', str(tmp_path / 'none.xml'))
    assert launcher.main(['--until-converged']) == ExitCode.BAD_CONFIG
    assert 'none.xml' in capsys.readouterr().err


def test_an_rmw_that_is_not_installed_is_refused_not_exit_102():
    """A missing rmw: rcl ends the process that loads it with 102; the launcher exits 2."""
    env = dict(os.environ, RMW_IMPLEMENTATION='rmw_no_such_dds_cpp', PYTHONPATH=str(REPO))
    loads = subprocess.run([PY, '-c', 'import sphere_servo.ros.params'], env=env,
                           capture_output=True, text=True, timeout=60)
    assert loads.returncode == 102  # ground truth: rcl's own exit
    p = subprocess.run([PY, '-m', 'sphere_servo.bringup.launcher', '--until-converged'],
                       env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == ExitCode.BAD_CONFIG, p.stdout + p.stderr
    assert "RMW_IMPLEMENTATION='rmw_no_such_dds_cpp' cannot be used" in p.stdout


def test_a_peer_rcl_cannot_resolve_is_refused_before_any_node_starts():
    """No node with ROS_STATIC_PEERS=@@@ (rcl cannot resolve it): the launcher's own is first."""
    env = dict(os.environ, ROS_STATIC_PEERS='@@@', ROS_DOMAIN_ID='61', PYTHONPATH=str(REPO))
    p = subprocess.run([PY, '-m', 'sphere_servo.bringup.launcher', '--until-converged'],
                       env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == ExitCode.BAD_CONFIG, p.stdout + p.stderr
    assert "the launcher's node cannot be made here, nothing started" in p.stdout
    assert 'Unable to resolve peer @@@' in p.stdout and 'Traceback' not in p.stderr
    assert not any(line.startswith('[servo]') for line in p.stdout.splitlines())


# --- the command line -----------------------------------------------------------------------
@pytest.mark.parametrize('timeout', ['nan', '-1', '0', 'inf'])
def test_a_timeout_that_cannot_end_a_run_is_refused(timeout, capsys):
    assert launcher.main(['--until-converged', f'--timeout={timeout}']) == ExitCode.BAD_CONFIG
    assert 'timeout must be a finite number of seconds > 0' in capsys.readouterr().out


# --- the scenario and its params files ------------------------------------------------------
def _scenario(tmp_path, params: str, nodes: str = '[servo]', teach: str = 'false') -> Path:
    (tmp_path / 'p.yaml').write_bytes(params.encode())
    path = tmp_path / 'sc.yaml'
    path.write_text(f'nodes: {nodes}\nparams: [p.yaml]\nteach: {teach}\n')
    return path


@pytest.mark.parametrize('params, needle', [
    ('', 'is not a YAML mapping'),                                 # empty
    ('- servo\n- features\n', 'is not a YAML mapping'),            # a list
    ('servo: [gain: 1\n', 'cannot read'),                          # not YAML
    ('servo: fast\n', "section 'servo' is not"),                   # a string section
    ('servo:\n  gain: 2.0\n', "section 'servo' is not"),           # ros__parameters missing
    ('servo:\n  ros__parameters: [1, 2]\n', "section 'servo' is not"),
    ('\x00\x01\x02', 'cannot read'),                               # binary
])
def test_a_params_file_of_the_wrong_shape_exits_2_naming_it(tmp_path, capsys, params, needle):
    path = _scenario(tmp_path, params)
    assert launcher.main(['--config', str(path)]) == ExitCode.BAD_CONFIG
    err = capsys.readouterr().err
    assert needle in err and 'p.yaml' in err, err


@pytest.mark.parametrize('section', ['sevro', 'launcher', '/*', '/**/servo', 'servo_*'])
def test_a_section_for_no_node_of_the_pipeline_is_refused(tmp_path, section):
    """A node ignores another name's section: a typo would run the servo on its defaults."""
    sc = load_scenario(_scenario(tmp_path, f'"{section}":\n  ros__parameters:\n    gain: 2.0\n'))
    assert sc.node_params('servo') == {}  # what the servo would get
    code, sup, codes, out = _run(sc)
    assert (code, sup, codes) == (ExitCode.BAD_CONFIG, None, {}), out
    assert repr(section) in out and 'the nodes would ignore them' in out


@pytest.mark.parametrize('section', ['servo', '/servo', '/**', 'arm_sim'])
def test_sections_a_node_reads_pass(tmp_path, section):
    body = 'ros__parameters:\n    start_enabled: false\n' if 'arm' not in section else \
        'ros__parameters:\n    camera_rate: 30.0\n'
    sc = load_scenario(_scenario(tmp_path, f'"{section}":\n  {body}'))
    assert check_scenario(sc) == ''


@pytest.mark.parametrize('nodes, needle', [
    ('[]', 'no nodes: nothing would run'),
    ('[servo, features, servo]', "node(s) ['servo'] named twice"),
])
def test_no_node_or_a_node_twice_is_refused(tmp_path, nodes, needle):
    sc = load_scenario(_scenario(tmp_path, 'servo:\n  ros__parameters: {}\n', nodes))
    code, sup, codes, out = _run(sc)
    assert (code, sup, codes) == (ExitCode.BAD_CONFIG, None, {}), out
    assert needle in out


def test_a_scenario_given_a_directory_or_a_params_file_exits_2(tmp_path, capsys):
    assert launcher.main(['--config', str(tmp_path)]) == ExitCode.BAD_CONFIG
    assert str(tmp_path) in capsys.readouterr().err
    assert launcher.main(['--config', str(PARAMS / 'arm_sim.yaml')]) == ExitCode.BAD_CONFIG
    assert 'unknown key(s)' in capsys.readouterr().err


def test_pipeline_refuses_a_node_named_twice(capsys):
    with pytest.raises(SystemExit) as exc:
        single.main(['pipeline', 'servo', 'arm_sim', 'servo', '--ros-args'])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert 'refused to start' in err and "['servo'] named twice" in err


def _launch_file(monkeypatch):
    """Load launch/sphere_servo.launch.py over stand-ins of ``launch`` and ``launch_ros``."""
    class Node:

        def __init__(self, **kw):
            self.kw = kw

    class LaunchConfiguration:

        def __init__(self, name):
            self.name = name

        def perform(self, context):
            return context[self.name]
    names = {'launch': {'LaunchDescription': list},
             'launch.actions': {'DeclareLaunchArgument': dict, 'OpaqueFunction': dict},
             'launch.substitutions': {'LaunchConfiguration': LaunchConfiguration},
             'launch_ros': {}, 'launch_ros.actions': {'Node': Node}}
    for module, attrs in names.items():
        monkeypatch.setitem(sys.modules, module, types.SimpleNamespace(**attrs))
    spec = importlib.util.spec_from_file_location('launch_file',
                                                  REPO / 'launch' / 'sphere_servo.launch.py')
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize('nodes, params, needle', [
    ('[]', 'servo:\n  ros__parameters: {}\n', 'no nodes'),
    ('[servo, servo]', 'servo:\n  ros__parameters: {}\n', 'named twice'),
    ('[servo]', 'sevro:\n  ros__parameters:\n    gain: 2.0\n', "['sevro']"),
])
def test_the_launch_file_refuses_what_the_launcher_refuses(monkeypatch, tmp_path,
                                                           nodes, params, needle):
    mod = _launch_file(monkeypatch)
    path = _scenario(tmp_path, params, nodes)
    with pytest.raises(ConfigError, match='nothing started') as exc:
        mod._nodes({'scenario': str(path)})
    assert needle in str(exc.value) and str(path) in str(exc.value)
    started = mod._nodes({'scenario': 'special_sphere'})  # the shipped one starts its four
    assert [n.kw['name'] for n in started] == list(scenario('special_sphere').nodes)


# --- the processes --------------------------------------------------------------------------
def _on_sigint(name: str, log: Path, ignore: bool = False) -> list[str]:
    """Return a child that appends its name to ``log`` on SIGINT, then exits 0 (or not)."""
    body = 'pass' if ignore else 'sys.exit(0)'
    code = (f'import signal, sys, time\n'
            f'def h(*a):\n    open({str(log)!r}, "a").write({name!r} + "\\n")\n    {body}\n'
            f'signal.signal(signal.SIGINT, h)\nprint("up", flush=True)\n'
            f'while True:\n    time.sleep(0.05)\n')
    return [PY, '-c', code]


def _wait_up(run: Launcher, names, timeout=30.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if all('up' in run.children[n].last for n in names):
            return
        time.sleep(0.05)
    pytest.fail(f'children not up: {[list(run.children[n].last) for n in names]}')


def test_stop_kills_a_node_that_ignores_sigint_and_still_stops_the_others_in_order(tmp_path):
    log = tmp_path / 'order'
    run = Launcher(scenario('special_sphere'), out=io.StringIO())
    names = ('arm_sim', 'detector', 'record', 'features', 'servo')
    for name in names:
        run._spawn(name, _on_sigint(name, log, ignore=name == 'features'))
    _wait_up(run, names)
    codes = run.stop(timeout=1.0)
    assert codes == {'arm_sim': 0, 'detector': 0, 'record': 0, 'features': -9, 'servo': 0}
    assert log.read_text().split() == ['servo', 'record', 'features', 'detector', 'arm_sim']


def test_a_node_killed_by_a_signal_is_reported_with_its_name(tmp_path):
    run = Launcher(scenario('special_sphere'), out=io.StringIO())
    run._spawn('servo', _on_sigint('servo', tmp_path / 'log'))
    _wait_up(run, ['servo'])
    run.children['servo'].popen.kill()
    run.children['servo'].popen.wait(10)
    assert run.dead() == ['servo']
    assert run.deaths() == 'servo exited with code -9 (SIGKILL): up'
    run.stop()


# SIGHUP as a terminal's hang-up ends a program: its default action, whatever this test
# process inherited (under nohup, SIGHUP is ignored, and the launcher would live on)
LAUNCHER_DIES = """
import io, os, signal, sys, time
signal.signal(signal.SIGHUP, signal.SIG_DFL)
from sphere_servo.bringup.processes import Launcher
from sphere_servo.pipeline.config import scenario
run = Launcher(scenario('special_sphere'), out=io.StringIO())
run._spawn('servo', [sys.executable, '-c', 'import time\\nwhile True: time.sleep(0.05)'])
print(run.children['servo'].popen.pid, flush=True)
while True:
    time.sleep(0.05)
"""


def _gone(pid: int, timeout: float = 20.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            with open(f'/proc/{pid}/stat') as f:
                if f.read().rsplit(')', 1)[1].split()[0] == 'Z':
                    return True
        except FileNotFoundError:
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize('sig', [signal.SIGKILL, signal.SIGHUP])
def test_a_launcher_killed_by_a_signal_takes_its_nodes_with_it(sig):
    p = subprocess.Popen([PY, '-c', LAUNCHER_DIES], stdout=subprocess.PIPE, text=True,
                         env=dict(os.environ, PYTHONPATH=str(REPO)))
    child = int(p.stdout.readline())
    p.send_signal(sig)
    assert p.wait(30) == -sig
    gone = _gone(child)
    if not gone:
        os.kill(child, signal.SIGKILL)
    assert gone, f'node {child} outlived a launcher killed by {sig.name}'


def test_a_refused_start_leaves_the_launcher_s_signal_handlers_alone(tmp_path):
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(LaunchError):
        check_environment({'ROS_DOMAIN_ID': 'x'})
    _run(scenario('special_sphere'), env=dict(os.environ, ROS_DOMAIN_ID='x'))
    assert signal.getsignal(signal.SIGINT) is before
