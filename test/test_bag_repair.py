"""
``reindex``: bags whose writer was killed (SIGKILL) or lost power, made complete again.

Offline (no DDS). The recorder over DDS, killed and interrupted, is in ``test_bag_crash.py``.
"""
from __future__ import annotations

import os
from pathlib import Path
import random
import shutil
import subprocess
import sys

import bag_cases as bc
import pytest
from rosbags.highlevel import AnyReader
from sphere_servo.bag import bagio
from sphere_servo.bag.repair import main as reindex_main, reindex
from sphere_servo.bag.writer import BagWriter

REPO = Path(__file__).resolve().parents[1]
BIG = 50_000  # bytes of a "big" message: several per 768 KiB chunk

KILLED_WRITER = """
import os, signal, sys
from sphere_servo.bag.writer import BagWriter
import bag_cases as bc
storage, out, committed, extra, compression = sys.argv[1:6]
w = BagWriter(out, storage, compression, commit_period=1e9)  # commits only when told
w.create()
small = w.add_topic('/chatter', bc.STRING, [bc.foxy_qos()], typestore=bc.TS)
big = w.add_topic('rel/big', bc.STRING, typestore=bc.TS)
for i in range(int(committed) + int(extra)):
    w.write(small, 1000 + 2 * i, bc.string_cdr(str(i)))
    w.write(big, 1001 + 2 * i, bc.string_cdr(str(i) * (%d // len(str(i)))))
    if i == int(committed) - 1:
        w.commit()
        print('committed', flush=True)
os.kill(os.getpid(), signal.SIGKILL)
""" % BIG


def _kill_while_writing(tmp: Path, storage: str, committed: int, extra: int,
                        compression: str = 'none') -> Path:
    out = tmp / 'killed'
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(REPO / 'test')]))
    p = subprocess.run([sys.executable, '-c', KILLED_WRITER, storage, str(out), str(committed),
                        str(extra), compression], env=env, capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == -9 and 'committed' in p.stdout, p.stderr
    assert not (out / 'metadata.yaml').exists()
    return out


def _read(bag: Path) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    with bagio.bag(bag) as r:
        for c, _, raw in bagio.iter_raw(r):
            out.setdefault(c.topic, []).append(r.deserialize(raw, c.msgtype).data)
    return out


@pytest.mark.parametrize('storage, compression', [('mcap', 'none'), ('mcap', 'zstd'),
                                                  ('sqlite3', 'none'), ('sqlite3', 'zstd')])
def test_killed_writer_is_recovered(tmp_path, storage, compression, capsys):
    committed, extra = 30, 20  # 20 big ones fill a 768 KiB chunk
    bag = _kill_while_writing(tmp_path, storage, committed, extra, compression)
    with pytest.raises(bagio.BagError, match=r'not closed.*reindex'):
        bagio.open_bag(bag)
    assert reindex_main(['reindex', str(bag)]) == 0
    out = capsys.readouterr().out
    assert 'recovered' in out and 'metadata.yaml' in out
    got = _read(bag)
    small, big = got['/chatter'], got['rel/big']
    # everything committed is there, and nothing but what was written, in order
    assert committed <= len(small) <= committed + extra
    assert small == [str(i) for i in range(len(small))]
    assert big == [str(i) * (BIG // len(str(i))) for i in range(len(big))]
    if storage == 'sqlite3':  # the interrupted transaction is dropped as a whole
        assert len(small) == len(big) == committed
    else:  # full chunks were on disk before the commit window ended
        assert len(big) > committed
    with bagio.bag(bag) as r:
        s = bagio.summary(r)
        assert s['message_count'] == len(small) + len(big) and r.warnings == []
        assert s['compression'] == (('message', 'zstd') if storage == 'sqlite3' and
                                    compression == 'zstd' else (None, None))
        qos = {t['name']: t['qos'] for t in s['topics']}
        assert qos['/chatter'][0]['deadline'] == {'sec': 9223372036, 'nsec': 854775807}
    # the repaired bag is a standard one: rosbags reads it all as well
    with AnyReader([bag], default_typestore=bc.TS) as r:
        assert len(list(r.messages())) == len(small) + len(big)
    # a second reindex finds it intact
    done = reindex(bag)
    assert [f.state for f in done.files] == ['intact']
    assert done.meta.message_count == len(small) + len(big)


def _finished_mcap(tmp: Path, n: int = 60) -> tuple[Path, list]:
    """Write a closed MCAP bag of many small chunks; return its file and chunk indexes."""
    bag = tmp / 'full'
    with BagWriter(bag, 'mcap', chunk_size=4000) as w:
        a = w.add_topic('/a', bc.STRING, typestore=bc.TS)
        b = w.add_topic('/b', bc.STRING, typestore=bc.TS)
        for i in range(n):
            w.write(a, 10 * i, bc.string_cdr(f'a{i}'))
            w.write(b, 10 * i + 5, bc.string_cdr(f'b{i}' + 'x' * (300 * (i % 7))))
    f = next(bag.glob('*.mcap'))
    from rosbags.rosbag2.storage_mcap import McapReader
    r = McapReader(f)
    r.open()
    chunks = sorted((c.chunk_start_offset, c.chunk_length, sum(c.channel_count.values()),
                     c.message_index_length) for c in r.chunks)
    r.close()
    assert len(chunks) > 8
    return f, chunks


def _complete_before(chunks, cut: int) -> int:
    """Messages in the chunks whose chunk record ends at or before ``cut``."""
    return sum(n for off, length, n, _ in chunks if off + length <= cut)


def test_torn_mcap_keeps_every_complete_chunk(tmp_path):
    """Cut anywhere (SIGKILL), zero-filled (power loss), garbled: complete chunks are kept."""
    f, chunks = _finished_mcap(tmp_path)
    data = f.read_bytes()
    cuts = set()
    for off, length, _, mi in chunks:
        end = off + length
        cuts |= {off, off + 5, end - 1, end, end + 7, end + mi - 1, end + mi}
    rnd = random.Random(7)
    cuts |= {rnd.randrange(chunks[0][0], len(data)) for _ in range(25)}
    cases = [(f'cut{c}', data[:c]) for c in sorted(cuts) if c < len(data) - 200]
    off, length, _, _ = chunks[len(chunks) // 2]
    cases.append(('zeros', data[:off + length // 2] + bytes(1 << 16)))
    garbled = bytearray(data[:off + length])
    garbled[off + length - 40] ^= 0xFF  # a torn chunk: checksum mismatch
    cases.append(('garbled', bytes(garbled)))
    for name, content in cases:
        bag = tmp_path / name
        bag.mkdir()
        (bag / f.name).write_bytes(content)
        done = reindex(bag)
        cut = len(content) if name.startswith('cut') else off + length // 2 \
            if name == 'zeros' else off
        expect = _complete_before(chunks, cut)
        assert done.meta.message_count == expect, (name, done.files)
        got = _read(bag)
        n = len(got.get('/a', [])) + len(got.get('/b', []))
        assert n == expect, name
        assert got.get('/a', []) == [f'a{i}' for i in range(len(got.get('/a', [])))], name
        with AnyReader([bag], default_typestore=bc.TS) as r:
            assert len(list(r.messages())) == expect, name


def test_reindex_refuses_a_bag_being_written(tmp_path):
    for storage in ('mcap', 'sqlite3'):
        w = BagWriter(tmp_path / storage, storage)
        w.create()
        t = w.add_topic('/a', bc.STRING, typestore=bc.TS)
        w.write(t, 1, bc.string_cdr('x'))
        w.commit()
        with pytest.raises(bagio.BagError, match='still being written'):
            reindex(tmp_path / storage)
        w.close()
        assert reindex(tmp_path / storage).meta.message_count == 1


def test_reindex_split_bag_without_metadata(tmp_path):
    """As ros2 bag reindex: the files in split order, topics merged by name."""
    bag = tmp_path / 'wbag'
    stamps = bc.split_bag(bag, 'sqlite3')
    written = (bag / 'metadata.yaml').read_text()
    (bag / 'metadata.yaml').unlink()
    done = reindex(bag)
    assert [f.state for f in done.files] == ['intact'] * 3
    m = done.meta
    assert m.relative_file_paths == ('wbag_0.db3', 'wbag_1.db3', 'wbag_2.db3')
    assert [f.message_count for f in m.files] == [15, 15, 15]
    assert {t.name: t.message_count for t in m.topics} == {'AAA': 15, 'BBB': 15, 'CCC': 15}
    assert (m.start_ns, m.start_ns + m.duration_ns) == (stamps[0], stamps[-1])
    assert m.message_count == 45 and 'AAA' in written
    assert sum(len(v) for v in _read(bag).values()) == 45


def test_reindex_exit_codes(tmp_path, capsys):
    (tmp_path / 'empty').mkdir()
    assert reindex_main(['reindex', str(tmp_path / 'empty')]) == 1
    assert reindex_main(['reindex', str(tmp_path / 'nope')]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(e.startswith('reindex: error:') for e in err)
    with BagWriter(tmp_path / 'none', 'mcap') as w:  # a bag with no message
        w.add_topic('/a', bc.STRING, typestore=bc.TS)
    assert reindex_main(['reindex', str(tmp_path / 'none')]) == 1
    assert 'no message could be recovered' in capsys.readouterr().err
    shutil.rmtree(tmp_path / 'none')
