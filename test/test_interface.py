"""
The ROS interface a Jazzy user plugs into (issue 13), over DDS with the installed package.

- every node starts with ``--ros-args --params-file`` of each shipped params file (the
  installed copy) and exits 0 on SIGINT;
- ``/diagnostics`` carries one status per node (name, hardware_id, level, a state of its
  enum), on change and once a second, and each node's ``~/state`` carries the header of
  the image it answers;
- a late subscriber to ``features/<set>/desired`` (transient-local) gets the desired, with
  the taught image's header, and so does a servo started after the teach;
- the launch file is installed and names a scenario whose params files are installed.

The loop converging with TwistStamped commands and a wrong frame being refused are in
test_loop.py and test_arm_sim_node.py.
"""
from __future__ import annotations

import ast
from pathlib import Path
import subprocess
import sys

from conftest import executable_path, REPO
import numpy as np
import pytest

pytest.importorskip('rclpy')
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402, I100
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from sphere_servo.core.targets import special_sphere  # noqa: E402
from sphere_servo.experiments.scenarios import CMO_DESIRED  # noqa: E402
from sphere_servo.pipeline.detector import DetectStatus  # noqa: E402
from sphere_servo.pipeline.features import FeaturesState  # noqa: E402
from sphere_servo.pipeline.servo import ServoState  # noqa: E402
from sphere_servo.pipeline.vectors import FEATURE_NAMES  # noqa: E402
from sphere_servo.ros.vectors import DESIRED_QOS  # noqa: E402
from sphere_servo.sim.arm import Status  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from test_loop import _exact_measurement  # noqa: E402

NODES = ('arm_sim', 'detector', 'features', 'servo')
PARAMS = sorted(p.name for p in (REPO / 'config' / 'params').glob('*.yaml'))
STATES = {'arm_sim': Status, 'detector': DetectStatus, 'features': FeaturesState,
          'servo': ServoState}
HARDWARE = {'arm_sim': 'ur5', 'detector': 'camera', 'features': 'camera', 'servo': 'camera'}


def share(env: dict) -> Path:
    """Return ``share/sphere_servo`` of the install space (next to lib/sphere_servo)."""
    return Path(executable_path(env, 'arm_sim')).parents[2] / 'share' / 'sphere_servo'


def stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def _running(node, names) -> bool:
    return set(names) <= {n for n, _ in node.get_node_names_and_namespaces()}


@pytest.mark.parametrize('params', PARAMS)
def test_every_node_starts_with_a_shipped_params_file_and_exits_0(
        params, launch, test_node, ros_env):
    """Each node takes its own section of any shipped params file and ignores the others'."""
    node, spin = test_node
    path = share(ros_env) / 'config' / 'params' / params
    assert path.is_file(), path
    procs = {name: launch(name, '--ros-args', '--params-file', str(path)) for name in NODES}
    assert spin(60.0, until=lambda: _running(node, NODES)), {
        n: p.log()[-1500:] for n, p in procs.items()}
    for name, proc in procs.items():
        assert proc.popen.poll() is None, proc.log()
    for name, proc in procs.items():
        assert proc.stop() == 0, (name, proc.log()[-2000:])
        assert 'Traceback' not in proc.log() and 'refused to start' not in proc.log()


def test_diagnostics_carry_a_status_per_node(launch, test_node, ros_env):
    """
    Check ``/diagnostics`` and each node's ``~/state``, the four nodes in lockstep.

    One status per node (``<node>: state``, its hardware_id, a level, a state of the
    node's enum), again without a change (the 1 Hz publication: stamps a period apart);
    ``~/state`` messages carry the header of the image they answer (nothing is taught:
    the features node has no desired, the servo only its watchdog's states).
    """
    node, spin = test_node
    diag: dict[str, list] = {}

    def on_diag(msg):
        for st in msg.status:
            diag.setdefault(st.name, []).append((stamp(msg), st))
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 100)
    states: dict[str, list] = {name: [] for name in NODES}
    for name in NODES:
        node.create_subscription(DiagnosticArray, f'/{name}/state',
                                 lambda m, name=name: states[name].append(m), 100)
    files = [str(share(ros_env) / 'config' / 'params' / f)
             for f in ('arm_sim.yaml', 'special_sphere.yaml')]
    args = ['--ros-args'] + [x for f in files for x in ('--params-file', f)]
    procs = {name: launch(name, *args) for name in NODES}
    names = {f'{n}: state' for n in NODES}
    assert spin(60.0, until=lambda: names <= set(diag) and all(states.values())), (
        sorted(diag), {n: p.log()[-800:] for n, p in procs.items()})
    for name in NODES:
        _, st = diag[f'{name}: state'][-1]
        assert st.hardware_id == HARDWARE[name], (name, st)
        assert st.level in (DiagnosticStatus.OK, DiagnosticStatus.WARN,
                            DiagnosticStatus.ERROR), (name, st.level)
        STATES[name](st.message)  # a value of the node's state enum (ValueError if not)
    # arm_sim's state does not change (the disabled servo's zero twists): published anyway
    assert spin(20.0, until=lambda: len(diag['arm_sim: state']) >= 3)
    same = [(t, st) for t, st in diag['arm_sim: state']
            if (st.level, st.message) == (DiagnosticStatus.OK, 'ok')]
    assert len(same) >= 3 and np.min(np.diff([t for t, _ in same[-3:]])) > 0.5, same
    # ~/state: the header of the image answered, through detector, features and servo
    # (arm_sim's small messages can come seconds late under load: wait for those stamps)
    seen = {name: list(states[name]) for name in ('detector', 'features', 'servo')}
    want = {stamp(m) for msgs in seen.values() for m in msgs if stamp(m) > 0}
    assert spin(30.0, until=lambda: want <= {stamp(m) for m in states['arm_sim']}), sorted(
        want - {stamp(m) for m in states['arm_sim']})[:10]
    for name in ('detector', 'features'):
        assert {m.header.frame_id for m in seen[name]} == {'camera_optical_frame'}
    assert {m.status[0].message for m in seen['features']} == {FeaturesState.NO_DESIRED.value}
    # nothing taught: no features, so the servo's states are the watchdog's (no image)
    assert {(stamp(m), m.status[0].message) for m in seen['servo']} == {
        (0.0, ServoState.WAITING.value)}
    for proc in procs.values():
        assert proc.stop() == 0, proc.log()[-2000:]


def test_a_late_subscriber_gets_the_desired_with_the_taught_image_header(launch, test_node):
    """
    Subscribe to ``features/s_n/desired`` after the teach: the desired still comes.

    With the taught image's header (stamp and frame), the set's labels and s* of that image,
    from a transient-local, reliable publisher; a servo started after the teach holds it.
    """
    node, spin = test_node
    pub = node.create_publisher(JointState, 'detector/measurement', 10)
    feat = launch('features')
    assert spin(20.0, until=lambda: pub.get_subscription_count() > 0), feat.log()
    for t in (1.5, 1.6, 1.7):
        msg = _exact_measurement(CMO_DESIRED, special_sphere(), t)
        msg.header.frame_id = 'camera_optical_frame'
        pub.publish(msg)
        spin(0.2)
    cli = node.create_client(Trigger, '/features/teach')
    assert spin(10.0, until=cli.service_is_ready)
    fut = cli.call_async(Trigger.Request())
    assert spin(10.0, until=fut.done) and fut.result().success, fut.result()
    infos = node.get_publishers_info_by_topic('/features/s_n/desired')
    assert len(infos) == 1
    qos = infos[0].qos_profile
    assert qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert qos.reliability == ReliabilityPolicy.RELIABLE
    late = []
    node.create_subscription(JointState, 'features/s_n/desired', late.append, DESIRED_QOS)
    assert spin(10.0, until=lambda: bool(late)), feat.log()
    spin(0.5)
    assert len(late) == 1
    d = late[0]
    assert (d.header.stamp.sec, d.header.stamp.nanosec, d.header.frame_id) == (
        1, 700_000_000, 'camera_optical_frame')
    assert tuple(d.name) == FEATURE_NAMES['s_n']
    np.testing.assert_allclose(d.position[:3], CMO_DESIRED.translation / 0.05, atol=1e-9)
    np.testing.assert_allclose(d.position[3:], 0.0, atol=1e-12)
    states = []
    node.create_subscription(DiagnosticArray, '/servo/state',
                             lambda m: states.append(m.status[0]), 100)
    servo = launch('servo')

    def holds():
        return any({kv.key: kv.value for kv in st.values}.get('desired_stamp') ==
                   '1.700000000' for st in states)
    assert spin(30.0, until=holds), servo.log()
    assert 'desired features of the image stamped 1.700000000' in servo.log()
    assert servo.stop() == 0 and feat.stop() == 0


def test_the_launch_file_is_installed_with_the_files_it_names(ros_env):
    """
    Check the installed launch file without ``launch`` (not on PyPI here).

    It compiles, and the scenarios it reads (its default among them), with the launcher's
    reader in the install space, name installed params files and installed executables; its
    nodes are given the shipped Fast DDS profile.
    """
    root = share(ros_env)
    path = root / 'launch' / 'sphere_servo.launch.py'
    assert path.is_file()
    tree = ast.parse(path.read_text())
    compile(tree, str(path), 'exec')
    default = next(ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign)
                   and any(getattr(t, 'id', '') == 'DEFAULT_SCENARIO' for t in n.targets))
    code = ('import sys\nfrom sphere_servo.pipeline.config import scenario\n'
            'for name in sys.argv[1:]:\n    sc = scenario(name)\n'
            '    print(sc.path, *sc.nodes, *sc.params_files)\n')
    names = sorted(p.stem for p in (root / 'config' / 'scenarios').glob('*.yaml'))
    shipped = sorted(p.stem for p in (REPO / 'config' / 'scenarios').glob('*.yaml'))
    assert default in names and names == shipped and len(names) >= 7  # fisheye, catadioptric
    out = subprocess.run([sys.executable, '-c', code, *names], env=ros_env,
                         capture_output=True, text=True, timeout=60, cwd='/')
    assert out.returncode == 0, out.stderr
    lib = Path(executable_path(ros_env, 'arm_sim')).parent
    for line in out.stdout.splitlines():
        sc_path, *rest = line.split()
        assert Path(sc_path).parent == root / 'config' / 'scenarios'
        nodes = [r for r in rest if '/' not in r]
        files = [Path(r) for r in rest if '/' in r]
        assert nodes == list(NODES) and all((lib / n).is_file() for n in nodes)
        assert files and all(f.parent == root / 'config' / 'params' and f.is_file()
                             for f in files), line
    # its nodes get the shipped profile as the launcher's do (middleware_additions)
    nodes = [n for n in ast.walk(tree) if isinstance(n, ast.Call)
             and getattr(n.func, 'id', '') == 'Node']
    assert nodes and all(any(k.arg == 'additional_env' for k in n.keywords) for n in nodes)
    assert 'middleware_additions(os.environ)' in ast.unparse(tree)
