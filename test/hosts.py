"""
Two hosts on one machine: two Linux network namespaces joined by a veth pair.

``TwoHosts(domain)`` is a context manager: on entry it creates the namespaces ``ssv<d>a`` and
``ssv<d>b`` (d = the ROS domain id the test holds, so parallel test runs never share a name),
a veth pair with one end in each (``veth-a`` ↔ ``veth-b``), addresses ``10.213.<d>.1/24`` and
``.2/24`` of their own, and ``lo`` up in both. ``popen(host, cmd, env)`` runs a process inside
a namespace (``ip netns exec``), ``cut()`` / ``restore()`` take the link down and up,
``rx_bytes(host)`` counts what the host's veth end (or another device) received. Each host
also gets a default route through the veth, as a LAN host has: DDS discovery multicasts, and
multicast needs a route. On exit, even after a failure or Ctrl-C, it stops the processes it
started (SIGINT, then SIGKILL) and deletes both namespaces (which deletes the veth pair).
Leftovers of a run that was killed before it could clean up are removed on entry: namespaces
of this domain, of any domain whose lock no test holds (conftest's lock files), and probes.

Each namespace has its own interfaces and routes but shares the rest of the machine (files,
``/dev/shm``, the clock, the hostname). Fast DDS tells hosts apart by a host id hashed from
the hostname and the IPv4 addresses of the interfaces it sees, and keeps a remote participant's
shared-memory locator only when that locator carries its own host id; the two namespaces see
different addresses, so their participants talk UDP over the veth (the two-host test checks
that, with the veth's byte counter and by cutting the link).

:func:`namespaces_unavailable` says why namespaces cannot be made here (not root, no ``ip``,
or the kernel refuses), or None; the ``two_hosts`` fixture of ``test_two_hosts.py`` skips
with that reason.
"""
from __future__ import annotations

from dataclasses import dataclass
import fcntl
import json
import os
from pathlib import Path
import re
import shutil
import signal
import subprocess
import time

from conftest import LOCK_DIR

from sphere_servo.bringup.processes import interrupt

NAME = re.compile(r'^ssv(\d+)[ab]$')
PROBE = re.compile(r'^ssvprobe(\d+)$')  # named after the pid of the process that probes
IP_TIMEOUT = 20.0
# processes are stopped as Ctrl-C does first: a DDS participant that exits removes its
# shared-memory segment (32 MiB with the profile), one killed outright leaves it in /dev/shm
STOP_TIMEOUT = 5.0


@dataclass(frozen=True)
class Host:
    """One simulated host: its namespace, its end of the veth pair and its address."""

    netns: str
    device: str
    address: str


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    out = subprocess.run(['ip', *args], capture_output=True, text=True, timeout=IP_TIMEOUT)
    if check and out.returncode != 0:
        raise RuntimeError(f'ip {" ".join(args)} failed ({out.returncode}): '
                           f'{out.stderr.strip()}')
    return out


def namespaces() -> list[str]:
    """Return the names of the network namespaces that exist (``ip netns list``)."""
    out = _ip('-j', 'netns', 'list').stdout.strip()
    return [ns['name'] for ns in json.loads(out)] if out else []


def namespaces_unavailable() -> str | None:
    """Return why network namespaces cannot be created here, or None if they can."""
    if shutil.which('ip') is None:
        return 'no `ip` command (iproute2) to create network namespaces'
    if os.geteuid() != 0:
        return f'network namespaces need root (running as uid {os.geteuid()})'
    probe = f'ssvprobe{os.getpid()}'
    made = _ip('netns', 'add', probe, check=False)
    if made.returncode != 0:
        return f'`ip netns add` fails here: {made.stderr.strip()}'
    _ip('netns', 'del', probe, check=False)
    return None


def _kill_and_delete(netns: str) -> None:
    """Stop every process inside ``netns``, then delete it (a namespace with processes stays)."""
    pids = [int(p) for p in _ip('netns', 'pids', netns, check=False).stdout.split()]
    for sig, grace in ((signal.SIGINT, STOP_TIMEOUT), (signal.SIGKILL, 0.0)):
        for pid in pids:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline and any(Path(f'/proc/{p}').exists() for p in pids):
            time.sleep(0.05)
    _ip('netns', 'del', netns, check=False)


def _domain_is_free(domain: int) -> bool:
    """Return True if no test holds ``domain`` (its lock file can be taken, and is let go)."""
    LOCK_DIR.mkdir(exist_ok=True)
    with open(LOCK_DIR / f'{domain}.lock', 'w') as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return False
        fcntl.flock(fh, fcntl.LOCK_UN)
        return True


def remove_leftovers(domain: int) -> list[str]:
    """
    Delete the namespaces a killed run left behind; return their names.

    Ours (``domain``, which the caller holds), those of domains that no test holds, and the
    probes of processes that are gone.
    """
    gone = []
    for netns in namespaces():
        m, probe = NAME.match(netns), PROBE.match(netns)
        if (m and (int(m.group(1)) == domain or _domain_is_free(int(m.group(1))))) \
                or (probe and not Path(f'/proc/{probe.group(1)}').exists()):
            _kill_and_delete(netns)
            gone.append(netns)
    return gone


class TwoHosts:
    """Two network namespaces joined by a veth pair (see the module docstring)."""

    def __init__(self, domain: int):
        if not 0 <= domain <= 232:
            raise ValueError(f'ROS domain id {domain} outside 0..232')
        self.domain = domain
        subnet = f'10.213.{domain}'
        self.a = Host(f'ssv{domain}a', 'veth-a', f'{subnet}.1')
        self.b = Host(f'ssv{domain}b', 'veth-b', f'{subnet}.2')
        self.procs: list[subprocess.Popen] = []

    def __enter__(self) -> TwoHosts:
        remove_leftovers(self.domain)
        try:
            for h in (self.a, self.b):
                _ip('netns', 'add', h.netns)
            _ip('link', 'add', self.a.device, 'netns', self.a.netns, 'type', 'veth',
                'peer', 'name', self.b.device, 'netns', self.b.netns)
            for h in (self.a, self.b):
                _ip('-n', h.netns, 'addr', 'add', f'{h.address}/24', 'dev', h.device)
                _ip('-n', h.netns, 'link', 'set', 'dev', 'lo', 'up')
            self.restore()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the processes started here and delete both namespaces (and so the veth pair)."""
        for p in self.procs:
            interrupt(p, STOP_TIMEOUT)
        for h in (self.a, self.b):
            if h.netns in namespaces():
                _kill_and_delete(h.netns)

    def popen(self, host: Host, cmd: list[str], env: dict, **kwargs) -> subprocess.Popen:
        """Start ``cmd`` inside ``host``'s namespace with exactly ``env``; stopped on exit."""
        p = subprocess.Popen(['ip', 'netns', 'exec', host.netns, *cmd], env=env, **kwargs)
        self.procs.append(p)
        return p

    def cut(self) -> None:
        """Take both ends of the link down: nothing crosses until :meth:`restore`."""
        for h in (self.a, self.b):
            _ip('-n', h.netns, 'link', 'set', 'dev', h.device, 'down')

    def restore(self) -> None:
        """
        Bring both ends of the link up, with each host's default route through it.

        The default route carries the multicast of DDS discovery (239.255.0.1), which has no
        route otherwise; the kernel drops it when its device goes down and, unlike the
        subnet's route, does not put it back (a real host's network manager does).
        """
        for h in (self.a, self.b):
            _ip('-n', h.netns, 'link', 'set', 'dev', h.device, 'up')
            _ip('-n', h.netns, 'route', 'replace', 'default', 'dev', h.device)

    def rx_bytes(self, host: Host, device: str | None = None) -> int:
        """Return the bytes ``device`` of ``host`` (default: its veth end) has received so far."""
        out = _ip('-n', host.netns, '-j', '-s', 'link', 'show', 'dev',
                  device or host.device).stdout
        return int(json.loads(out)[0]['stats64']['rx']['bytes'])
