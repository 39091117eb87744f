"""
``pipeline.allocator.keep_heap``: image-sized blocks come back from the heap, no fresh pages.

Each case runs in a process of its own (the thresholds are the process's for good): three
921,600-byte blocks (a 640×480 rgb8 image each) allocated, filled and freed per frame, as a
subscriber of images does, and the minor page faults a frame counted.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys

import pytest
from sphere_servo.pipeline.allocator import keep_heap, USER_VARIABLES

REPO = Path(__file__).resolve().parents[1]
PAGES = 3 * 921600 // 4096  # the pages one frame's blocks span
# what an image message's reception allocates and frees: three 900 KB blocks, filled
FRAME = r"""
import resource
import numpy as np


def frame():
    blocks = [np.ones(921600, np.uint8) for _ in range(3)]
    return sum(int(b[::4096].sum()) for b in blocks)


def faults_per_frame(n=50):
    for _ in range(5):
        frame()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        frame()
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / n
"""
SCRIPT = FRAME + r"""
import json, sys
from sphere_servo.pipeline.allocator import keep_heap

done = keep_heap() if sys.argv[1] == 'keep' else None
print(json.dumps({'set': done, 'faults_per_frame': faults_per_frame(100)}))
"""


def _faults(mode: str, **env) -> dict:
    e = {k: v for k, v in os.environ.items() if k not in USER_VARIABLES}
    e.update(env, PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, '-c', SCRIPT, mode], env=e, capture_output=True,
                         text=True, timeout=60, check=True)
    return json.loads(out.stdout)


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='glibc (Linux) only')
def test_glibc_defaults_refault_each_frame_and_keep_heap_does_not():
    plain = _faults('plain')
    kept = _faults('keep')
    # the premise: with glibc's defaults most of a frame's pages are new each frame
    assert plain['faults_per_frame'] > 0.5 * PAGES, plain
    assert kept['set'] is True, kept
    assert kept['faults_per_frame'] < 0.01 * PAGES, kept


@pytest.mark.parametrize('name', USER_VARIABLES)
def test_a_users_glibc_variable_wins(name):
    """The user's own MALLOC_*_ setting is left as it is: nothing set, glibc reads it."""
    assert keep_heap({name: '131072'}) is False
    got = _faults('keep', **{name: '131072'})
    assert got['set'] is False, got
