"""
The nodes' parameter dataclasses without ROS: built from a mapping, validated, frozen.

Every params file and scenario of the package builds every node's parameters (data this
code did not make); bad values, wrong types and broken cross-parameter rules are refused
with a message that names the parameter.
"""
from __future__ import annotations

import array
import dataclasses
from pathlib import Path

import pytest

from sphere_servo.pipeline.config import load_params_files, load_scenario, section
from sphere_servo.pipeline.params import (ArmSimParams, DetectorParams, FeaturesParams,
                                          NODE_PARAMS as NODES, ParameterError, ServoParams)

CONFIG = Path(__file__).resolve().parents[1] / 'config'
CONFIGS = sorted(CONFIG.glob('params/*.yaml')) + sorted(CONFIG.glob('scenarios/*.yaml'))


@pytest.mark.parametrize('cls', NODES.values(), ids=NODES.keys())
def test_defaults_are_the_table_and_round_trip(cls):
    p = cls.from_mapping({})
    table = cls.table()
    assert p.to_mapping() == {name: prm.default for name, prm in table.items()}
    assert cls.from_mapping(p.to_mapping()) == p
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(p, dataclasses.fields(p)[0].name, None)


@pytest.mark.parametrize('path', CONFIGS, ids=lambda p: f'{p.parent.name}/{p.name}')
def test_every_config_builds_every_node(path):
    """Each params file alone, and each scenario's params files merged in order."""
    cfg = load_scenario(path).params if path.parent.name == 'scenarios' \
        else load_params_files([path])
    for node, cls in NODES.items():
        given = section(cfg, node)
        p = cls.from_mapping(given)
        flat = p.to_mapping()
        for key, value in given.items():  # nested sections are ROS's dotted names
            if isinstance(value, dict):
                for sub, v in value.items():
                    assert flat[f'{key}.{sub}'] == v, (node, key, sub)
            elif key in flat:
                assert flat[key] == value, (node, key)


def test_names_and_types():
    p = ArmSimParams.from_mapping({'camera': {'px': 500, 'width': 320},
                                   'target.kind': 'cc', 'hand_eye': (0, 0, 0.1, 0, 0, 0),
                                   'start_joints': array.array('d', [0.1] * 6),
                                   'use_sim_time': True})  # not a parameter: ignored
    assert p.camera_px == 500.0 and isinstance(p.camera_px, float)
    assert p.camera_width == 320 and p.target_kind == 'cc'
    assert p.hand_eye == (0.0, 0.0, 0.1, 0.0, 0.0, 0.0) and p.start_joints == (0.1,) * 6
    assert FeaturesParams.from_mapping({'sets': ['s', 's_cc']}).sets == ('s', 's_cc')


@pytest.mark.parametrize('cls, values, needle', [
    (ServoParams, {'r_hat': -0.05}, 'r_hat must be in'),
    (ServoParams, {'r_hat': float('nan')}, 'r_hat must be finite'),
    (ServoParams, {'feature_set': 's_cc'}, 'feature_set must be one of'),
    (ServoParams, {'gain': True}, 'gain must be of the type'),
    (ServoParams, {'adaptive': 1}, 'adaptive must be of the type'),
    (ServoParams, {'tol': '1e-3'}, 'tol must be of the type'),
    (DetectorParams, {'intrinsics_error': [0.1, 0.2]}, 'intrinsics_error needs 4'),
    (DetectorParams, {'intrinsics_error': [0.1, 0.2, float('inf'), 0]}, 'NaN or inf'),
    (ArmSimParams, {'camera.width': 64.0}, 'camera.width must be of the type'),
    (ArmSimParams, {'target': {'axes': [0.06, 0.0, 0.045]}}, 'target.axes must be > 0'),
    (ArmSimParams, {'camera_rate': -1.0}, 'camera_rate'),
    (FeaturesParams, {'sets': ['s_x']}, 'unknown feature set'),
    (FeaturesParams, {'sets': []}, 'at least one feature set'),
    (FeaturesParams, {'sets': [1.0]}, 'sets must be of the type'),
])
def test_refused_values_name_the_parameter(cls, values, needle):
    with pytest.raises(ParameterError, match=needle):
        cls.from_mapping(values)


def test_cross_parameter_rules_hold_at_start_and_on_change():
    with pytest.raises(ParameterError, match='singular_threshold must be > singular_stop'):
        ArmSimParams.from_mapping({'singular_threshold': 0.01, 'singular_stop': 0.01})
    p = ArmSimParams.from_mapping({})
    with pytest.raises(ParameterError, match='singular_threshold must be > singular_stop'):
        p.replace({'singular_stop': 0.05})
    moved = p.replace({'start_cMo': [0.0, 0.0, 0.5, 0.0, 0.0, 0.0]})
    assert moved.start_cMo == (0.0, 0.0, 0.5, 0.0, 0.0, 0.0) and p.start_cMo != moved.start_cMo
    # the adaptive gain must decrease, but only when it is used
    assert not ServoParams.from_mapping({'lambda_0': 0.2, 'lambda_inf': 0.3}).adaptive
    with pytest.raises(ParameterError, match='lambda_0 > lambda_inf'):
        ServoParams.from_mapping({'adaptive': True, 'lambda_0': 0.2, 'lambda_inf': 0.3})
