"""The allocator setting of the command line: large freed blocks are reused, not unmapped."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

# allocate, touch and free a 64 MB array ten times; report the minor page faults of the loop
_PROBE = """
import json, resource, sys
import numpy as np
from sgpor_pipeline.allocator import keep_freed_memory
applied = keep_freed_memory()
np.ones(16 << 20, np.float32)  # the first one faults in any case
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    np.ones(16 << 20, np.float32)
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
print(json.dumps({"applied": applied, "faults": faults}))
"""


def _probe(**env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if k not in ("SGPOR_MALLOC", "MALLOC_MMAP_MAX_",
                                                                "MALLOC_TRIM_THRESHOLD_")}
    out = subprocess.run([sys.executable, "-c", _PROBE], env={**clean, **env}, capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the setting is glibc's")
def test_large_blocks_are_reused_instead_of_faulted_in_again():
    tuned = _probe()
    default = _probe(SGPOR_MALLOC="default")
    assert tuned["applied"] and not default["applied"]
    # 10 x 64 MB of new pages with glibc's default: at least 320 faults (2 MB huge pages; 160k with
    # 4 kB pages; 5.4k here); reused blocks fault almost never
    assert default["faults"] >= 320
    assert tuned["faults"] < default["faults"] / 10


def test_a_users_own_malloc_settings_are_kept():
    assert not _probe(MALLOC_MMAP_MAX_="65536")["applied"]
    assert not _probe(MALLOC_TRIM_THRESHOLD_="131072")["applied"]
