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


_LARGE = """
import ctypes
import numpy as np
from magcal.core.memory import keep_large_blocks

libc = ctypes.CDLL("libc.so.6")

class Info(ctypes.Structure):  # glibc's struct mallinfo2
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

libc.mallinfo2.restype = Info

def mapped_for(n=8 << 20):  # bytes of fresh mappings a 64 MB array (above glibc's largest mmap threshold) takes
    before = libc.mallinfo2().hblkhd
    a = np.ones(n)
    mapped = libc.mallinfo2().hblkhd - before
    del a
    return mapped

keep_large_blocks()  # the plain setting first: an array this large is still a fresh mapping
first = mapped_for()
done = keep_large_blocks(every_size=True)
mapped_for()
print(first, mapped_for(), done, keep_large_blocks(every_size=True), keep_large_blocks())
"""


def test_every_size_serves_even_the_largest_temporaries_from_the_heap():
    """Above 32 MB glibc maps every array afresh, whatever the thresholds, each time zeroed and faulted in (a
    4 x 1e6 fit's temporaries); keep_large_blocks(every_size=True), as the diagnosis's workers call it, serves them
    from the heap and keeps them there."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
    out = subprocess.run([sys.executable, "-c", _LARGE], capture_output=True, text=True, env=env, timeout=120)
    if "mallinfo2" in out.stderr:
        pytest.skip("glibc before 2.33 has no mallinfo2")
    assert out.returncode == 0, out.stderr[-2000:]
    before, after, done, again, plain = out.stdout.split()
    assert int(before) >= 64 << 20  # a fresh mapping
    assert int(after) == 0  # from the heap
    assert (done, again, plain) == ("True", "False", "False")  # once; the plain call does not undo it
