"""
Params files, scenarios, the launch file and the declared dependencies, without DDS.

The shipped params files are plain ROS 2 params files naming only declared parameters; a
scenario's merged parameters are what rcl itself reads from the same files given as
several ``--params-file`` (checked against rclpy's parser); the launch file compiles and
starts the scenario's nodes with its params files; every third-party module the package
imports is declared in package.xml and setup.py.
"""
from __future__ import annotations

import ast
from pathlib import Path
import re
import sys
import xml.etree.ElementTree as ET

from conftest import _acquire_domain_id
import pytest
from sphere_servo.pipeline.config import (check_params_file, ConfigError, load_node_params,
                                          load_scenario, read_yaml, scenario, section)
from sphere_servo.pipeline.params import NODE_PARAMS, ParameterError
import yaml

REPO = Path(__file__).resolve().parents[1]
PARAMS = sorted((REPO / 'config' / 'params').glob('*.yaml'))
SCENARIOS = sorted((REPO / 'config' / 'scenarios').glob('*.yaml'))
# parameters every rclpy node declares itself
ROS_LEVEL = {'use_sim_time', 'start_type_description_service'}


def _flat(d: dict, prefix: str = '') -> dict:
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f'{prefix}{k}.') if isinstance(v, dict) else {f'{prefix}{k}': v})
    return out


def test_the_shipped_scenarios_and_params_files_exist():
    assert [p.stem for p in SCENARIOS] == ['balloon', 'calibration_error', 'catadioptric',
                                           'cc_target', 'fisheye', 'special_sphere',
                                           'wrong_radius']
    assert not list((REPO / 'config').glob('*.yaml')), 'configs live in params/, scenarios/'
    for path in SCENARIOS:
        sc = load_scenario(path)
        assert sc.nodes == ('arm_sim', 'detector', 'features', 'servo') and sc.teach
        assert [p.name for p in sc.params_files[:2]] == ['arm_sim.yaml', 'special_sphere.yaml']
        assert all(p.parent == REPO / 'config' / 'params' for p in sc.params_files)
        assert not sc.node_params('servo')['start_enabled']  # the launcher teaches first


@pytest.mark.parametrize('path', PARAMS, ids=lambda p: p.name)
def test_params_files_are_plain_and_name_declared_parameters_only(path):
    """A typo in a params file would be ignored by the node: every key must be declared."""
    data = check_params_file(read_yaml(path), path)
    assert set(data) <= set(NODE_PARAMS), set(data)
    for node, sec in data.items():
        unknown = set(_flat(sec['ros__parameters'])) - set(NODE_PARAMS[node].table()) - \
            ROS_LEVEL
        assert not unknown, (node, unknown)


def _write(tmp: Path, name: str, text: str) -> Path:
    (tmp / name).write_text(text)
    return tmp / name


def test_the_merge_is_what_rcl_reads_from_several_params_files(tmp_path):
    """The scenario's merge against rcl's own parser, on files with overlaps and nesting."""
    import rclpy
    _write(tmp_path, 'a.yaml', 'arm_sim:\n  ros__parameters:\n    camera:\n      px: 500.0'
           '\n      py: 510.0\n    start_joints: [0.0, -1.0, 1.0, -1.0, -1.0, 0.0]\n'
           '    camera_rate: 20.0\nservo:\n  ros__parameters:\n    gain: 2.0\n')
    _write(tmp_path, 'b.yaml', 'arm_sim:\n  ros__parameters:\n    camera:\n      py: 520.0'
           '\n    start_joints: [0.1, -1.1, 1.1, -1.1, -1.1, 0.1]\n')
    sc = load_scenario(_write(tmp_path, 's.yaml', 'nodes: [arm_sim]\nparams: [a.yaml, b.yaml]\n'))
    ours = _flat(sc.node_params('arm_sim'))
    assert ours == {'camera.px': 500.0, 'camera.py': 520.0, 'camera_rate': 20.0,
                    'start_joints': [0.1, -1.1, 1.1, -1.1, -1.1, 0.1]}
    domain, lock = _acquire_domain_id()
    ctx = rclpy.Context()
    try:
        args = ['--ros-args'] + [x for p in sc.params_files for x in ('--params-file', str(p))]
        rclpy.init(context=ctx, args=args, domain_id=domain)
        node = rclpy.create_node('arm_sim', context=ctx,
                                 automatically_declare_parameters_from_overrides=True)
        theirs = {name: p.value for name, p in node.get_parameters_by_prefix('').items()
                  if name not in ROS_LEVEL}
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
        lock.close()
    assert {k: list(v) if not isinstance(v, (int, float, str)) else v
            for k, v in theirs.items()} == ours


@pytest.mark.parametrize('text, files, needle', [
    ('nodes: [servo]\nparams: [p.yaml]\nwhatever: 1\n', {}, "unknown key(s) ['whatever']"),
    ('nodes: [servo, planner]\n', {}, "unknown node 'planner'"),
    ('params: [missing.yaml]\n', {}, 'does not exist'),
    ('params: [p.yaml]\n', {'p.yaml': 'launch:\n  include: [x.yaml]\n'},
     'is not "launch: ros__parameters'),
    ('params: [p.yaml]\n', {'p.yaml': 'servo:\n  ros__parameters:\n    r_hat: -1.0\n'},
     'servo: r_hat must be in'),
    ('params: [p.yaml]\nteach: yes please\n', {'p.yaml': ''}, 'teach must be true or false'),
    ('timeout: -3\n', {}, 'timeout must be a number of seconds > 0'),
])
def test_a_bad_scenario_is_refused_with_its_path(tmp_path, text, files, needle):
    for name, body in files.items():
        _write(tmp_path, name, body or 'servo:\n  ros__parameters: {}\n')
    path = _write(tmp_path, 'bad.yaml', text)
    with pytest.raises(ConfigError) as exc:
        load_scenario(path)
    assert needle in str(exc.value) and str(path) in str(exc.value)


def test_a_scenario_by_name_and_params_by_scenario_or_file():
    sc = scenario('cc_target')
    assert sc.name == 'cc_target' and sc.node_params('features')['target_kind'] == 'cc'
    assert sc.node_params('features')['sets'] == ['s_n', 's', 's_cc']  # special_sphere.yaml
    assert section(load_node_params('cc_target'), 'detector')['target_kind'] == 'cc'
    one = load_node_params(str(REPO / 'config' / 'params' / 'cc_target.yaml'))
    assert set(one) == {'arm_sim', 'detector', 'features'}
    with pytest.raises(ConfigError, match="scenario 'nope' not found"):
        scenario('nope')
    with pytest.raises(ParameterError):  # the servo would refuse it: so would the launcher
        NODE_PARAMS['servo'].from_mapping({'r_hat': 0.0})


def _launch_tree() -> ast.Module:
    return ast.parse((REPO / 'launch' / 'sphere_servo.launch.py').read_text())


def test_the_launch_file_starts_the_scenarios_nodes_with_its_params_files():
    """No ``launch`` package here: the file's structure, read with ast."""
    tree = _launch_tree()
    compile(tree, 'sphere_servo.launch.py', 'exec')
    imports = {(n.module, a.name) for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
               for a in n.names}
    assert ('sphere_servo.pipeline.config', 'scenario') in imports  # the launcher's reader
    funcs = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert 'generate_launch_description' in funcs
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
    node = next(c for c in calls if getattr(c.func, 'id', '') == 'Node')
    kw = {k.arg: k.value for k in node.keywords}
    assert ast.literal_eval(kw['package']) == 'sphere_servo'
    assert ast.unparse(kw['executable']) == 'name' == ast.unparse(kw['name'])
    assert 'sc.params_files' in ast.unparse(kw['parameters'])
    loops = [ast.unparse(c.iter) for n in ast.walk(tree) if isinstance(n, ast.ListComp)
             for c in n.generators if node is n.elt]
    assert loops == ['sc.nodes']  # one Node per node of the scenario
    default = {t.id: n.value for n in tree.body if isinstance(n, ast.Assign)
               for t in n.targets if isinstance(t, ast.Name)}['DEFAULT_SCENARIO']
    assert load_scenario(REPO / 'config' / 'scenarios' / f'{ast.literal_eval(default)}.yaml')


PYPI = {'numpy': 'numpy', 'cv2': 'opencv-python-headless', 'pinocchio': 'pin',
        'yaml': 'PyYAML', 'matplotlib': 'matplotlib', 'rosbags': 'rosbags', 'PIL': 'pillow',
        'backports': 'backports.zstd', 'lz4': 'lz4', 'imageio_ffmpeg': 'imageio-ffmpeg',
        'meshcat': 'meshcat', 'umsgpack': 'u-msgpack-python'}
ROSDEP = {'numpy': 'python3-numpy', 'cv2': 'python3-opencv', 'pinocchio': 'pinocchio',
          'yaml': 'python3-yaml', 'matplotlib': 'python3-matplotlib',
          'rosbags': 'python3-rosbags-pip', 'PIL': 'python3-pil',
          # zstd and lz4 (MCAP chunk compressions) come with rosbags, which requires both
          'backports': 'python3-rosbags-pip', 'lz4': 'python3-rosbags-pip',
          'imageio_ffmpeg': 'python3-imageio-ffmpeg-pip', 'meshcat': 'python3-meshcat-pip',
          # meshcat's wire format (its viewer decodes msgpack): meshcat requires it
          'umsgpack': 'python3-meshcat-pip'}


def _third_party_imports() -> set[str]:
    mods = set()
    for p in [*(REPO / 'sphere_servo').rglob('*.py'), REPO / 'launch' / 'sphere_servo.launch.py']:
        for n in ast.walk(ast.parse(p.read_text())):
            if isinstance(n, ast.Import):
                mods |= {a.name.split('.')[0] for a in n.names}
            elif isinstance(n, ast.ImportFrom) and n.level == 0 and n.module:
                mods.add(n.module.split('.')[0])
    return mods - set(sys.stdlib_module_names) - {'sphere_servo'}


def test_every_runtime_dependency_is_declared():
    """package.xml (rosdep keys), setup.py (PyPI names) and the package's own rosdep file."""
    depends = {e.text for e in ET.parse(REPO / 'package.xml').getroot().iter('exec_depend')}
    setup = ast.parse((REPO / 'setup.py').read_text())
    call = next(n for n in ast.walk(setup) if isinstance(n, ast.Call)
                and getattr(n.func, 'id', '') == 'setup')
    requires = ast.literal_eval(next(k.value for k in call.keywords
                                     if k.arg == 'install_requires'))
    for mod in sorted(_third_party_imports()):
        if mod in PYPI:
            assert PYPI[mod] in requires and ROSDEP[mod] in depends, mod
        else:  # a ROS package: its own name is its rosdep key
            assert mod in depends, mod
    # example-robot-data ships the UR5 URDF (data, not imported)
    assert 'example-robot-data' in requires
    assert 'python3-example-robot-data-pip' in depends
    own = yaml.safe_load((REPO / 'rosdep' / 'sphere_servo.yaml').read_text())
    pip_keys = sorted(d for d in depends if d.endswith('-pip'))
    assert pip_keys == sorted(own)
    for key in pip_keys:
        for os_name in ('ubuntu', 'debian'):
            (pkg,) = own[key][os_name]['pip']['packages']
            assert pkg in requires, (key, pkg)
    pinned = {re.split('[=<>]', line)[0].lower() for line in
              (REPO / 'requirements.txt').read_text().splitlines()
              if line and not line.startswith('#')}
    assert {r.lower() for r in requires} - {'setuptools'} <= pinned
