"""
Bad parameters and bad scenarios: one line, exit code 2, nothing started (issue 14, items 10-11).

The dataclass rules and the launcher's checks run in this process (no DDS); the nodes'
own refusals are checked on the installed executables, all started at once; the launcher's
reaction to a node that dies during start-up, and to its own SIGKILL, over DDS.
"""
from __future__ import annotations

import io
import os
from pathlib import Path
import time

from conftest import REPO, wait_for
import pytest

from sphere_servo.bringup import launcher, processes
from sphere_servo.bringup.launcher import ExitCode
from sphere_servo.pipeline.config import ConfigError, load_scenario
from sphere_servo.pipeline.params import (ArmSimParams, DetectorParams, FeaturesParams,
                                          ParameterError, ServoParams)
from sphere_servo.ros import guard
from sphere_servo.ros.params import check_params_files, params_files

PARAMS = REPO / 'config' / 'params'


# --- the dataclasses -------------------------------------------------------------------------
def test_a_misspelt_parameter_is_refused_listing_the_known_ones():
    with pytest.raises(ParameterError) as info:
        ServoParams.from_mapping({'gian': 5.0}, strict=True)
    text = str(info.value)
    assert 'unknown parameter gian' in text and 'gain' in text and 'r_hat' in text
    assert '\n' not in text
    ServoParams.from_mapping({'use_sim_time': True, 'gain': 2.0}, strict=True)  # ROS's own
    assert ServoParams.from_mapping({'gian': 5.0}).gain == 0.5  # a bag's config: ignored


@pytest.mark.parametrize('cls, values, needle', [
    (ArmSimParams, {'start_joints': [0.0, -1.57, 7.0, -1.57, -1.57, 0.0]},
     'start_joints[2] must be in'),
    (ArmSimParams, {'hand_eye': [2.0, 0.0, 0.0, 0.0, 0.0, 0.0]}, 'hand_eye[0] must be in'),
    (ArmSimParams, {'target_pose': [0.5, 0.1, 1e3, 0.0, 0.0, 0.0]}, 'target_pose[2]'),
    (ArmSimParams, {'start_cMo': [0.0, 0.0, 0.5, 0.0, 40.0, 0.0]}, 'start_cMo[4]'),
    (ArmSimParams, {'target.axes': [0.06, 20.0, 0.045]}, 'target.axes[1]'),
    (FeaturesParams, {'desired_cMo': [0.0, 0.0, 0.45, 0.0, 0.0, -7.0]}, 'desired_cMo[5]'),
    (DetectorParams, {'intrinsics_error': [-1.0, 0.0, 0.0, 0.0]},
     'intrinsics_error px = -1.0 must be > -1'),
    (FeaturesParams, {'intrinsics_error': [0.0, -1.5, 0.0, 0.0]}, 'intrinsics_error[1]'),
    (DetectorParams, {'intrinsics_error': [0.0, 0.0, 5.0, 0.0]}, 'intrinsics_error[2]'),
])
def test_every_entry_of_a_vector_parameter_is_range_checked(cls, values, needle):
    with pytest.raises(ParameterError) as info:
        cls.from_mapping(values)
    assert needle in str(info.value), str(info.value)


def test_an_empty_list_and_an_integer_for_a_float_are_one_line_errors():
    with pytest.raises(ParameterError, match='sets must be a non-empty list'):
        FeaturesParams.from_mapping({'sets': None})  # what ROS gives for `sets:=[]`
    with pytest.raises(ParameterError, match='write 1.0'):
        ServoParams.from_mapping({'gain': 1}, strict=True)  # rclpy would refuse the node
    with pytest.raises(ParameterError, match='write'):
        ArmSimParams.from_mapping({'hand_eye': [0, 0.0, 0.0, 0.0, 0.0, 0.0]}, strict=True)


def test_params_files_of_a_command_line(tmp_path):
    argv = ['servo', '--params-file', 'not-ros', '--ros-args', '-p', 'a:=1', '--params-file',
            'A.yaml', '--', '--params-file', 'B', '--ros-args', '--params-file', 'C.yaml']
    assert params_files(argv) == ['A.yaml', 'C.yaml']
    (tmp_path / 'bad.yaml').write_text('servo:\n  ros__parameters:\n    gain: [1,\n')
    (tmp_path / 'list.yaml').write_text('- 1\n- 2\n')
    for path, needle in ((tmp_path / 'none.yaml', 'does not exist'),
                         (tmp_path, 'not a file'), (tmp_path / 'bad.yaml', 'cannot read'),
                         (tmp_path / 'list.yaml', 'not a YAML mapping')):
        with pytest.raises(ConfigError, match=needle):
            check_params_files(['--ros-args', '--params-file', str(path)])
    check_params_files(['--ros-args', '--params-file', str(PARAMS / 'arm_sim.yaml')])


def test_the_guard_logs_and_goes_safe():
    """An exception a callback did not expect is logged; the node goes safe and lives."""

    class Logger:

        def __init__(self):
            self.lines = []

        def error(self, text, **kw):
            self.lines.append(text)

    class Node:

        def __init__(self):
            self.logger, self.safe = Logger(), []

        def get_logger(self):
            return self.logger

        def go_safe(self, *args):
            self.safe.append(args)

        @guard.guarded
        def on_msg(self, msg):
            raise ZeroDivisionError('division by zero')

        @guard.guarded_service
        def on_call(self, request, response):
            raise KeyError('k')

    class Response:

        success, message = True, ''

    n = Node()
    assert n.on_msg('m') is None and n.safe == [('m',)]
    assert 'ZeroDivisionError: division by zero' in n.logger.lines[0]
    r = n.on_call(None, Response())
    assert r.success is False and 'KeyError' in r.message


# --- the launcher's check of a scenario, before anything starts ------------------------------
def _scenario(tmp_path, params: str, nodes='[arm_sim, detector, features, servo]',
              extra: str = '') -> Path:
    (tmp_path / 'p.yaml').write_text(params)
    path = tmp_path / 'sc.yaml'
    path.write_text(f'nodes: {nodes}\nparams: [{PARAMS / "arm_sim.yaml"}, '
                    f'{PARAMS / "special_sphere.yaml"}, p.yaml]\nteach: true\n{extra}')
    return path


SCENARIOS = {
    'r_hat negative': ('servo:\n  ros__parameters:\n    r_hat: -1.0\n', 'r_hat must be in'),
    'misspelt parameter': ('servo:\n  ros__parameters:\n    gian: 5.0\n',
                           'unknown parameter gian'),
    'unknown target kind': ('features:\n  ros__parameters:\n    target_kind: cube\n',
                            'target_kind must be one of'),
    'integer for a float': ('arm_sim:\n  ros__parameters:\n    camera_rate: 30\n',
                            'write 30.0'),
    'missing desired_image': ('features:\n  ros__parameters:\n    desired_source: image\n'
                              '    desired_image: /nonexistent/d.png\n',
                              '[features] refused to start: desired_image '
                              "'/nonexistent/d.png' is not a file"),
    'unreachable start pose': ('arm_sim:\n  ros__parameters:\n'
                               '    start_cMo: [0.0, 0.0, 5.0, 0.0, 0.0, 0.0]\n',
                               '[arm_sim] refused to start: no UR5 configuration reaches '
                               'start_cMo'),
    'timeout not a number': ('', 'timeout must be a number'),
    'unknown node': ('', "unknown node 'servoo'"),
}


@pytest.mark.parametrize('case', SCENARIOS)
def test_a_bad_scenario_is_one_line_exit_2_and_nothing_starts(case, tmp_path, capsys,
                                                              monkeypatch):
    params, needle = SCENARIOS[case]
    path = _scenario(tmp_path, params,
                     nodes='[arm_sim, servoo]' if case == 'unknown node' else
                     '[arm_sim, detector, features, servo]',
                     extra='timeout: abc\n' if case == 'timeout not a number' else '')

    def started(*a, **k):
        raise AssertionError('a process was started')
    monkeypatch.setattr(processes.Launcher, 'start', started)
    assert launcher.main(['--config', str(path), '--until-converged']) == ExitCode.BAD_CONFIG
    out = capsys.readouterr()
    said = [ln for ln in (out.out + out.err).splitlines() if needle in ln]
    assert len(said) == 1, out
    assert 'Traceback' not in out.out + out.err


def test_the_shipped_scenarios_pass_the_check():
    for path in sorted((REPO / 'config' / 'scenarios').glob('*.yaml')):
        assert launcher.preflight(load_scenario(path)) == '', path


# --- the nodes' own refusals (installed executables) -----------------------------------------
def test_each_node_refuses_bad_parameters_with_one_line_and_exit_2(launch, tmp_path):
    (tmp_path / 'bad.yaml').write_text('servo:\n  ros__parameters:\n    gain: [1,\n')
    (tmp_path / 'mixed.yaml').write_text("servo:\n  ros__parameters:\n    gain: [1.0, 'a']\n")
    cases = {  # name: (node, args, what the one line names)
        'misspelt -p gian:=5': ('servo', ['-p', 'gian:=5'], 'unknown parameter gian'),
        'missing params file': ('servo', ['--params-file', str(tmp_path / 'none.yaml')],
                                'does not exist'),
        'malformed params file': ('servo', ['--params-file', str(tmp_path / 'bad.yaml')],
                                  'cannot read'),
        'unreadable params file (a directory)': ('servo', ['--params-file', str(tmp_path)],
                                                 'not a file'),
        'params file rcl refuses': ('servo', ['--params-file', str(tmp_path / 'mixed.yaml')],
                                    'Sequence should be of same type'),
        'sets:=[]': ('features', ['-p', 'sets:=[]'], 'sets must be a non-empty list'),
        'intrinsics_error px -1': ('detector', ['-p', 'intrinsics_error:=[-1.0, 0.0, 0.0, 0.0]'],
                                   'intrinsics_error px = -1.0 must be > -1'),
        'start_joints out of range': ('arm_sim', ['-p', 'start_joints:=[0.0, -1.57, 7.0, '
                                                  '-1.57, -1.57, 0.0]'],
                                      'start_joints[2] must be in'),
        'a bad desired_file': ('features', ['-p', f'desired_file:={tmp_path / "bad.yaml"}'],
                               'is not a kept desired'),
    }
    procs = {case: launch(node, '--ros-args', *args)  # all at once: the machine's 2 cores
             for case, (node, args, _) in cases.items()}
    for case, proc in procs.items():
        rc = proc.popen.wait(60)
        log = proc.log()
        refusals = [ln for ln in log.splitlines() if 'refused to start' in ln]
        assert rc == 2, (case, rc, log)
        assert len(refusals) == 1 and cases[case][2] in refusals[0], (case, log)
        assert 'Traceback' not in log, (case, log)


# --- the launcher over DDS -------------------------------------------------------------------
def test_a_node_that_dies_during_start_up_ends_the_launch_at_once(ros_env, tmp_path,
                                                                  monkeypatch):
    """
    The features node refuses (a file gone between the check and the start): exit 3 at once.

    Its own line is reported, not a missing service; the arm never jumped.
    """
    path = _scenario(tmp_path, 'features:\n  ros__parameters:\n    desired_source: image\n'
                     '    desired_image: /nonexistent/d.png\n')
    monkeypatch.setattr(launcher, 'preflight', lambda sc: '')  # as if the file had been there
    out = io.StringIO()
    t0 = time.monotonic()
    code, sup, codes = launcher.run(load_scenario(path), until_converged=True, out=out,
                                    env=ros_env)
    took = time.monotonic() - t0
    log = out.getvalue()
    assert code is ExitCode.NODE_DIED and codes['features'] == 2, log[-3000:]
    said = [ln for ln in log.splitlines() if ln.startswith('[launcher]')]
    assert any('features exited with code 2' in ln and "desired_image '/nonexistent/d.png' "
               'is not a file' in ln for ln in said), said
    assert 'not available' not in log and 'at the desired pose' not in log, said
    assert took < 30.0, took  # not a service timeout (30 s)
    print(f'the launch ended {took:.1f} s after it began: {said}')


def test_a_killed_launcher_leaves_no_file_and_no_node(launch, ros_env, tmp_path):
    """SIGKILL: the launcher writes no temporary file, and its nodes exit (PR_SET_PDEATHSIG)."""
    tmp = tmp_path / 'tmp'
    tmp.mkdir()
    (tmp_path / 'servo.yaml').write_text('servo:\n  ros__parameters:\n    timeout: 0.5\n')
    sc = tmp_path / 'sc.yaml'
    sc.write_text('nodes: [servo]\nparams: [servo.yaml]\nteach: false\n')
    proc = launch('launcher', '--config', str(sc), env_extra={'TMPDIR': str(tmp)})
    wait_for(lambda: 'servo' in proc.log() and '[servo]' in proc.log(), 60.0,
             what='the servo to start')
    pids = [int(p) for p in os.listdir('/proc') if p.isdigit()]

    def servo_alive():
        for pid in pids:
            try:
                cmd = Path(f'/proc/{pid}/cmdline').read_bytes()
                env = Path(f'/proc/{pid}/environ').read_bytes()
            except OSError:
                continue
            if b'servo' in cmd and f'ROS_DOMAIN_ID={ros_env["ROS_DOMAIN_ID"]}'.encode() in env \
                    and pid != proc.popen.pid:
                state = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0]
                if state != 'Z':
                    return True
        return False
    proc.popen.kill()
    proc.popen.wait(5)
    wait_for(lambda: not servo_alive(), 20.0, what='the servo to exit')
    assert sorted(os.listdir(tmp)) == [], os.listdir(tmp)
