"""
Drive Debian's headless Chromium from the tests: screenshots, and what a page requests.

- :func:`chromium` finds the browser, or fails the test saying why (``make test`` installs
  it with apt-get as root; its log is read when the install failed). Never a skip.
- :func:`screenshot` takes ``--screenshot`` of a page, WebGL through SwiftShader.
- :func:`load` opens a page under the DevTools protocol (over ``--remote-debugging-pipe``:
  JSON messages ending in a NUL byte, on file descriptors 3 and 4) and returns every
  request the *page* made (the Network domain of its own target, so Chromium's own
  background traffic is not mixed in) and every uncaught JavaScript exception.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import json
import os
from pathlib import Path
import select
import shutil
import subprocess
import tempfile
import time

import cv2
import numpy as np
import pytest

INSTALL_LOG = Path(__file__).resolve().parents[1] / '.venv' / 'chromium-install.log'
# as the machine notes say for a closed network: no background connections, a new profile
FLAGS = ['--headless', '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
         '--disable-background-networking', '--disable-component-update', '--disable-sync',
         '--disable-default-apps', '--disable-extensions', '--hide-scrollbars',
         '--use-angle=swiftshader', '--enable-unsafe-swiftshader']


def chromium() -> str:
    """Debian's chromium, or fail the test with why it is missing."""
    path = shutil.which('chromium') or shutil.which('chromium-browser')
    if path is None:
        why = INSTALL_LOG.read_text(errors='replace')[-1500:] if INSTALL_LOG.is_file() else \
            'no install was tried: run the tests with `make test`, which installs it'
        pytest.fail('chromium is not installed, so the page cannot be checked in a browser; '
                    f'`apt-get install -y chromium` (as root) installs it. {why}')
    return path


def _profile():
    # chromium's helper processes (crashpad) may still write to the profile after the
    # browser exits: a cleanup that races them is no failure of the page under test
    return tempfile.TemporaryDirectory(prefix='chromium-', ignore_cleanup_errors=True)


def screenshot(url: str, out: Path, size: tuple[int, int], budget_ms: int = 4000) -> np.ndarray:
    """Screenshot of ``url`` at ``size`` (W, H) after ``budget_ms`` of virtual time, rgb."""
    with _profile() as profile:
        cmd = [chromium(), *FLAGS, f'--user-data-dir={profile}',
               f'--window-size={size[0]},{size[1]}', f'--virtual-time-budget={budget_ms}',
               f'--screenshot={out}', url]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    img = cv2.imread(str(out))
    assert proc.returncode == 0 and img is not None, proc.stderr[-2000:]
    assert img.shape[:2] == (size[1], size[0])
    return img[..., ::-1]


@dataclass
class PageLoad:
    """What a page did when loaded: its requests' URLs, its uncaught exceptions."""

    requests: list = field(default_factory=list)
    exceptions: list = field(default_factory=list)
    loaded: bool = False


def load(url: str, seconds: float = 4.0) -> PageLoad:
    """Open ``url`` in a new tab under the DevTools protocol; watch it for ``seconds``."""
    to_child_r, to_child_w = os.pipe()
    from_child_r, from_child_w = os.pipe()

    def fds():  # the protocol's pipe ends as the child's fds 3 and 4 (dup2 makes them
        a, b = os.dup(to_child_r), os.dup(from_child_w)  # inheritable; dup first so a pipe
        os.dup2(a, 3)                                    # already on 3 or 4 moves too)
        os.dup2(b, 4)

    with _profile() as profile:
        proc = subprocess.Popen([chromium(), *FLAGS, f'--user-data-dir={profile}',
                                 '--remote-debugging-pipe', 'about:blank'],
                                preexec_fn=fds, close_fds=False, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        os.close(to_child_r)
        os.close(from_child_w)
        events, state = [], {'buf': b'', 'id': 0}

        def send(method, params=None, session=None) -> int:
            state['id'] += 1
            msg = {'id': state['id'], 'method': method, 'params': params or {}}
            if session:
                msg['sessionId'] = session
            os.write(to_child_w, json.dumps(msg).encode() + b'\0')
            return state['id']

        def read(until: int | None = None, timeout: float = 30.0):
            end = time.monotonic() + timeout
            while time.monotonic() < end:
                while b'\0' in state['buf']:
                    raw, state['buf'] = state['buf'].split(b'\0', 1)
                    msg = json.loads(raw)
                    if until is not None and msg.get('id') == until:
                        assert 'error' not in msg, msg
                        return msg['result']
                    if 'method' in msg:
                        events.append(msg)
                if select.select([from_child_r], [], [], 0.1)[0]:
                    chunk = os.read(from_child_r, 1 << 16)
                    assert chunk, 'chromium closed the DevTools pipe'
                    state['buf'] += chunk
            assert until is None, f'no DevTools answer to message {until} in {timeout} s'

        try:
            target = read(send('Target.createTarget', {'url': 'about:blank'}))['targetId']
            sid = read(send('Target.attachToTarget', {'targetId': target,
                                                      'flatten': True}))['sessionId']
            for domain in ('Network', 'Page', 'Runtime'):
                read(send(f'{domain}.enable', {}, sid))
            read(send('Page.navigate', {'url': url}, sid))
            read(None, seconds)
        finally:
            proc.terminate()
            proc.wait(30)
            os.close(to_child_w)
            os.close(from_child_r)
    out = PageLoad()
    for e in events:
        if e.get('sessionId') != sid:
            continue
        if e['method'] == 'Network.requestWillBeSent':
            out.requests.append(e['params']['request']['url'])
        elif e['method'] == 'Runtime.exceptionThrown':
            out.exceptions.append(e['params']['exceptionDetails'])
        elif e['method'] == 'Page.loadEventFired':
            out.loaded = True
    return out
