"""
Parameter files and scenario files (no ROS).

Shared by the launcher, the launch file, the bag tools and the experiments. A *params
file* (``config/params/<name>.yaml``) is a plain ROS 2 parameters file, one
``<node>: ros__parameters: …`` section per node, as ``--ros-args --params-file`` reads it: a
node takes its own section and ignores the others'.

A *scenario* (``config/scenarios/<name>.yaml``) is what the launcher (and the launch file)
starts::

    nodes: [arm_sim, detector, features, servo]
    params: [../params/arm_sim.yaml, ../params/special_sphere.yaml]
    teach: true          # arm to desired → teach that image → arm to start → enable servo
    timeout: 180.0       # wall seconds for ``launcher --until-converged``
    record_topics: [...]  # optional: what ``launcher --record`` records

Every node is started with every params file of its scenario, in order (``--params-file``
given several times: a later file overrides the parameters it sets), and
:meth:`Scenario.node_params` merges them the same way. Paths are relative to the scenario
file. A scenario is found by path, or by name in the installed package's
``share/sphere_servo/config/scenarios`` and then in the source tree's ``config/scenarios``.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

from sphere_servo.pipeline.params import NODE_PARAMS, ParameterError
import yaml

SOURCE_CONFIG = Path(__file__).resolve().parents[2] / 'config'
SCENARIO_KEYS = ('nodes', 'params', 'teach', 'timeout', 'record_topics')
PARAMS = 'ros__parameters'


class ConfigError(RuntimeError):
    """A scenario or a params file cannot be found, read or used."""


def merge(base: dict, over: dict) -> dict:
    """Deep merge: dicts merge recursively, anything else in ``over`` replaces."""
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) \
            else copy.deepcopy(v)
    return out


def read_yaml(path: Path) -> dict:
    """Return the mapping of a YAML file; ConfigError if it cannot be read or is not one."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f'cannot read {path}: {exc}') from None
    if not isinstance(data, dict):
        raise ConfigError(f'{path} is not a YAML mapping')
    return data


def check_params_file(data: dict, path: Path) -> dict:
    """Return ``data`` if it is a plain ROS 2 params file; ConfigError otherwise."""
    for node, section in data.items():
        if not (isinstance(section, dict) and list(section) == [PARAMS]
                and isinstance(section[PARAMS], dict)):
            raise ConfigError(f'{path}: section {node!r} is not "{node}: {PARAMS}: {{…}}" '
                              '(a plain ROS 2 params file)')
    return data


def load_params_files(paths) -> dict:
    """Merge params files in order, as ROS does with several ``--params-file``."""
    merged: dict = {}
    for path in paths:
        merged = merge(merged, check_params_file(read_yaml(path), path))
    return merged


def section(params: dict, node: str) -> dict:
    """
    Return the ``ros__parameters`` of ``node`` in merged params files ({} if none).

    The sections that name it: ``/**`` (every node), then ``/<node>``, then ``<node>``.
    """
    out: dict = {}
    for key in ('/**', f'/{node}', node):
        out = merge(out, (params.get(key) or {}).get(PARAMS) or {})
    return out


@dataclass(frozen=True)
class Scenario:
    """A scenario file, read and checked (see the module docstring)."""

    path: Path
    nodes: tuple[str, ...]
    params_files: tuple[Path, ...]
    teach: bool = True
    timeout: float = 120.0
    record_topics: tuple[str, ...] | None = None
    params: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def name(self) -> str:
        """Return the stem of the scenario's file, its name."""
        return self.path.stem

    def node_params(self, node: str) -> dict:
        """Return the parameters ``node`` starts with, merged from the params files."""
        return section(self.params, node)


def _search_dirs(kind: str) -> list[Path]:
    prefix = package_prefix()
    return ([prefix / 'share' / 'sphere_servo' / 'config' / kind] if prefix else []) + \
        [SOURCE_CONFIG / kind]


def find_scenario(name: str) -> Path:
    """Find a scenario by path or by name (``special_sphere`` or ``special_sphere.yaml``)."""
    p = Path(name)
    if p.is_file():
        return p
    fname = name if name.endswith('.yaml') else f'{name}.yaml'
    dirs = _search_dirs('scenarios')
    for d in dirs:
        if (d / fname).is_file():
            return d / fname
    raise ConfigError(f'scenario {name!r} not found (looked in {", ".join(map(str, dirs))})')


def _list(data: dict, key: str, path: Path) -> list[str]:
    value = data.get(key, [])
    if not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
        raise ConfigError(f'{path}: {key} must be a list of strings, got {value!r}')
    return value


def load_scenario(path: Path) -> Scenario:
    """
    Read and check a scenario file.

    Raises ConfigError on an unknown key, an unknown node, a params file that is missing or
    not a plain params file, a parameter value a node would refuse, or a name that is not
    one of the node's parameters (a node refuses to start with it).
    """
    path = Path(path).resolve()
    data = read_yaml(path)
    unknown = sorted(set(data) - set(SCENARIO_KEYS))
    if unknown:
        raise ConfigError(f'{path}: unknown key(s) {unknown}; a scenario has '
                          f'{list(SCENARIO_KEYS)} (parameters go into a params file)')
    nodes = _list(data, 'nodes', path) if 'nodes' in data else list(NODE_PARAMS)
    for node in nodes:
        if node not in NODE_PARAMS:
            raise ConfigError(f'{path}: unknown node {node!r}, use {list(NODE_PARAMS)}')
    files = [(path.parent / f).resolve() for f in _list(data, 'params', path)]
    for f in files:
        if not f.is_file():
            raise ConfigError(f'{path}: params file {str(f)!r} does not exist')
    teach, timeout = data.get('teach', True), data.get('timeout', 120.0)
    if not isinstance(teach, bool):
        raise ConfigError(f'{path}: teach must be true or false, got {teach!r}')
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not timeout > 0:
        raise ConfigError(f'{path}: timeout must be a number of seconds > 0, got {timeout!r}')
    record = _list(data, 'record_topics', path) if 'record_topics' in data else None
    try:
        params = load_params_files(files)
    except ConfigError as exc:
        raise ConfigError(f'{path}: {exc}') from None
    sc = Scenario(path, tuple(nodes), tuple(files), teach, float(timeout),
                  None if record is None else tuple(record), params)
    for node in nodes:
        try:
            NODE_PARAMS[node].from_mapping(sc.node_params(node), strict=True)
        except ParameterError as exc:
            raise ConfigError(f'{path}: {node}: {exc}') from None
    return sc


def scenario(name: str) -> Scenario:
    """Find and read a scenario by name or path."""
    return load_scenario(find_scenario(name))


def load_node_params(spec: str) -> dict:
    """
    Return the merged params of a scenario (name or path) or of a params file (path).

    A file with a scenario's key (``nodes``, ``params``, …) is a scenario; any other file a
    params file.
    """
    p = Path(spec)
    if p.is_file() and not set(read_yaml(p)) & set(SCENARIO_KEYS):
        return load_params_files([p])
    return scenario(spec).params


def package_prefix() -> Path | None:
    """
    Return the install prefix of sphere_servo in the ament index (as ``ros2 run`` finds it).

    None when the package is not installed (no ament index, or not in it).
    """
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_prefix
        return Path(get_package_prefix('sphere_servo'))
    except (ImportError, PackageNotFoundError, OSError):  # OSError: no AMENT_PREFIX_PATH
        return None
