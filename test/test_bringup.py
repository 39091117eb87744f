"""The launcher's command-line contract without ROS: exit codes, and a bad config refused."""
from __future__ import annotations

import io

from sphere_servo.bringup import launcher
from sphere_servo.bringup.launcher import ExitCode
from sphere_servo.experiments import demo
from sphere_servo.pipeline.config import scenario


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
