"""
The middleware settings of the pipeline (no ROS): the shipped Fast DDS profile and its environment.

``config/fastdds.xml`` gives rmw_fastrtps_cpp a shared-memory transport whose segment holds
several 1280×720 rgb8 images, plus UDPv4 for other hosts (the file says why, setting by
setting). Fast DDS reads it from the environment when a participant is created, so it has to
be in the environment of every node process before ``rclpy.init``:

- ``FASTRTPS_DEFAULT_PROFILES_FILE``, the name Fast DDS 2.x (ROS 2 Jazzy) reads, and
  ``FASTDDS_DEFAULT_PROFILES_FILE``, its name from Fast DDS 3 on: both point at the profile;
- ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp``: the profile means nothing to another rmw.

:func:`profile_path` finds the profile as :func:`~sphere_servo.pipeline.config.find_config`
finds a config: in the install space (``share/sphere_servo/config``) if the package is
installed, else in the source tree. :func:`middleware_env` adds the variables to an
environment, keeping what the user chose there (:func:`middleware_additions`: only what it
adds). :func:`environment_problem` says what in an
environment no node can work with (the launcher and every node refuse to start on it).
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
import re

from sphere_servo.pipeline.config import package_prefix, SOURCE_CONFIG

PROFILE_NAME = 'fastdds.xml'
RMW = 'rmw_fastrtps_cpp'
# Fast DDS 2.x (Jazzy) reads the first, Fast DDS 3.x the second
PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')
MAX_DOMAIN_ID = 232  # Fast DDS's default ports: 7400 + 250 · id + offsets ≤ 65535


def environment_problem(env: Mapping[str, str]) -> str | None:
    """
    Return what in ``env`` no node can work with (one line), or None.

    ``ROS_DOMAIN_ID``: empty/unset (rcl's default 0) or a plain decimal integer in
    0…MAX_DOMAIN_ID (rcl reads ``010`` as octal 8, Fast DDS has no ports above 232). With
    Fast DDS, every profiles file named must be well-formed XML whose root is ``<profiles>``
    or ``<dds>`` (Fast DDS logs a malformed one and runs on its defaults).
    """
    domain = env.get('ROS_DOMAIN_ID', '')
    if domain != '' and not (re.fullmatch(r'0|[1-9][0-9]{0,2}', domain)
                             and int(domain) <= MAX_DOMAIN_ID):
        return (f'ROS_DOMAIN_ID={domain!r} is not a domain: use a decimal integer '
                f'0…{MAX_DOMAIN_ID} without a leading zero (or unset it for 0)')
    if (env.get('RMW_IMPLEMENTATION') or RMW) != RMW:
        return None
    from xml.etree import ElementTree
    for name in PROFILE_VARIABLES:
        path = env.get(name)
        if not path:
            continue
        try:
            root = ElementTree.parse(path).getroot()
        except (OSError, ElementTree.ParseError) as exc:
            return (f'{name}={path}: not a readable XML file ({exc}); Fast DDS would run on '
                    'its defaults')
        if root.tag.rsplit('}', 1)[-1] not in ('profiles', 'dds'):
            return (f'{name}={path}: not a Fast DDS profile (its root is <{root.tag}>, not '
                    '<profiles> or <dds>)')
    return None


def profile_path() -> Path:
    """
    Return the shipped Fast DDS profile: the installed one if the package is installed.

    Raises FileNotFoundError, naming the places looked in, if neither exists.
    """
    prefix = package_prefix()
    dirs = ([prefix / 'share' / 'sphere_servo' / 'config'] if prefix else []) + [SOURCE_CONFIG]
    for d in dirs:
        if (d / PROFILE_NAME).is_file():
            return d / PROFILE_NAME
    raise FileNotFoundError(
        f'Fast DDS profile {PROFILE_NAME} not found (looked in {", ".join(map(str, dirs))})')


def profile_env(profile: Path | None = None) -> dict[str, str]:
    """
    Return the variables that make an rclpy process use ``profile`` (default: the shipped one).

    The path is made absolute (processes may start elsewhere); a missing file is a
    FileNotFoundError here rather than a silent fall-back to Fast DDS's defaults later.
    """
    path = Path(profile if profile is not None else profile_path()).resolve()
    if not path.is_file():
        raise FileNotFoundError(f'Fast DDS profile {path} does not exist')
    return {'RMW_IMPLEMENTATION': RMW, **{name: str(path) for name in PROFILE_VARIABLES}}


def middleware_env(base: Mapping[str, str], profile: Path | None = None) -> dict[str, str]:
    """
    Return a copy of ``base`` with the profile's variables added.

    What the user set in ``base`` wins: another ``RMW_IMPLEMENTATION`` leaves ``base``
    unchanged (the profile is Fast DDS's), and a profiles file already named in either
    variable is kept, and given under both names so that both Fast DDS generations read it.
    An explicit ``profile`` argument replaces the user's file.
    """
    env = dict(base)
    if env.get('RMW_IMPLEMENTATION', RMW) != RMW:
        return env
    user = next((env[name] for name in PROFILE_VARIABLES if env.get(name)), None)
    chosen = profile if profile is not None else (Path(user) if user else None)
    env.update(profile_env(chosen))
    return env


def middleware_additions(base: Mapping[str, str]) -> dict[str, str]:
    """
    Return only what :func:`middleware_env` adds to ``base`` or changes in it.

    For a launcher that passes a node the variables to add to its own environment (``ros2
    launch``: ``Node(additional_env=...)``); empty when the user chose another rmw.
    """
    return {k: v for k, v in middleware_env(base).items() if base.get(k) != v}
