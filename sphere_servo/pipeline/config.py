"""
Config files (no ROS).

Find a config by name, load it with its includes, read a node's parameters. Shared by the
launcher, the bag tools and the experiments.

A config is a ROS 2 parameters file (``<node>: ros__parameters: …``) plus a ``launch:``
section read by the launcher (``include``, ``nodes``, ``teach``, ``timeout``).
"""
from __future__ import annotations

import copy
from pathlib import Path

import yaml

SOURCE_CONFIG = Path(__file__).resolve().parents[2] / 'config'


class ConfigError(RuntimeError):
    """A config cannot be found, read or used."""


def merge(base: dict, over: dict) -> dict:
    """Deep merge: dicts merge recursively, anything else in ``over`` replaces."""
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) \
            else copy.deepcopy(v)
    return out


def find_config(name: str) -> Path:
    """Find a config by path or by name (``special_sphere`` or ``special_sphere.yaml``)."""
    p = Path(name)
    if p.is_file():
        return p
    fname = name if name.endswith('.yaml') else f'{name}.yaml'
    prefix = package_prefix()
    dirs = ([prefix / 'share' / 'sphere_servo' / 'config'] if prefix else []) + [SOURCE_CONFIG]
    for d in dirs:
        if (d / fname).is_file():
            return d / fname
    raise ConfigError(f'config {name!r} not found (looked in {", ".join(map(str, dirs))})')


def load_config(path: Path, _seen=()) -> dict:
    """Load the config ``path``, merged with its ``launch.include`` files."""
    path = Path(path).resolve()
    if path in _seen:
        raise ConfigError(f'config include cycle at {path}')
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f'cannot read config {path}: {exc}') from None
    if not isinstance(data, dict):
        raise ConfigError(f'config {path} is not a mapping')
    merged: dict = {}
    for inc in (data.get('launch') or {}).get('include', []):
        merged = merge(merged, load_config(path.parent / inc, (*_seen, path)))
    merged = merge(merged, data)
    merged.setdefault('launch', {}).pop('include', None)
    return merged


def node_params(config: dict, node: str) -> dict:
    """Return the ``ros__parameters`` of ``node`` in a merged config ({} if none)."""
    return ((config.get(node) or {}).get('ros__parameters') or {})


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
