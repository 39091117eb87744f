"""
Shared pytest fixtures for the tests that run ROS 2.

An isolated ROS 2 domain per test, a colcon-built install space, and a launcher for the
installed executables (launch_testing style, without launch_testing, which is not on PyPI).

- ``ros_env``       environment for processes of one test: its own ``ROS_DOMAIN_ID``,
                    localhost discovery, the install space sourced, and the installed Fast
                    DDS profile (``middleware_env``: what the launcher gives its nodes).
- ``install_space`` ``colcon build`` of this package into a temporary install base, once per
                    session; executables are resolved as ``ros2 run`` does:
                    ``get_package_prefix('sphere_servo')/lib/sphere_servo/<name>``.
- ``launch``        start an installed executable as a process; all are stopped (SIGINT,
                    then SIGKILL) at the end of the test; logs go to the test's tmp dir.
"""
from __future__ import annotations

import fcntl
import itertools
import os
from pathlib import Path
import re
import subprocess
import sys
import tempfile
import time

import pytest

from sphere_servo.bringup.processes import interrupt
from sphere_servo.pipeline.middleware import middleware_env, PROFILE_NAME

REPO = Path(__file__).resolve().parents[1]
_domain_counter = itertools.count()

# the participants of this process (test nodes, supervisors) use the profile too; Fast DDS
# reads it when the process's first participant is made, so it is set before any test runs
os.environ.update(middleware_env(os.environ))


ROS_FIXTURES = {'install_space', 'ros_env', 'launch', 'test_node'}


def pytest_collection_modifyitems(config, items):
    """
    Mark every test that needs the colcon install or DDS as ``ros``; refuse unstable ids.

    ``pytest -m "not ros"`` then leaves them out: a fast inner loop. An id holding an
    object's address (``<object object at 0x…>``) differs between pytest-xdist's workers,
    which then stop the run at collection: it is refused here, in any run, by name.
    """
    unstable = [item.nodeid for item in items if re.search(r' at 0x[0-9a-f]+', item.nodeid)]
    if unstable:
        raise pytest.UsageError('test ids with an address (give the parametrization ids): '
                                + ', '.join(unstable[:5]))
    for item in items:
        if ROS_FIXTURES & set(getattr(item, 'fixturenames', ())):
            item.add_marker(pytest.mark.ros)


LOCK_DIR = Path(tempfile.gettempdir()) / 'sphere_servo_ros_domains'


def _acquire_domain_id():
    """
    Take a ROS_DOMAIN_ID that no other test on this machine holds.

    1..100, within the default port mapping on Linux. An exclusive lock file per domain,
    held until released, so concurrent pytest runs never hear each other. Returns
    (domain_id, lock file object).
    """
    LOCK_DIR.mkdir(exist_ok=True)
    start = (os.getpid() * 7 + next(_domain_counter)) % 100
    for k in range(100):
        domain = 1 + (start + k) % 100
        fh = open(LOCK_DIR / f'{domain}.lock', 'w')
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return domain, fh
        except OSError:
            fh.close()
    raise RuntimeError('all ROS domain ids 1..100 are taken by other tests')


@pytest.fixture(scope='session')
def install_space(tmp_path_factory) -> dict:
    """
    Build the package with colcon into a temporary install base.

    Returns the environment of ``source install/setup.bash``.
    """
    base = tmp_path_factory.mktemp('colcon')
    venv_bin = Path(sys.executable).parent
    colcon = venv_bin / 'colcon'
    cmd = [str(colcon), '--log-base', str(base / 'log'), 'build', '--base-paths', str(REPO),
           '--build-base', str(base / 'build'), '--install-base', str(base / 'install')]
    env = dict(os.environ, PATH=f'{venv_bin}:{os.environ.get("PATH", "")}')
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    if out.returncode != 0:
        pytest.fail(f'colcon build failed:\n{out.stdout}\n{out.stderr}')
    dump = subprocess.run(
        ['bash', '-c', f'source "{base}/install/setup.bash" && env -0'], env=env,
        capture_output=True, timeout=60, check=True).stdout.decode()
    sourced = dict(kv.split('=', 1) for kv in dump.split('\0') if '=' in kv)
    # the repository checkout must not shadow the installed package
    sourced['PYTHONPATH'] = ':'.join(
        p for p in sourced.get('PYTHONPATH', '').split(':') if p and Path(p) != REPO)
    sourced['SPHERE_SERVO_INSTALL'] = str(base / 'install')
    return sourced


def installed_profile(install_space: dict) -> Path:
    """Return the Fast DDS profile the install space ships."""
    return Path(install_space['SPHERE_SERVO_INSTALL']) / 'sphere_servo' / 'share' \
        / 'sphere_servo' / 'config' / PROFILE_NAME


def executable_path(env: dict, name: str) -> str:
    """Resolve ``name`` exactly as ``ros2 run sphere_servo <name>`` does."""
    code = ('from ament_index_python.packages import get_package_prefix as g;'
            'print(g("sphere_servo"))')
    prefix = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                            text=True, check=True).stdout.strip()
    path = Path(prefix) / 'lib' / 'sphere_servo' / name
    if not path.is_file() or not os.access(path, os.X_OK):
        raise FileNotFoundError(f'no executable {name!r} in {path.parent}')
    return str(path)


@pytest.fixture
def ros_env(install_space):
    """Environment for this test's processes: a domain no other test holds, localhost discovery."""
    domain, lock = _acquire_domain_id()
    env = dict(install_space)
    env['ROS_DOMAIN_ID'] = str(domain)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['PYTHONUNBUFFERED'] = '1'
    env.pop('ROS_LOCALHOST_ONLY', None)
    env.update(middleware_env(env, installed_profile(install_space)))
    yield env
    lock.close()


class Proc:
    """A started executable; ``log()`` returns what it printed so far."""

    def __init__(self, name: str, popen: subprocess.Popen, log_path: Path):
        self.name, self.popen, self.log_path = name, popen, log_path

    def log(self) -> str:
        return self.log_path.read_text(errors='replace')

    def stop(self, timeout: float = 10.0) -> int:
        """SIGINT (as Ctrl-C), wait, then SIGKILL; returns the exit code."""
        return interrupt(self.popen, timeout)


@pytest.fixture
def launch(ros_env, tmp_path):
    """
    Start installed executables, each as a process stopped at the end of the test.

    ``launch(name, *args, env_extra=None)`` starts one and returns its :class:`Proc`.
    """
    procs: list[Proc] = []

    def _launch(name: str, *args: str, env_extra: dict | None = None) -> Proc:
        env = dict(ros_env, **(env_extra or {}))
        log_path = tmp_path / f'{name}-{len(procs)}.log'
        fh = open(log_path, 'w')
        popen = subprocess.Popen([executable_path(env, name), *args], env=env,
                                 stdout=fh, stderr=subprocess.STDOUT)
        proc = Proc(name, popen, log_path)
        procs.append(proc)
        return proc

    yield _launch
    for p in procs:
        p.stop()


def wait_for(predicate, timeout: float, interval: float = 0.05, what: str = 'condition'):
    """Poll ``predicate`` until it is truthy; fail the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    pytest.fail(f'timed out after {timeout} s waiting for {what}')


@pytest.fixture
def test_node(ros_env):
    """
    An rclpy node in this test process, on the test's domain, with its own context and executor.

    ``node, spin = test_node``; ``spin(seconds)`` processes callbacks.
    """
    rclpy = pytest.importorskip('rclpy')
    from rclpy.executors import SingleThreadedExecutor

    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = rclpy.create_node(f'test_node_{os.getpid()}', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)

    def spin(seconds: float = 0.1, until=None):
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
            if until is not None and until():
                return True
        return until() if until is not None else None

    yield node, spin
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=ctx)
