"""
reindex: make a rosbag2 whose recorder was killed (or lost power) a complete bag again.

    ros2 run sphere_servo reindex BAG

As ``ros2 bag reindex`` (``rosbag2_cpp/reindexer.cpp``), it takes the storage files of the
bag directory in split order (``NAME_<n>``), reads what each holds, merges the topics by name
and writes ``metadata.yaml`` (Jazzy's version 9), keeping the ``custom_data`` of an old
readable one. Unlike it, it first repairs files that were never closed:

- MCAP (no footer): every complete, checksum-valid record is kept; the file is cut after the
  last one (the chunk the kill interrupted, at most one commit window of messages) and
  finished with the message indexes that were cut, the ``rosbag2`` metadata record, the
  summary and the footer (:func:`sphere_servo.bag.mcap.recover`).
- sqlite3 (a WAL or rollback journal left behind): SQLite's own recovery keeps every
  committed transaction and drops the one the kill interrupted (at most one commit window);
  the file is then returned to rollback-journal mode, self-contained.

A bag still being written (its storage file locked by a running recorder) is refused. Exit
code 0 once ``metadata.yaml`` is written and lists at least one message, 1 otherwise.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, field
import fcntl
from pathlib import Path
import sys

from sphere_servo.bag import mcap
from sphere_servo.bag.metadata import (BagError, BagMeta, FileMeta, metadata_text, normal_qos,
                                       read_metadata, TopicMeta, write_metadata)
from sphere_servo.bag.reader import (check_sqlite, message_compression, one_line,
                                     storage_files, unclosed)
from sphere_servo.bag.storage import storage_reader


@dataclass
class FileReport:
    """What reindex did with one storage file."""

    name: str
    state: str          # 'intact' or 'recovered'
    messages: int
    dropped_bytes: int = 0
    detail: str = ''


def _unlocked(path: Path) -> None:
    """Refuse a file a running recorder holds (see :mod:`sphere_servo.bag.writer`)."""
    with open(path, 'rb') as fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise BagError(f'{path.name} is still being written (a recorder holds it); stop '
                           'the recorder first') from None
        fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def _file_meta(path: Path) -> tuple[list[TopicMeta], FileMeta, str]:
    """Read a closed storage file: its topics (with counts), span, and compression mode."""
    st = storage_reader(path)
    try:
        st.open()
    except Exception as err:  # rosbags raises several types: all "unreadable"
        raise BagError(f'{path.name}: {one_line(err)}') from None
    try:
        hashes = {}
        if path.suffix == '.mcap':  # rosbags does not read the channels' topic_type_hash
            for ch in st.channels.values():
                meta = mcap.map_entries(ch.metadata) if ch.metadata else {}
                hashes[ch.id] = meta.get('topic_type_hash', '')
        topics = [TopicMeta(c.topic, c.msgtype, c.ext.serialization_format,
                            tuple(normal_qos(q) for q in c.ext.offered_qos_profiles),
                            c.digest or hashes.get(c.id, ''), c.msgcount)
                  for c in st.connections]
        md = st.metadata
        n = md.message_count
        compressed = message_compression(st) if path.suffix == '.db3' else ''
        span = FileMeta(path.name, md.start_time if n else 0,
                        max(0, md.end_time - 1 - md.start_time) if n else 0, n)
        return topics, span, compressed
    finally:
        st.close()


def _single_meta(topics, span, storage, mode) -> BagMeta:
    return BagMeta(storage=storage, relative_file_paths=(span.path,), start_ns=span.start_ns,
                   duration_ns=span.duration_ns, message_count=span.message_count,
                   topics=tuple(topics), compression_format='zstd' if mode else '',
                   compression_mode=mode, files=(span,))


@dataclass
class Reindexed:
    """The result of :func:`reindex`: the bag, its new metadata, and what each file needed."""

    bag_dir: Path
    meta: BagMeta
    files: list
    warnings: list = field(default_factory=list)


def reindex(path: str | Path) -> Reindexed:
    """Repair the storage files of a bag directory and write its ``metadata.yaml``."""
    path = Path(path)
    if not path.exists():
        raise BagError(f'no such bag: {str(path)!r} does not exist')
    if path.is_file() and path.suffix not in ('.mcap', '.db3') and path.name != 'metadata.yaml':
        # its directory may hold a bag it was not asked to rewrite
        raise BagError(f'{str(path)!r} is not a rosbag2 bag: give a bag directory, an .mcap '
                       'or a .db3 file')
    bag_dir = path if path.is_dir() else path.parent
    files = storage_files(bag_dir)
    if not files:
        raise BagError(f'{str(bag_dir)!r} holds no .mcap or .db3 file to reindex')
    storage = {'.mcap': 'mcap', '.db3': 'sqlite3'}[files[0].suffix]
    if any(f.suffix != files[0].suffix for f in files):
        raise BagError(f'{str(bag_dir)!r} holds both .mcap and .db3 files')
    reports, merged, spans, modes, warnings = [], {}, [], set(), []
    for f in files:
        _unlocked(f)
        why = unclosed(f)
        size = f.stat().st_size
        if why is None:
            state, detail = 'intact', ''
        elif storage == 'mcap':
            def record_text(sc, f=f):
                topics, span = _scan_topics(sc, f.name)
                return metadata_text(_single_meta(topics, span, 'mcap', ''), wrapped=False)
            try:
                sc = mcap.recover(f, record_text)
            except (OSError, ValueError) as err:
                raise BagError(f'{f.name}: cannot recover: {one_line(err)}') from None
            state, detail = 'recovered', sc.stopped
            size -= sc.good_end
        else:
            check_sqlite(f, recover=True)
            state, detail = 'recovered', 'committed transactions kept, the interrupted one dropped'
            size = 0
        topics, span, mode = _file_meta(f)
        modes.add(mode)
        spans.append(span)
        for t in topics:
            old = merged.get(t.name)
            if old is not None and t.msgtype != old.msgtype:
                # the reader reads a topic as one type (its first file's): so does the count
                warnings.append(f'topic {t.name} has type {t.msgtype} in {f.name} and '
                                f'{old.msgtype} before: its {t.message_count} {t.msgtype} '
                                'messages are not counted and will not be read')
                continue
            merged[t.name] = t if old is None else TopicMeta(
                t.name, old.msgtype, old.serialization_format, old.qos or t.qos,
                old.type_hash or t.type_hash, old.message_count + t.message_count)
        reports.append(FileReport(f.name, state, span.message_count,
                                  size if state == 'recovered' else 0, detail))
    if len(modes) > 1:
        raise BagError('some files hold zstd-compressed messages and some not')
    mode = modes.pop()
    custom = {}
    if (bag_dir / 'metadata.yaml').is_file():
        try:
            custom = read_metadata(bag_dir).custom_data
        except BagError:
            pass  # the metadata being replaced is unreadable: nothing to keep
    n = sum(t.message_count for t in merged.values())  # what a reader will read
    with_msgs = [s for s in spans if s.message_count]
    start = min((s.start_ns for s in with_msgs), default=0)
    end = max((s.start_ns + s.duration_ns for s in with_msgs), default=0)
    meta = BagMeta(storage=storage, relative_file_paths=tuple(s.path for s in spans),
                   start_ns=start, duration_ns=end - start, message_count=n,
                   topics=tuple(merged.values()), compression_format='zstd' if mode else '',
                   compression_mode=mode, files=tuple(spans), custom_data=custom)
    write_metadata(bag_dir, meta)
    return Reindexed(bag_dir, meta, reports, warnings)


def _scan_topics(sc: mcap.Scan, name: str) -> tuple[list[TopicMeta], FileMeta]:
    """Topics and span of a scanned MCAP file, for the metadata record it is finished with."""
    from sphere_servo.bag.metadata import parse_qos
    topics = []
    for cid in sorted(sc.channels):
        ch = sc.channels[cid]
        schema = sc.schemas.get(ch.schema_id)
        try:
            qos = parse_qos(ch.metadata.get('offered_qos_profiles', ''), ch.topic)
        except BagError:
            qos = ()
        topics.append(TopicMeta(ch.topic, schema.name if schema else '', ch.message_encoding,
                                qos, ch.metadata.get('topic_type_hash', ''),
                                sc.counts.get(cid, 0)))
    n = sc.message_count
    return topics, FileMeta(name, sc.start if n else 0, sc.end - sc.start if n else 0, n)


def main(args=None) -> int:
    argv = sys.argv[1:] if args is None else list(args)[1:]
    p = argparse.ArgumentParser(prog='reindex', description=__doc__.strip().split('\n\n')[0])
    p.add_argument('bag', help='bag directory (or one of its storage files)')
    opts = p.parse_args(argv)
    try:
        done = reindex(opts.bag)
    except BagError as err:
        print(f'reindex: error: {err}', file=sys.stderr)
        return 1
    for r in done.files:
        line = f'reindex: {r.name}: {r.state}, {r.messages} messages'
        if r.state == 'recovered':
            line += f' ({r.detail}; {r.dropped_bytes} bytes cut)' if r.dropped_bytes else \
                f' ({r.detail})'
        print(line)
    for w in done.warnings:
        print(f'reindex: warning: {w}', file=sys.stderr)
    print(f'reindex: wrote {done.bag_dir / "metadata.yaml"}: {done.meta.message_count} '
          f'messages on {len(done.meta.topics)} topics')
    if not done.meta.message_count:
        print('reindex: error: no message could be recovered', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv))
