"""
Adversarial command lines for the bag tools, run as processes (``python -m ...``).

A tool that did nothing exits non-zero and says why in one ``error:`` line, and writes
nothing; the cases are the ones a user types by mistake:

- ``record`` with a duration that records nothing (0, negative, NaN), a queue depth < 1, an
  idle time that never elapses (NaN), a topic name no publisher can have;
- ``replay`` with a delay or a wait that is NaN or negative, a ``--remap`` of a topic the bag
  does not have (a typo: the topic would be played under its own name), two topics of
  different types remapped onto one name (one publisher: one type's bytes sent as the other);
- every tool on no argument, a path that does not exist, an empty directory, a directory with
  only ``metadata.yaml``, a file that is not a bag.

Every case here fails before ``rclpy.init``: no DDS.
"""
from __future__ import annotations

import os
from pathlib import Path
import shutil
import subprocess
import sys

from bag_cases import rosbag2_case
import pytest
from sphere_servo.bag.bagio import BagError, open_bag, select

pytest.importorskip('rclpy')

REPO = Path(__file__).resolve().parents[1]
MODULES = {'record': 'sphere_servo.bag.record', 'replay': 'sphere_servo.bag.replay',
           'reindex': 'sphere_servo.bag.repair', 'refeatures': 'sphere_servo.bag.refeatures'}


def _run(tool: str, *args) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED='1')
    return subprocess.run([sys.executable, '-m', MODULES[tool], *map(str, args)], env=env,
                          capture_output=True, text=True, timeout=60, cwd=REPO)


def _refused(res: subprocess.CompletedProcess, why: str) -> None:
    """Non-zero exit, no traceback, the last stderr line an error that says ``why``."""
    out = res.stdout + res.stderr
    assert res.returncode != 0, f'exit 0:\n{out}'
    assert 'Traceback' not in out, out
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert lines and 'error:' in lines[-1] and why in lines[-1], res.stderr


@pytest.fixture(scope='module')
def good_bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp('bags') / 'good'
    rosbag2_case(path, 'mcap')
    return path


@pytest.mark.parametrize('args, why', [
    (('--duration', '0'), '--duration'),
    (('--duration', '-1'), '--duration'),
    (('--duration', 'nan'), '--duration'),
    (('--qos-depth', '0'), '--qos-depth'),
    (('--qos-depth', '-5'), '--qos-depth'),
    (('--idle-quiet', 'nan'), '--idle-quiet'),
    (('--idle-quiet', '-1'), '--idle-quiet'),
    (('--topics', '/camera/image_raw', 'bad~name'), 'bad~name'),
    (('--topics', '/a b'), 'not a valid topic name'),
])
def test_record_refuses_options_that_record_nothing(tmp_path, args, why):
    out = tmp_path / 'rec'
    _refused(_run('record', '-o', out, *args), why)
    assert not out.exists()


@pytest.mark.parametrize('args, why', [
    (('--delay', 'nan'), '--delay'),
    (('--delay', '-1'), '--delay'),
    (('--wait-for-subscribers', 'nan'), '--wait-for-subscribers'),
    (('--wait-for-subscribers', '-2'), '--wait-for-subscribers'),
    (('--remap', '/no/such:=/x'), '/no/such'),
    (('--remap', 'chatte:=/x'), '/chatte'),
    (('--remap', '/svc/_service_event:=/chatter'), 'would both be published on /chatter'),
    (('--remap', '/svc/_service_event:=/x', 'chatter:=/x'), 'would both be published on /x'),
])
def test_replay_refuses_options_that_play_wrongly(good_bag, args, why):
    _refused(_run('replay', good_bag, *args), why)


def test_remaps_of_one_type_onto_one_name_are_kept(good_bag):
    """``AAA`` and ``/chatter`` (both String) may go out on one topic, as rosbag2 allows."""
    from sphere_servo.bag.replay import check_remaps
    reader = open_bag(good_bag)
    try:
        sel = select(reader, None, None)
        check_remaps(reader, sel.connections, {'/AAA': '/chatter'})
        check_remaps(reader, sel.connections, {'/chatter': '/x', '/AAA': '/x'})
        with pytest.raises(BagError, match='would both'):
            check_remaps(reader, sel.connections, {'/chatter': '/arrays'})
    finally:
        reader.close()


def _not_bags(root: Path) -> dict[str, Path]:
    (root / 'empty').mkdir()
    (root / 'only_metadata').mkdir()
    src = root / 'src'
    rosbag2_case(src, 'sqlite3')
    shutil.copy(src / 'metadata.yaml', root / 'only_metadata' / 'metadata.yaml')
    (root / 'notes.txt').write_text('not a bag\n')
    return {'missing': root / 'no_such_bag', 'empty dir': root / 'empty',
            'only metadata.yaml': root / 'only_metadata', 'a text file': root / 'notes.txt'}


@pytest.mark.parametrize('tool', ['replay', 'reindex', 'refeatures'])
def test_tools_refuse_what_is_not_a_bag(tmp_path, tool):
    res = _run(tool)
    assert res.returncode == 2 and 'required' in res.stderr, res.stderr
    cases = _not_bags(tmp_path)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob('*'))
    for what, path in cases.items():
        res = _run(tool, path)
        assert res.returncode == 1, f'{what}: {res.returncode}\n{res.stdout}{res.stderr}'
        _refused(res, 'error:')
    # nothing written next to what was refused (reindex of a text file writes no metadata)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob('*')) == before
