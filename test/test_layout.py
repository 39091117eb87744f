"""The package's layout rules, checked on the source (no import is executed).

- Layers, lowest first: ``core < vision < sim < pipeline < ros < bag < bringup < experiments``.
  A module imports only modules of its own layer or of lower ones, and no module imports
  itself back through others (no cycles, lazy imports inside functions included).
- The ROS-free layers (core, vision, sim, pipeline) import neither rclpy nor a message or
  service package: they are what the nodes, the headless loop and the bag tools share.
- No source file of the package is over 500 lines; no benchmark module is installed.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / 'sphere_servo'
LAYERS = ('core', 'vision', 'sim', 'pipeline', 'ros', 'bag', 'bringup', 'experiments')
ROS_FREE = ('core', 'vision', 'sim', 'pipeline')
# top-level modules that are ROS itself: the client library, its tooling, and the
# interface packages of common_interfaces and rcl_interfaces
ROS_MODULES = ('rclpy', 'rcl_interfaces', 'builtin_interfaces', 'std_msgs', 'std_srvs',
               'sensor_msgs', 'geometry_msgs', 'diagnostic_msgs', 'rosgraph_msgs',
               'visualization_msgs', 'nav_msgs', 'shape_msgs', 'stereo_msgs',
               'trajectory_msgs', 'action_msgs', 'lifecycle_msgs', 'unique_identifier_msgs',
               'type_description_interfaces', 'service_msgs', 'tf2_msgs')
MAX_LINES = 500
# the redesign in progress (issue 12): files still to split, imports still to turn around;
# each entry is removed by the change that fixes it (a fixed entry fails as XPASS)
KNOWN_OVERSIZE = {'sphere_servo/bringup/launcher.py',
                  'sphere_servo/experiments/paper.py', 'sphere_servo/experiments/study.py',
                  'sphere_servo/vision/detector.py'}
KNOWN_UPWARD: set = set()


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
    """Every module named by an import statement anywhere in the file, absolute, with its
    line (``from a import b`` gives both ``a`` and ``a.b``: b may be a module)."""
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


def _graph() -> dict[str, set[str]]:
    g = {}
    for mod, path in MODULES.items():
        g[mod] = {name for name, _ in _imports(mod, path) if name in MODULES and name != mod}
    return g


def test_every_module_lives_in_a_known_layer():
    stray = [m for m in MODULES if m != 'sphere_servo' and _layer(m) not in LAYERS]
    assert not stray, f'modules outside the layers {LAYERS}: {stray}'


def test_no_import_from_a_higher_layer():
    bad = []
    for mod, path in MODULES.items():
        lay = _layer(mod)
        if lay is None or mod in KNOWN_UPWARD:
            continue
        for name, line in _imports(mod, path):
            other = _layer(name)
            if other in LAYERS and LAYERS.index(other) > LAYERS.index(lay):
                bad.append(f'{path.relative_to(REPO)}:{line} ({lay}) imports {name} ({other})')
    assert not bad, 'imports from a higher layer:\n' + '\n'.join(bad)


def test_ros_free_layers_do_not_import_ros():
    bad = []
    for mod, path in MODULES.items():
        if _layer(mod) not in ROS_FREE:
            continue
        for name, line in _imports(mod, path):
            if name.split('.')[0] in ROS_MODULES:
                bad.append(f'{path.relative_to(REPO)}:{line} imports {name}')
    assert not bad, 'ROS imported by a ROS-free layer:\n' + '\n'.join(bad)


def test_no_import_cycles():
    g = _graph()
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
    assert not cycles, 'import cycles:\n' + '\n'.join(cycles)


def test_the_layer_check_can_fail():
    """The checks see relative and lazy imports (a check that sees nothing passes)."""
    src = ('from ..ros import servo\n'
           'def f():\n'
           '    import rclpy\n'
           '    from . import loop\n')
    path = PKG / 'sim' / '_probe_for_test.py'
    path.write_text(src)
    try:
        names = {n for n, _ in _imports('sphere_servo.sim._probe_for_test', path)}
    finally:
        path.unlink()
    assert {'sphere_servo.ros', 'sphere_servo.ros.servo', 'rclpy',
            'sphere_servo.sim.loop'} <= names


@pytest.mark.parametrize('path', sorted(PKG.rglob('*.py')), ids=lambda p: str(
    p.relative_to(REPO)))
def test_source_files_are_at_most_500_lines(path, request):
    if str(path.relative_to(REPO)) in KNOWN_OVERSIZE:
        request.applymarker(pytest.mark.xfail(strict=True, reason='to split (issue 12)'))
    n = len(path.read_text().splitlines())
    assert n <= MAX_LINES, f'{path.relative_to(REPO)} has {n} lines (> {MAX_LINES}): split it'


def test_benchmarks_are_not_installed():
    assert not list(PKG.rglob('bench*.py')), 'benchmark modules inside the installed package'
    setup = (REPO / 'setup.py').read_text()
    assert "include=['sphere_servo', 'sphere_servo.*']" in setup, \
        'setup.py must install sphere_servo only (benchmarks/ and test/ stay out)'
