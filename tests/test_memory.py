"""magcal.core.memory: under Dask's MALLOC_TRIM_THRESHOLD_, every numpy temporary of 128 kB or more is a fresh mmap
whose pages fault in one by one; keep_large_blocks lets the heap serve and keep them again."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")

_FAULTS = """
import resource, sys
import numpy as np
from magcal.core.memory import keep_large_blocks

def faults(rounds=200, n=131_072):  # 1 MB temporaries, made and freed
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(rounds):
        a = np.ones(n)
        del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

faults(5)
first = faults()
done = keep_large_blocks()
faults(5)
print(first, faults(), done, keep_large_blocks())
"""


@pytest.mark.parametrize("dask_setting", [True, False])
def test_large_temporaries_stop_faulting_once_the_thresholds_are_raised(dask_setting):
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    if dask_setting:
        env["MALLOC_TRIM_THRESHOLD_"] = "65536"  # what dask.distributed gives its workers
    env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
    out = subprocess.run([sys.executable, "-c", _FAULTS], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    before, after, done, again = out.stdout.split()
    pages = 200 * 131_072 * 8 // 4096  # every temporary's pages, had each been a fresh mapping
    if dask_setting:
        assert int(before) > pages // 2  # Dask's setting: a fresh mmap, faulted page by page, every time
    assert int(after) < pages // 20  # raised: the heap keeps the block
    assert done == "True" and again == "False"  # set once per process
