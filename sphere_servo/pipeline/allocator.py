"""
The C allocator of a node process: image-sized blocks stay in the heap between messages.

glibc serves a block above ``M_MMAP_THRESHOLD`` (128 KB at first, raised to the largest block
freed since, up to 32 MB) with a fresh ``mmap`` and gives the top of the heap back to the
kernel once more than ``M_TRIM_THRESHOLD`` of it is free. A process that receives 640×480
rgb8 images allocates and frees several 900 KB blocks per message (rmw's buffer, the
message's ``data`` array, numpy's arrays), and either rule makes the next message's blocks
new pages: measured on this machine, a bare subscriber took 19 000 minor page faults a second
at 30 Hz, and the image hop publish → callback was 3.5 ms with them against 1.4 ms without
(1.65 against 0.76 ms in one process). Whether a process pays them depends on how its heap
happens to be laid out, so the nodes would have paid them or not by accident.

:func:`keep_heap` sets both thresholds once at start-up (``mallopt``), as the ROS 2 real-time
demos do (``rttest``: no trimming, no mmap): blocks up to :data:`MMAP_THRESHOLD` come from the
heap, and it is trimmed only when :data:`TRIM_THRESHOLD` of it is free. The resident memory of
a node then stays at its peak of the last frames: 3–4 MiB more in the detector and the
camera's process at 60 Hz (210 and 232 MiB; ``make bench``, area ``loop``, prints it).
Every node process (:func:`sphere_servo.ros.params.run`) and the benchmarks' bare hops call
it, so that the pipeline and the hop it is compared with allocate alike. Where the C library
is not glibc, or where the user set ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_``
(glibc's own environment variables), it changes nothing.
"""
from __future__ import annotations

from collections.abc import Mapping
import ctypes
import os

MMAP_THRESHOLD = 32 << 20   # bytes: a 4K rgb8 image (24.9 MB) still comes from the heap
TRIM_THRESHOLD = 128 << 20  # bytes of free heap top kept
M_TRIM_THRESHOLD = -1       # glibc's malloc.h
M_MMAP_THRESHOLD = -3
USER_VARIABLES = ('MALLOC_MMAP_THRESHOLD_', 'MALLOC_TRIM_THRESHOLD_')


def keep_heap(env: Mapping[str, str] | None = None) -> bool:
    """
    Set glibc's mmap and trim thresholds (module docstring); return whether they were set.

    False, and nothing changed, where ``env`` (default: this process's environment) names
    one of :data:`USER_VARIABLES` or where the C library has no ``mallopt`` (not glibc).
    """
    env = os.environ if env is None else env
    if any(name in env for name in USER_VARIABLES):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt returns 1 on success, 0 on error
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) \
        and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
