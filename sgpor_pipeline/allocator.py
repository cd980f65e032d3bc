"""Process-wide memory allocator settings for the command line and the benchmarks (not the library).

glibc serves every allocation above 32 MB (its largest mmap threshold) with a fresh ``mmap`` and
gives it back with ``munmap`` on free. A training iteration on a real capture allocates several such
buffers (kitchen, 360k Gaussians: the [N,15,3] SH gradient alone is 65 MB), so each iteration pays
the page faults and the zeroing of its new pages. With mmap off and no trimming, freed blocks stay
in the heap and the next iteration reuses them. The whole kitchen fit (2000 iterations, 360k
Gaussians), back to back: 455 s -> 426 s wall, 64 -> 16 s of system time, 27.2M -> 0.41M minor page
faults, the same result; peak memory 1.51 -> 1.75 GB. Its finetune, 33 iterations per process: 13 %
less CPU time. The demo scene (80k Gaussians, buffers under the threshold) is unchanged, in time
and peak memory. The cost: memory freed after the peak is not returned to the system until the
process ends.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

# mallopt parameter numbers (glibc malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
# the glibc environment variables for the same settings: a user who sets either keeps their choice
_ENV = ("MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_")


def keep_freed_memory() -> bool:
    """Make glibc keep large freed blocks for reuse instead of unmapping them (see the module
    docstring). Returns True when the settings were applied; False off glibc (macOS, musl), when
    the user set ``MALLOC_MMAP_MAX_`` or ``MALLOC_TRIM_THRESHOLD_``, or ``SGPOR_MALLOC=default``."""
    if not sys.platform.startswith("linux") or os.environ.get("SGPOR_MALLOC", "") == "default":
        return False
    if any(name in os.environ for name in _ENV):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018 (only glibc has it: musl's mallopt does nothing)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # the trim threshold first: with mmap off, a large free at the top of the heap would otherwise
    # give the pages back at once
    return bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)) and bool(mallopt(_M_MMAP_MAX, 0))
