"""
DDS between two hosts, and on one host, with the shipped Fast DDS profile (issue 17).

The hosts are network namespaces joined by a veth pair (``hosts.TwoHosts``); the processes
are the bare image hop of the transport benchmark (``benchmarks.hop``), 640×480 rgb8, with
the profile's environment and discovery on the subnet.

- ``test_dds_crosses_the_link_and_a_cut_stops_it``: a publisher on host A, a subscriber on
  host B and one on A. Images reach B, and B's veth receives at least their bytes (they go
  over the link, not through the shared memory both namespaces can see); with the link down
  for 2 s nothing reaches B while A's own subscriber keeps receiving (so the publisher did
  not stall); once it is up, new images reach B again.
- ``test_on_one_host_images_go_through_shared_memory``: publisher and subscriber in one
  namespace, where nothing else runs, 1280×720 best effort: with the profile the images do
  not touch that namespace's network devices (lo, the veth) at all, and none is lost; with
  Fast DDS's defaults most are lost (they too go through shared memory, as 64 KB fragments,
  but the default 512 KiB segment is reused before the reader has taken an image's
  fragments out: the segment_size warning of the Fast DDS docs).
- ``test_the_namespaces_are_gone_after_a_failure``: the context manager deletes both
  namespaces when the body raises, and removes the leftovers of a killed run on entry.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

from benchmarks.hop import hop_env
from conftest import _acquire_domain_id
from hosts import namespaces, namespaces_unavailable, TwoHosts
import pytest

IMAGE_BYTES = 640 * 480 * 3
HD, HD_BYTES = ('--width', '1280', '--height', '720'), 1280 * 720 * 3
RATE = 20.0
CUT = 2.0
# a frame already in B's socket buffer when the link goes down may still come out this late
DRAIN = 0.3


@pytest.fixture
def domain():
    """Return a ROS domain id no other test holds (conftest's lock), for this test."""
    domain, lock = _acquire_domain_id()
    yield domain
    lock.close()


@pytest.fixture
def two_hosts(domain):
    """Two namespaces joined by a veth pair, deleted afterwards; skipped where impossible."""
    reason = namespaces_unavailable()
    if reason:
        pytest.skip(reason)
    with TwoHosts(domain) as hosts:
        yield hosts
    assert not {hosts.a.netns, hosts.b.netns} & set(namespaces())


class Stream:
    """The per-frame lines of a ``hop sub --stream`` process, read as they come."""

    def __init__(self, popen: subprocess.Popen):
        self.popen, self.frames, self.text = popen, [], []
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self):
        for line in self.popen.stdout:
            self.text.append(line)
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if 'arrival' in rec:
                self.frames.append(rec)

    def arrivals(self, t0: float, t1: float) -> list[dict]:
        return [f for f in list(self.frames) if t0 <= f['arrival'] < t1]

    def wait(self, pred, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if pred(list(self.frames)):
                return
            if self.popen.poll() is not None:
                break
            time.sleep(0.05)
        pytest.fail(f'{what}: not within {timeout} s ({len(self.frames)} frames so far); '
                    f'subscriber said:\n{"".join(self.text[-20:])}')


def _hop(role: str, *args: str) -> list[str]:
    return [sys.executable, '-m', 'benchmarks.hop', role, *args]


@pytest.mark.ros
def test_dds_crosses_the_link_and_a_cut_stops_it(two_hosts, domain):
    env = hop_env(domain, True, 'SUBNET')
    a, b = two_hosts.a, two_hosts.b
    sub_b = Stream(two_hosts.popen(b, _hop('sub', '--stream'), env, stdout=subprocess.PIPE,
                                   text=True))
    sub_a = Stream(two_hosts.popen(a, _hop('sub', '--stream'), env, stdout=subprocess.PIPE,
                                   text=True))
    two_hosts.popen(a, _hop('pub', '--rate', str(RATE), '--seconds', '120', '--warmup', '0'),
                    env, stdout=subprocess.DEVNULL)
    sub_b.wait(lambda f: len(f) >= 10, 60, 'images from host A on host B')
    sub_a.wait(lambda f: len(f) >= 10, 30, 'images on host A itself')

    # the images cross the veth: B's end receives at least their bytes
    n0, rx0 = len(sub_b.frames), two_hosts.rx_bytes(b)
    time.sleep(2.0)
    n1, rx1 = len(sub_b.frames), two_hosts.rx_bytes(b)
    assert n1 - n0 >= RATE  # at least 1 s worth in 2 s
    assert rx1 - rx0 >= (n1 - n0) * IMAGE_BYTES, \
        f'{n1 - n0} images reached B but its veth received only {rx1 - rx0} bytes'

    t_cut = time.time()
    two_hosts.cut()
    time.sleep(CUT)
    t_restore = time.time()
    two_hosts.restore()
    during_b = sub_b.arrivals(t_cut + DRAIN, t_restore)
    during_a = sub_a.arrivals(t_cut + DRAIN, t_restore)
    assert not during_b, f'{len(during_b)} images reached B while the link was down'
    assert len(during_a) >= 0.5 * RATE * (CUT - DRAIN), \
        f'the publisher stalled during the cut: host A itself got {len(during_a)} images'

    # published after the link came back, and received
    sub_b.wait(lambda f: sum(x['stamp'] > t_restore for x in f) >= 10, 30,
               'images published after the link came back')


def _lo_and_veth_rx(hosts: TwoHosts) -> int:
    return hosts.rx_bytes(hosts.a, 'lo') + hosts.rx_bytes(hosts.a)


def _one_host_run(hosts: TwoHosts, env: dict) -> tuple[dict, dict, int]:
    """Best-effort 1280×720 hop inside host A; return (pub summary, sub summary, network bytes)."""
    sub = hosts.popen(hosts.a, _hop('sub', '--qos', 'best_effort', *HD), env,
                      stdout=subprocess.PIPE, text=True)
    rx0 = _lo_and_veth_rx(hosts)
    pub = hosts.popen(hosts.a, _hop('pub', '--qos', 'best_effort', '--seconds', '3',
                                    '--rate', '30', '--warmup', '1', *HD), env,
                      stdout=subprocess.PIPE, text=True)
    pub_out = pub.communicate(timeout=90)[0]
    rx1 = _lo_and_veth_rx(hosts)
    sub.send_signal(2)
    sub_out = sub.communicate(timeout=30)[0]
    assert pub.returncode == 0 and sub.returncode == 0, (pub_out, sub_out)
    return (json.loads(pub_out.strip().splitlines()[-1]),
            json.loads(sub_out.strip().splitlines()[-1]), rx1 - rx0)


@pytest.mark.ros
def test_on_one_host_images_go_through_shared_memory(two_hosts, domain):
    sent, got, network = _one_host_run(two_hosts, hop_env(domain, True, 'SUBNET'))
    assert sent['sent'] == 90
    assert got['received'] == sent['sent'], 'best effort lost images with the profile'
    # discovery and heartbeats only: far less than one image
    assert network < HD_BYTES / 10, f'{network} bytes went over lo/veth'

    sent, got, _ = _one_host_run(two_hosts, hop_env(domain, False, 'SUBNET'))
    assert got['received'] < 0.95 * sent['sent'], \
        f'defaults lost no image ({got["received"]}/{sent["sent"]}): is the profile needed?'


def test_the_namespaces_are_gone_after_a_failure(domain):
    reason = namespaces_unavailable()
    if reason:
        pytest.skip(reason)
    hosts = TwoHosts(domain)
    with pytest.raises(ZeroDivisionError):
        with hosts:
            assert {hosts.a.netns, hosts.b.netns} <= set(namespaces())
            proc = hosts.popen(hosts.a, ['sleep', '600'], dict(os.environ))
            1 / 0
    assert not {hosts.a.netns, hosts.b.netns} & set(namespaces())
    assert proc.poll() is not None

    # a run killed before its cleanup leaves a namespace with a process in it
    subprocess.run(['ip', 'netns', 'add', hosts.a.netns], check=True)
    orphan = subprocess.Popen(['ip', 'netns', 'exec', hosts.a.netns, 'sleep', '600'])
    time.sleep(0.2)
    with TwoHosts(domain) as again:
        assert set(namespaces()) >= {again.a.netns, again.b.netns}
        assert orphan.wait(timeout=10) != 0  # killed on entry
    assert not {hosts.a.netns, hosts.b.netns} & set(namespaces())


def test_hosts_module_names_its_namespaces_after_the_domain():
    hosts = TwoHosts(42)
    assert (hosts.a.netns, hosts.b.netns) == ('ssv42a', 'ssv42b')
    assert (hosts.a.address, hosts.b.address) == ('10.213.42.1', '10.213.42.2')
    with pytest.raises(ValueError):
        TwoHosts(300)
