"""
Benchmark of the bare image hop, Fast DDS defaults against the shipped profile (issue 17).

Each case in fresh processes (``benchmarks.hop``), 30 Hz, reliable, keep last 10, discovery
on localhost; latency = arrival in the subscriber's callback − the stamp taken right before
``publish`` (both on the system clock). :func:`hop` runs one case, :func:`busy_load` keeps
the CPU busy: the loop benchmark (``bench_loop``) measures with them, side by side with the
pipeline, the 640×480 hop with Fast DDS's defaults and with ``config/fastdds.xml``, in two
processes and in one, idle and under a load of two busy processes. This area adds 1280×720
rgb8 images, two processes, defaults and profile (median, p99, received / sent).

``python -m benchmarks.bench_transport [--quick]`` prints the rows as a table.
"""
from __future__ import annotations

from contextlib import contextmanager
import json
import os
import signal
import subprocess
import sys

from benchmarks.hop import hop_env
import numpy as np
from sphere_servo.bringup.processes import die_with

RATE = 30.0
VGA, HD = (640, 480), (1280, 720)


def own_session(nice: int = 0) -> dict:
    """
    Return the ``subprocess`` keywords that start a process as the launcher starts a node.

    A session of its own (with the kernel's autogroup scheduling, CPU time is shared between
    sessions first), its niceness (this process's, plus ``nice``) given to that session, and
    ended if this process dies: :func:`~sphere_servo.bringup.processes.die_with`.
    """
    return {'start_new_session': True, 'preexec_fn': die_with(os.getpid(), nice)}


@contextmanager
def busy_load(n: int = 2, own_sessions: bool = False):
    """
    Keep ``n`` processes spinning on the CPU (at normal priority) for the block's duration.

    ``own_sessions``: each in a session of its own, as an unrelated program runs, at this
    process's niceness, and ended if this process dies (as the launcher's nodes:
    :func:`~sphere_servo.bringup.processes.die_with`). With the kernel's autogroup scheduling
    (on here) CPU time is shared between sessions first, so loops in the caller's session
    load mostly the caller (and the launcher's nodes, each in a session of its own, little).
    """
    procs = [subprocess.Popen([sys.executable, '-c', 'while True: pass'],
                              **(own_session() if own_sessions else {}))
             for _ in range(n)]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
            p.wait()


def _last_json(text: str, who: str) -> dict:
    for line in reversed(text.strip().splitlines()):
        try:
            return json.loads(line)
        except ValueError:
            continue
    raise RuntimeError(f'{who} printed no result: {text[-500:]!r}')


def hop(processes: int, profile: bool, size=VGA, seconds: float = 10.0,
        domain: int | None = None) -> dict:
    """
    Run one bare hop case; return ``{'sent', 'received', 'latency_ms' (array)}``.

    ``processes`` is 2 (publisher → subscriber process) or 1 (both nodes, one executor).
    """
    domain = domain if domain is not None else 1 + (os.getpid() * 13 + 9) % 100
    env = hop_env(domain, profile)
    args = ['--rate', str(RATE), '--seconds', str(seconds), '--width', str(size[0]),
            '--height', str(size[1])]
    cmd = [sys.executable, '-m', 'benchmarks.hop']
    if processes == 1:
        out = subprocess.run([*cmd, 'both', *args], env=env, capture_output=True, text=True,
                             timeout=seconds + 120, **own_session())
        res = _last_json(out.stdout, 'hop both')
        sent = res
    elif processes == 2:
        sub = subprocess.Popen([*cmd, 'sub', *args], env=env, stdout=subprocess.PIPE, text=True,
                               **own_session())
        try:
            pub = subprocess.run([*cmd, 'pub', *args], env=env, capture_output=True, text=True,
                                 timeout=seconds + 120, **own_session())
            sent = _last_json(pub.stdout, 'hop pub')
        finally:
            sub.send_signal(signal.SIGINT)
            try:
                sub_out = sub.communicate(timeout=30)[0]
            except subprocess.TimeoutExpired:
                sub.kill()
                sub_out = sub.communicate()[0]
        res = _last_json(sub_out, 'hop sub')
    else:
        raise ValueError(f'processes must be 1 or 2, not {processes}')
    if 'error' in sent:
        raise RuntimeError(f'hop publisher: {sent["error"]}')
    lat = np.asarray(res['latency_ms'], dtype=float)
    if lat.size == 0:
        raise RuntimeError(f'no image arrived ({processes} process(es), profile={profile})')
    return {'sent': int(sent['sent']), 'received': int(res['received']), 'latency_ms': lat}


STATS = (('median', 50), ('p95', 95), ('p99', 99), ('max', 100))


def _stat(r: dict, q: float) -> float:
    return float(np.percentile(r['latency_ms'], q))


def _rows(label: str, r: dict, base: dict | None, base_name: str | None, target: str,
          stats=STATS) -> list[dict]:
    rows = []
    for k, (stat, q) in enumerate(stats):
        value = _stat(r, q)
        b = _stat(base, q) if base is not None else None
        rows.append({'name': f'{label}, {stat}', 'value': value, 'unit': 'ms', 'baseline': b,
                     'baseline_name': f'{base_name} {stat}' if base_name else None,
                     'ratio': value / b if b else None,
                     'target': target if k == 0 else 'information'})
    rows.append({'name': f'{label}, frames received', 'value': float(r['received']),
                 'unit': 'frames', 'baseline': float(r['sent']), 'baseline_name': 'sent',
                 'ratio': r['received'] / max(1, r['sent']), 'target': '1.0 (none lost)'})
    return rows


def run(quick: bool = False) -> list[dict]:
    """1280×720 images, defaults against the profile (the 640×480 rows: area ``loop``)."""
    seconds = 3.0 if quick else 10.0
    hd = (('median', 50), ('p99', 99))
    default = hop(2, False, HD, seconds)
    profiled = hop(2, True, HD, seconds)
    return _rows('transport: 1280×720 hop, 2 processes, defaults', default, None, None,
                 'baseline', hd) \
        + _rows('transport: 1280×720 hop, 2 processes, profile', profiled, default,
                'defaults', '≤ 0.5× defaults', hd)


if __name__ == '__main__':
    from benchmarks.bench import main
    sys.exit(main(['transport', *sys.argv[1:]]))
