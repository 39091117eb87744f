"""
The shipped Fast DDS profile (config/fastdds.xml) and the environment that selects it (issue 17).

- The file: well-formed, a default participant profile whose transports are all defined,
  the built-in transports off, a shared-memory segment that holds several 1280×720 rgb8
  images, a port queue that does not run out before the segment does, UDPv4 present, and
  participants announced every second, well within their lease (discovery across hosts).
- ``sphere_servo.pipeline.middleware``: the variables, what a user set wins, refusals.
- Over ROS: an image publisher started with that environment really sends through a segment
  of the profile's size (without it, through Fast DDS's 512 KiB one), which is what shows
  that rmw_fastrtps read the file; the colcon install ships it where ``profile_path()``
  finds it.
- The launcher gives every node it starts (both modes) the installed profile, or the
  user's own, and the nodes send through its segment; the tests' ``ros_env`` names it.
"""
from __future__ import annotations

from pathlib import Path
import re
import subprocess
import sys
import time
import xml.etree.ElementTree as ET

from benchmarks.hop import hop_env
from conftest import _acquire_domain_id, installed_profile, REPO
import pytest

from sphere_servo.bringup.processes import interrupt, Launcher
from sphere_servo.pipeline.config import package_prefix, scenario
from sphere_servo.pipeline.middleware import (middleware_additions, middleware_env,
                                              profile_env, profile_path, PROFILE_VARIABLES,
                                              RMW)

NS = {'p': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
HD_BYTES = 1280 * 720 * 3
UDP_FRAGMENT = 65500  # UDPv4's message size: the participant fragments to the smallest
SOURCE_PROFILE = REPO / 'config' / 'fastdds.xml'


def _descriptors(root) -> dict[str, ET.Element]:
    return {d.findtext('p:transport_id', namespaces=NS): d
            for d in root.iterfind('p:transport_descriptors/p:transport_descriptor', NS)}


def _shm_segment(root) -> int:
    shm = [d for d in _descriptors(root).values() if d.findtext('p:type', namespaces=NS) == 'SHM']
    assert len(shm) == 1
    return int(shm[0].findtext('p:segment_size', namespaces=NS))


def test_profile_is_a_default_participant_with_shm_and_udp():
    root = ET.parse(SOURCE_PROFILE).getroot()
    assert root.tag == f'{{{NS["p"]}}}profiles'
    defaults = [p for p in root.iterfind('p:participant', NS)
                if p.get('is_default_profile') == 'true']
    assert len(defaults) == 1
    rtps = defaults[0].find('p:rtps', NS)
    assert rtps.findtext('p:useBuiltinTransports', namespaces=NS) == 'false'
    used = [t.text for t in rtps.iterfind('p:userTransports/p:transport_id', NS)]
    descriptors = _descriptors(root)
    assert set(used) == set(descriptors)
    assert sorted(descriptors[t].findtext('p:type', namespaces=NS) for t in used) \
        == ['SHM', 'UDPv4']


def test_shm_segment_holds_several_hd_images_and_the_port_queue_keeps_up():
    root = ET.parse(SOURCE_PROFILE).getroot()
    segment = _shm_segment(root)
    assert segment >= 8 * HD_BYTES, f'{segment} bytes hold {segment / HD_BYTES:.1f} HD images'
    shm = next(d for d in _descriptors(root).values()
               if d.findtext('p:type', namespaces=NS) == 'SHM')
    queue = int(shm.findtext('p:port_queue_capacity', namespaces=NS))
    # every 64 KB fragment in the segment can also be queued at a receiving port
    assert queue * UDP_FRAGMENT >= segment


def _seconds(duration) -> float:
    return float(duration.findtext('p:sec', '0', NS)) + \
        float(duration.findtext('p:nanosec', '0', NS)) * 1e-9


def test_participants_announce_every_second_well_within_their_lease():
    root = ET.parse(SOURCE_PROFILE).getroot()
    discovery = root.find("p:participant[@is_default_profile='true']/p:rtps/p:builtin/"
                          'p:discovery_config', NS)
    assert discovery is not None
    announcement = _seconds(discovery.find('p:leaseAnnouncement', NS))
    lease = discovery.find('p:leaseDuration', NS)
    lease = 20.0 if lease is None else _seconds(lease)  # Fast DDS's default
    assert 0 < announcement <= 1.0
    assert lease >= 10 * announcement  # a few lost announcements drop no participant
    assert lease <= 10.0  # a killed process's publishers are forgotten within 10 s


def test_profile_env_names_the_profile_under_both_variables(tmp_path):
    env = profile_env()
    assert env['RMW_IMPLEMENTATION'] == RMW == 'rmw_fastrtps_cpp'
    assert set(PROFILE_VARIABLES) == {'FASTRTPS_DEFAULT_PROFILES_FILE',
                                      'FASTDDS_DEFAULT_PROFILES_FILE'}
    for name in PROFILE_VARIABLES:
        assert Path(env[name]).is_absolute() and Path(env[name]).samefile(profile_path())
    if package_prefix() is None:  # not installed: the source tree's
        assert profile_path().samefile(SOURCE_PROFILE)
    with pytest.raises(FileNotFoundError, match='does not exist'):
        profile_env(tmp_path / 'missing.xml')


def test_middleware_env_adds_the_profile_and_keeps_what_the_user_chose(tmp_path):
    base = {'PATH': '/usr/bin', 'FASTDDS_DEFAULT_PROFILES_FILE': ''}
    env = middleware_env(base)
    assert env['PATH'] == '/usr/bin' and base == {'PATH': '/usr/bin',
                                                  'FASTDDS_DEFAULT_PROFILES_FILE': ''}
    assert all(Path(env[n]).samefile(profile_path()) for n in PROFILE_VARIABLES)
    assert env['RMW_IMPLEMENTATION'] == RMW

    mine = tmp_path / 'mine.xml'
    mine.write_text('<profiles/>')
    env = middleware_env({'FASTDDS_DEFAULT_PROFILES_FILE': str(mine)})
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == env['FASTDDS_DEFAULT_PROFILES_FILE'] \
        == str(mine.resolve())
    env = middleware_env({'FASTRTPS_DEFAULT_PROFILES_FILE': str(mine)}, SOURCE_PROFILE)
    assert Path(env['FASTRTPS_DEFAULT_PROFILES_FILE']).samefile(SOURCE_PROFILE)

    cyclone = {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}
    assert middleware_env(cyclone) == cyclone
    with pytest.raises(FileNotFoundError):
        middleware_env({'FASTRTPS_DEFAULT_PROFILES_FILE': str(tmp_path / 'typo.xml')})


def test_middleware_additions_are_what_a_node_lacks(tmp_path):
    base = {'PATH': '/usr/bin', 'ROS_DOMAIN_ID': '7'}
    added = middleware_additions(base)
    assert set(added) == {'RMW_IMPLEMENTATION', *PROFILE_VARIABLES}
    assert {**base, **added} == middleware_env(base)
    mine = (tmp_path / 'mine.xml').resolve()
    mine.write_text('<profiles/>')
    added = middleware_additions({'FASTDDS_DEFAULT_PROFILES_FILE': str(mine),
                                  'RMW_IMPLEMENTATION': RMW})
    assert added == {'FASTRTPS_DEFAULT_PROFILES_FILE': str(mine)}  # the user's, both names
    assert middleware_additions({'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}) == {}


SEGMENT = re.compile(r'/dev/shm/fastrtps_[0-9a-f]{16}$')


def _own_segments(pid: int) -> list[int]:
    """Return the sizes of the Fast DDS segments ``pid`` maps (ports and locks left out)."""
    sizes = []
    for line in Path(f'/proc/{pid}/maps').read_text().splitlines():
        fields = line.split()
        if len(fields) >= 6 and SEGMENT.search(fields[5]):
            start, end = (int(x, 16) for x in fields[0].split('-'))
            sizes.append(end - start)
    return sizes


def _segments_while_publishing(env: dict) -> set[int]:
    """
    Run a two-process image hop; return the sizes of the segments its publisher mapped.

    Fast DDS maps a segment only while it sends through it (after matching), so they are
    looked for throughout the publisher's run.
    """
    hop = [sys.executable, '-m', 'benchmarks.hop']
    sub = subprocess.Popen([*hop, 'sub', '--max-seconds', '60'], env=env,
                           stdout=subprocess.DEVNULL)
    pub = subprocess.Popen([*hop, 'pub', '--seconds', '2'], env=env, stdout=subprocess.PIPE,
                           text=True)
    seen: set[int] = set()
    try:
        while pub.poll() is None:
            try:
                seen.update(_own_segments(pub.pid))
            except OSError:  # it exited between poll() and the read
                break
            time.sleep(0.1)
        assert pub.returncode == 0, pub.stdout.read()
        return seen
    finally:
        for p in (pub, sub):  # as Ctrl-C: a killed participant leaves its segment behind
            interrupt(p)


@pytest.mark.ros
def test_a_publisher_started_with_the_environment_sends_through_the_profiles_segment():
    domain, lock = _acquire_domain_id()
    try:
        segment = _shm_segment(ET.parse(SOURCE_PROFILE).getroot())
        with_profile = _segments_while_publishing(hop_env(domain, True))
        assert with_profile and max(with_profile) >= segment, with_profile
        defaults = _segments_while_publishing(hop_env(domain, False))
        assert defaults and max(defaults) < 1 << 20, defaults  # Fast DDS's own 512 KiB
    finally:
        lock.close()


def test_the_install_space_ships_the_profile(install_space):
    code = 'from sphere_servo.pipeline.middleware import profile_path; print(profile_path())'
    out = subprocess.run([sys.executable, '-c', code], env=install_space, capture_output=True,
                         text=True, check=True).stdout.strip()
    installed = Path(install_space['SPHERE_SERVO_INSTALL']) / 'sphere_servo' / 'share' \
        / 'sphere_servo' / 'config' / 'fastdds.xml'
    assert Path(out) == installed
    assert installed.read_bytes() == SOURCE_PROFILE.read_bytes()


def _environ(pid: int) -> dict[str, str]:
    raw = Path(f'/proc/{pid}/environ').read_bytes().split(b'\0')
    return dict(kv.decode().split('=', 1) for kv in raw if b'=' in kv)


def test_ros_env_names_the_installed_profile(ros_env, install_space):
    installed = installed_profile(install_space)
    assert installed.is_file()
    assert all(ros_env[n] == str(installed.resolve()) for n in PROFILE_VARIABLES)
    assert ros_env['RMW_IMPLEMENTATION'] == RMW


@pytest.mark.parametrize('single_process', [False, True], ids=['processes', 'single'])
def test_the_launcher_gives_every_node_the_profile_unless_the_user_names_one(
        single_process, ros_env, test_node, tmp_path):
    """
    The launcher's nodes get the profile and send images through its segment.

    Started from an environment without the profile's variables, every node process has
    them (the shipped file) and arm_sim (or the single process) maps a segment of the
    profile's size; a user's own profile in the environment is what the nodes get.
    """
    bare = {k: v for k, v in ros_env.items() if k not in PROFILE_VARIABLES}
    mine = tmp_path / 'mine.xml'
    mine.write_bytes(SOURCE_PROFILE.read_bytes())
    segment = _shm_segment(ET.parse(SOURCE_PROFILE).getroot())
    sc = scenario('special_sphere')
    node, spin = test_node
    nodes = {'arm_sim', 'detector', 'features', 'servo'}

    def graph() -> set[str]:
        return {n for n, _ in node.get_node_names_and_namespaces()}
    # the profile the launcher's process finds (installed when it runs installed)
    for env, expected in ((bare, profile_path().resolve()), (dict(bare, **{
            PROFILE_VARIABLES[0]: str(mine)}), mine.resolve())):
        log = open(tmp_path / 'launch.log', 'w')
        run = Launcher(sc, out=log, env=env, single_process=single_process)
        try:
            run.start()
            pids = {n: c.popen.pid for n, c in run.children.items()}
            for name, pid in pids.items():
                got = _environ(pid)
                assert all(got[n] == str(expected) for n in PROFILE_VARIABLES), (
                    name, expected, [got.get(n) for n in PROFILE_VARIABLES])
                assert got['RMW_IMPLEMENTATION'] == RMW
            imager = pids['pipeline' if single_process else 'arm_sim']
            sizes: set[int] = set()
            deadline = time.monotonic() + 60
            while max(sizes, default=0) < segment and time.monotonic() < deadline:
                sizes.update(_own_segments(imager))
                time.sleep(0.2)
            assert max(sizes, default=0) >= segment, sizes
            # every node up (and so stopped as Ctrl-C stops it, not during its imports)
            assert spin(60.0, until=lambda: nodes <= graph()), graph()
        finally:
            codes = run.stop()
            log.close()
        assert all(c == 0 for c in codes.values()), codes
        # gone from the graph: the next run's nodes are not mistaken for these
        assert spin(30.0, until=lambda: not nodes & graph()), graph()
