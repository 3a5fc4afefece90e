"""The C library's allocator in magcal's own worker processes.

``dask.distributed`` starts its workers with ``MALLOC_TRIM_THRESHOLD_`` set (``distributed.nanny.pre-spawn-environ``),
and a fork server started by Dask passes it on to every process forked from it, magcal's diagnosis workers included.
Setting it turns off glibc's dynamic mmap threshold: every array of 128 kB or more is then a fresh ``mmap`` whose
pages fault in one by one and are unmapped when freed, and the heap is trimmed whenever 64 kB lie free at its top.
numpy's temporaries (a 20 000-row column is 160 kB; a diagnosis's Jacobian blocks are megabytes) then cost a page
fault per 4 kB every time. :func:`keep_large_blocks` sets the thresholds glibc's dynamic rule would reach.
"""

from __future__ import annotations

#: Bytes below which glibc's ``malloc`` serves an allocation from the heap (its dynamic threshold's ceiling on a
#: 64-bit machine), and free bytes at the heap's top above which it gives them back to the system.
MMAP_THRESHOLD_BYTES = 32 << 20
TRIM_THRESHOLD_BYTES = 2 * MMAP_THRESHOLD_BYTES

#: With :func:`keep_large_blocks`'s ``every_size``: free bytes at the heap's top kept for the next arrays.
LARGE_TRIM_THRESHOLD_BYTES = 1 << 30

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4  # mallopt's parameters (malloc.h)
_SET = False
_EVERY_SIZE = False


def keep_large_blocks(every_size: bool = False) -> bool:
    """Raise this process's mmap and trim thresholds (``mallopt``, once per process).

    Measured on the 2-core development machine: a survey partition of 4e5 rows in a process with Dask's setting
    took a median 5.2 s against 1.6 s with the thresholds raised (four runs each); a diagnosis of 4 x 1e5 samples
    in two worker processes 9.1-11.6 s against 4.4-5.8 s.

    Parameters
    ----------
    every_size : bool
        Also serve arrays above glibc's largest mmap threshold (32 MB) from the heap, and keep up to
        :data:`LARGE_TRIM_THRESHOLD_BYTES` free at its top: such an array is otherwise a fresh ``mmap`` every time,
        each of its pages faulted in and zeroed (at 4 x 1e6 samples a fit's temporaries are 30-100 MB; a refit took
        13.3-14.6 s against 10.9-11.1 s served from the heap, the calibration 4.0-4.1 against 3.4-3.6 s, for 3 %
        more peak memory: ``benchmarks/large_records.py --parts malloc``).
        For the diagnosis's worker processes, which live for one diagnosis.

    Returns
    -------
    bool
        Whether the thresholds were set (False where the C library is not glibc, or already done).
    """
    global _SET, _EVERY_SIZE
    if _SET and (_EVERY_SIZE or not every_size):
        return False
    _SET, _EVERY_SIZE = True, _EVERY_SIZE or every_size
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
        trim = LARGE_TRIM_THRESHOLD_BYTES if every_size else TRIM_THRESHOLD_BYTES
        ok = libc.mallopt(_M_TRIM_THRESHOLD, trim) == 1 and ok
        if every_size:
            ok = libc.mallopt(_M_MMAP_MAX, 0) == 1 and ok
        return bool(ok)
    except (OSError, AttributeError):
        return False


def available_bytes() -> int | None:
    """Memory this process may still take without the machine (or its container) running out, bytes.

    The smaller of the kernel's estimate of what can be allocated without swapping (``MemAvailable`` in
    ``/proc/meminfo``) and what a cgroup's limit leaves (``memory.max`` less ``memory.current``, or cgroup v1's
    ``memory.limit_in_bytes`` less ``memory.usage_in_bytes``), so that a container with a limit below the machine's
    memory is not taken for the machine. None where neither can be read (not Linux).
    """
    found = []
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    found.append(int(line.split()[1]) * 1024)
                    break
    except (OSError, ValueError, IndexError):
        pass
    for limit_path, usage_path in (
        ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
        ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"),
    ):
        try:
            with open(limit_path, encoding="ascii") as fh:
                limit = fh.read().strip()
            with open(usage_path, encoding="ascii") as fh:
                usage = int(fh.read().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < 1 << 60:  # "max", or v1's huge number: no limit
            found.append(max(int(limit) - usage, 0))
        break
    return min(found) if found else None
