"""
The package's layout rules, checked on the source (no import is executed).

- Layers, lowest first: ``core < vision < sim < pipeline < ros < bag < bringup < experiments``.
  A module imports only modules of its own layer or of lower ones, and no module imports
  itself back through others (no cycles). Imports inside functions count as well.
- The ROS-free layers (core, vision, sim, pipeline) import neither rclpy nor a message,
  service or action package: they are what the nodes, the headless loop and the bag tools
  share.
- No source file of the package is over 500 lines; no benchmark module is installed.

``test_the_layer_check_can_fail`` runs the three import checks on probe modules that break
their rules: a check that stopped seeing imports would pass on any tree, and fails there.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / 'sphere_servo'
LAYERS = ('core', 'vision', 'sim', 'pipeline', 'ros', 'bag', 'bringup', 'experiments')
ROS_FREE = ('core', 'vision', 'sim', 'pipeline')
# top-level modules that are ROS itself: the client library, the rosidl runtime that looks
# message classes up, and interface packages by name (any ``<pkg>.msg``, ``.srv`` or
# ``.action`` is an interface package too: see _is_ros)
ROS_MODULES = ('rclpy', 'rosidl_runtime_py', 'rcl_interfaces', 'builtin_interfaces',
               'std_msgs', 'std_srvs', 'sensor_msgs', 'geometry_msgs', 'diagnostic_msgs',
               'rosgraph_msgs', 'visualization_msgs', 'nav_msgs', 'shape_msgs',
               'stereo_msgs', 'trajectory_msgs', 'action_msgs', 'lifecycle_msgs',
               'unique_identifier_msgs', 'type_description_interfaces', 'service_msgs',
               'tf2_msgs')
INTERFACE_SUBMODULES = ('msg', 'srv', 'action')
MAX_LINES = 500


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PKG.rglob('*.py')):
        rel = path.relative_to(REPO).with_suffix('')
        parts = list(rel.parts)
        if parts[-1] == '__init__':
            parts = parts[:-1]
        out['.'.join(parts)] = path
    return out


def _imports(module: str, path: Path) -> list[tuple[str, int]]:
    """
    List every module named by an import statement anywhere in the file, with its line.

    Names are absolute (relative imports resolved against ``module``); ``from a import b``
    gives both ``a`` and ``a.b``, since b may be a module.
    """
    tree = ast.parse(path.read_text(), str(path))
    is_pkg = path.name == '__init__.py'
    here = module.split('.') if is_pkg else module.split('.')[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[:len(here) - node.level + 1]
                name = '.'.join(base + ([node.module] if node.module else []))
            else:
                name = node.module
            out.append((name, node.lineno))
            out += [(f'{name}.{a.name}', node.lineno) for a in node.names]
    return out


MODULES = _modules()


def _layer(module: str) -> str | None:
    parts = module.split('.')
    return parts[1] if len(parts) > 1 and parts[0] == 'sphere_servo' else None


def _is_ros(name: str) -> bool:
    parts = name.split('.')
    return parts[0] in ROS_MODULES or (len(parts) > 1 and parts[1] in INTERFACE_SUBMODULES)


def _where(path: Path) -> Path:
    return path.relative_to(REPO) if path.is_relative_to(REPO) else path


def _upward_imports(modules: dict[str, Path]) -> list[str]:
    """List the imports of a module from a layer above its own, as ``file:line`` lines."""
    bad = []
    for mod, path in modules.items():
        lay = _layer(mod)
        if lay not in LAYERS:  # the package itself, or a stray: its own test reports it
            continue
        for name, line in _imports(mod, path):
            other = _layer(name)
            if other in LAYERS and LAYERS.index(other) > LAYERS.index(lay):
                bad.append(f'{_where(path)}:{line} ({lay}) imports {name} ({other})')
    return bad


def _ros_imports(modules: dict[str, Path]) -> list[str]:
    """List the imports of ROS by a module of a ROS-free layer, as ``file:line`` lines."""
    bad = []
    for mod, path in modules.items():
        if _layer(mod) not in ROS_FREE:
            continue
        for name, line in _imports(mod, path):
            if _is_ros(name):
                bad.append(f'{_where(path)}:{line} imports {name}')
    return bad


def _graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    g = {}
    for mod, path in modules.items():
        g[mod] = {name for name, _ in _imports(mod, path) if name in modules and name != mod}
    return g


def _cycles(g: dict[str, set[str]]) -> list[str]:
    """List the import cycles of graph ``g`` found by a depth-first search, as ``a → b → a``."""
    color, stack, cycles = {}, [], []

    def visit(m):
        color[m] = 1
        stack.append(m)
        for n in sorted(g[m]):
            if color.get(n) == 1:
                cycles.append(' → '.join(stack[stack.index(n):] + [n]))
            elif n not in color:
                visit(n)
        stack.pop()
        color[m] = 2
    for m in sorted(g):
        if m not in color:
            visit(m)
    return cycles


def test_every_module_lives_in_a_known_layer():
    stray = [m for m in MODULES if m != 'sphere_servo' and _layer(m) not in LAYERS]
    assert not stray, f'modules outside the layers {LAYERS}: {stray}'


def test_no_import_from_a_higher_layer():
    bad = _upward_imports(MODULES)
    assert not bad, 'imports from a higher layer:\n' + '\n'.join(bad)


def test_ros_free_layers_do_not_import_ros():
    bad = _ros_imports(MODULES)
    assert not bad, 'ROS imported by a ROS-free layer:\n' + '\n'.join(bad)


def test_no_import_cycles():
    cycles = _cycles(_graph(MODULES))
    assert not cycles, 'import cycles:\n' + '\n'.join(cycles)


def test_the_layer_check_can_fail(tmp_path):
    """
    Each import check reports a probe that breaks its rule (a check that sees nothing passes).

    The probe, a sim module, imports the ros layer relatively at the top, and rclpy, a
    sibling and a message package inside a function; the sibling imports the probe back.
    """
    path = tmp_path / '_probe_for_test.py'
    path.write_text('from ..ros import servo\n'
                    'def f():\n'
                    '    import rclpy\n'
                    '    from . import loop\n'
                    '    from foo_msgs.msg import Bar\n')
    sibling = tmp_path / 'loop.py'
    sibling.write_text('from sphere_servo.sim import _probe_for_test\n')
    probe = {'sphere_servo.sim._probe_for_test': path, 'sphere_servo.sim.loop': sibling}
    names = {n for n, _ in _imports('sphere_servo.sim._probe_for_test', path)}
    assert {'sphere_servo.ros', 'sphere_servo.ros.servo', 'rclpy',
            'sphere_servo.sim.loop'} <= names
    assert set(_upward_imports(probe)) == {
        f'{path}:1 (sim) imports sphere_servo.ros (ros)',
        f'{path}:1 (sim) imports sphere_servo.ros.servo (ros)'}
    assert set(_ros_imports(probe)) == {
        f'{path}:3 imports rclpy', f'{path}:5 imports foo_msgs.msg',
        f'{path}:5 imports foo_msgs.msg.Bar'}
    assert _cycles(_graph(probe)) == [
        'sphere_servo.sim._probe_for_test → sphere_servo.sim.loop → '
        'sphere_servo.sim._probe_for_test']


@pytest.mark.parametrize('path', sorted(PKG.rglob('*.py')), ids=lambda p: str(
    p.relative_to(REPO)))
def test_source_files_are_at_most_500_lines(path):
    n = len(path.read_text().splitlines())
    assert n <= MAX_LINES, f'{path.relative_to(REPO)} has {n} lines (> {MAX_LINES}): split it'


def test_benchmarks_are_not_installed():
    assert not list(PKG.rglob('bench*.py')), 'benchmark modules inside the installed package'
    setup = (REPO / 'setup.py').read_text()
    assert "include=['sphere_servo', 'sphere_servo.*']" in setup, \
        'setup.py must install sphere_servo only (benchmarks/ and test/ stay out)'
