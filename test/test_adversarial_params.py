"""
Adversarial parameter values, as a params file gives them (YAML read by PyYAML).

- an integer too large for a float (YAML reads ``999…9`` as a Python int of any size): a
  :class:`ParameterError` naming the parameter, never an ``OverflowError`` from inside;
- a params file given to the offline tools (``refeatures --config FILE``) is checked as a
  node checks its own: a misspelt name, or a mapping where a number belongs (which ROS
  flattens to ``gain.a``), is refused; before, it was ignored and the default used.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from sphere_servo.pipeline.params import (DetectorParams, FeaturesParams, ParameterError,
                                          ServoParams)

HUGE = int('9' * 400)  # what yaml.safe_load gives for 400 nines


@pytest.mark.parametrize('cls, name, value', [
    (ServoParams, 'gain', HUGE),
    (ServoParams, 'timeout', -HUGE),
    (DetectorParams, 'intrinsics_error', [0.0, 0.0, 0.0, HUGE]),
    (FeaturesParams, 'desired_cMo', [0.0, 0.0, HUGE, 0.0, 0.0, 0.0]),
], ids=['gain', 'timeout', 'intrinsics_error', 'desired_cMo'])
def test_an_integer_too_large_for_a_float_is_refused_by_name(cls, name, value):
    with pytest.raises(ParameterError, match=name):
        cls.from_mapping({name: value})


def _write(tmp_path: Path, text: str) -> str:
    path = tmp_path / 'params.yaml'
    path.write_text(text)
    return str(path)


def test_a_params_file_is_read_with_its_values(tmp_path):
    """The baseline: a params file's servo gain and features sets are the settings'."""
    pytest.importorskip('rclpy')
    from sphere_servo.bag.offline import load_settings
    s = load_settings(_write(tmp_path, 'servo:\n  ros__parameters:\n    gain: 0.25\n'
                                       'features:\n  ros__parameters:\n    sets: [s_n, s]\n'))
    assert s.servo.gain == 0.25 and s.features.sets == ('s_n', 's')


@pytest.mark.parametrize('text, needle', [
    ('servo:\n  ros__parameters:\n    gian: 0.25\n', 'gian'),           # misspelt
    ('servo:\n  ros__parameters:\n    gain: {a: 1}\n', 'gain.a'),       # a mapping
    ('detector:\n  ros__parameters:\n    gain: 0.25\n', 'gain'),        # another node's
], ids=['misspelt', 'mapping', 'other node'])
def test_a_params_file_with_a_name_no_node_has_is_refused(tmp_path, text, needle):
    """The node would refuse to start with it; the offline tools must not run without it."""
    pytest.importorskip('rclpy')
    from sphere_servo.bag.offline import load_settings
    with pytest.raises(ParameterError, match=needle):
        load_settings(_write(tmp_path, text))


def test_refeatures_exits_1_on_a_huge_integer_in_its_config(tmp_path):
    """The error is one line on stderr, not an OverflowError's traceback."""
    pytest.importorskip('rclpy')
    from test_refeatures import _images_only_bag, _run
    _images_only_bag(tmp_path / 'bag')
    cfg = _write(tmp_path, f'servo:\n  ros__parameters:\n    gain: {HUGE}\n')
    code, out, err = _run([str(tmp_path / 'bag'), '--desired', 'stamp:1.0', '--config', cfg])
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 1 and len(lines) == 1 and 'gain' in lines[0], (out, err)
