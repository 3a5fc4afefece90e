"""Independent fits of a diagnosis run side by side on the machine's cores, or on a Dask cluster.

The confirming refits of the best candidates, the held-out fits of each scheme and candidate and the chunks of a
score round's normal equations do not depend on one another. Results come back in the order of the calls, so the
diagnosis reads the same whatever finishes first, and wherever it ran.

Where the work runs (:class:`Pool`, chosen per diagnosis):

- **threads** (the fallback): numpy releases the interpreter in its loops and BLAS calls, so threads keep two cores
  busy and nothing is copied. Python threads contend for the interpreter between numpy calls, so beyond a few cores
  they stop paying; a small record (fewer than :data:`PROCESS_MIN_READINGS` readings, or
  :data:`PROCESS_MIN_READINGS_MANY` with :data:`MANY_WORKERS` workers or more) or one core stays here.
- **processes** (:class:`~concurrent.futures.ProcessPoolExecutor`, forked from a fork server that imported
  magcal once, or started with ``spawn`` where there is none, :func:`process_context`): the readings are
  written once into one shared-memory segment (:class:`SharedDataset`; nothing of them is pickled per task), each
  worker maps it read-only on its first task and keeps it, and BLAS runs one thread per worker (threadpoolctl), so
  the workers do not oversubscribe the cores. The segment is unlinked when the diagnosis ends, on an error and on
  Ctrl-C too. Killed outright (SIGKILL), the diagnosis leaves nothing running: each worker ends with the process
  that started its pool (:func:`magcal.core.leftovers.exit_with`), then the fork server and the resource tracker
  end, and the tracker unlinks the segment; a segment left even so (the tracker killed too) is removed by the next
  diagnosis, which says so (:func:`remove_stale_segments`). A fit's notes travel back with its result
  (:class:`~magcal.fitting.fitter.FitResult` ``.notes``).
- **Dask** (``scheduler``: an address, or a ``distributed.Client``): the dataset is scattered to the workers once;
  each task gets it by reference.

The fits (module-level functions whose first argument is the dataset: :func:`fit_task`, :func:`validate_task`,
:func:`normal_equations_task`) go to the processes or the cluster through :meth:`Pool.remote`; everything else
(orchestration, the structure tests, the evidence) runs on the pool's threads in the calling process. A model holding
an effect that is not magcal's own (a user's effects file) stays on threads: a worker process could not import it.

:func:`in_parallel` runs a batch of calls on threads and waits for all of it. A :class:`Pool` lives for a whole
diagnosis and starts each piece of work as soon as what it needs is ready (a candidate's held-out fits the moment
its refit returns, the evidence about the base fit while the refits run), by priority, so that the longest chain of
dependent fits is never queued behind work that can wait.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import itertools
import os
import pickle
import queue
import re
import sys
import threading
import uuid
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor

import numpy as np

from magcal.core import blas, leftovers, memory
from magcal.core.errors import MagcalError
from magcal.data.dataset import Dataset

#: Workers for independent fits (None: one per core, threads at most :data:`MAX_THREADS`; 1: one after the other,
#: in the calling thread).
PARALLEL_FITS = None

#: Most threads by default: every fit in flight holds its own temporaries (about 100 MB for 4 x 1e5 samples), and
#: a diagnosis rarely has more than a dozen pieces of work at once.
MAX_THREADS = 8

#: Most worker processes by default (each holds its own fit's temporaries: about 1 GB for 4 x 1e6 samples).
MAX_PROCESSES = 32

#: Where the fits run: None (by the record's size and the cores: :func:`backend_for`), ``"threads"`` or
#: ``"processes"``.
BACKEND = None

#: Readings (sensors x samples) from which a diagnosis's fits run in worker processes when there is more than one
#: core. Below it the processes' start (the fork server importing numpy, scipy and magcal once per program: about
#: 1.2 s of one core on the 2-core development machine) costs more than the threads lose. Measured there with two
#: workers (2026-11-25, a fresh program each, the fork server cold; benchmarks/notes/scaling.md): 4 x 5e4 samples
#: serial 3.1 s, threads 3.0 s, processes 3.4 s; 4 x 1e5 serial 5.6 s, threads 5.3-6.3 s, processes 5.2-5.4 s (4.3 s
#: once the fork server runs); 4 x 2e5 threads 10.2-12.2 s, processes 9.0-9.7 s. (With ``spawn``, which imported
#: magcal in every worker of every pool, the crossing lay near 1e6 readings.) More cores only widen the processes'
#: lead: threads stop paying beyond a few cores, processes do not.
PROCESS_MIN_READINGS = 400_000

#: From this many workers on, the fits run in processes from :data:`PROCESS_MIN_READINGS_MANY` readings instead:
#: threads stop paying beyond about four (the interpreter's lock), while the processes' start is paid once per
#: program. Measured on a 16-core Intel Xeon (2026-11-26, ``benchmarks/scaling.py --parts diagnosis``, one program
#: per size; benchmarks/notes/scaling.md): threads / processes with 4 workers 0.68 / 0.56 s at 4 x 12 500 samples,
#: 1.08 / 0.75 s at 4 x 25 000, 1.52 / 1.04 s at 4 x 5e4; with 16, 0.80 / 0.59, 1.14 / 0.68, 1.93 / 0.77 s; with
#: 2 workers threads still won below 4 x 1e5 (4 x 5e4: 2.15 / 2.75 s).
MANY_WORKERS = 4

#: Readings from which the fits run in processes when there are at least :data:`MANY_WORKERS` workers: the
#: smallest record measured (4 x 12 500 samples), where a diagnosis takes about a second on one core.
PROCESS_MIN_READINGS_MANY = 50_000

#: Memory of one worker process of a diagnosis: a fixed part (the interpreter, numpy, scipy, magcal) and a part per
#: reading (sensors x samples) of the record, its fits' temporaries (a thread's fit takes the second part only).
#: Measured with ``benchmarks/scaling.py``'s ``DescendantsPeak`` (the largest worker's peak resident memory) on the
#: 2-core development machine: 285, 467, 820 and 1 940 MB at 4e5, 8e5, 1.6e6 and 4e6 readings (about 110 MB and
#: 460 bytes a reading); rounded up here.
WORKER_BASE_BYTES = 120 << 20
WORKER_BYTES_PER_READING = 500

#: What the calling process still adds while its diagnosis runs, per reading: its peak was 490, 804, 1 359 and
#: 3 360 MB at those sizes, of which 220-420 MB before the diagnosis started (about 650 bytes a reading); rounded up.
CALLER_BYTES_PER_READING = 700

#: Share of the memory free at the start that the workers are planned to fill (the rest: other programs, the page
#: cache the next read needs, the estimate's error).
MEMORY_SHARE = 0.8


def workers_for_memory(dataset, workers: int, backend: str) -> tuple[int, str | None]:
    """How many of ``workers`` (worker processes, or threads each running a fit) fit in the memory free now, and
    what to tell the user when that is fewer.

    A diagnosis of 4 x 1e6 samples takes about 2 GB per worker process: on 64 cores with 128 GB, one worker per
    core would run the machine out of memory. The estimate is :data:`WORKER_BASE_BYTES` (processes only) plus
    :data:`WORKER_BYTES_PER_READING` per reading per worker, and :data:`CALLER_BYTES_PER_READING` for this process;
    the free memory is :func:`magcal.core.memory.available_bytes` (a container's limit included). Where it cannot
    be read, ``workers`` is kept.

    Returns
    -------
    workers : int
        At least 1.
    note : str or None
    """
    free = memory.available_bytes()
    if free is None or workers <= 1:
        return workers, None
    readings = dataset.n_sensors * dataset.n_samples
    each = WORKER_BYTES_PER_READING * readings + (WORKER_BASE_BYTES if backend == "processes" else 0)
    budget = MEMORY_SHARE * free - CALLER_BYTES_PER_READING * readings
    fits = max(1, int(budget // each))
    if fits >= workers:
        return workers, None
    kind = "worker processes" if backend == "processes" else "threads"
    return fits, (
        f"the diagnosis ran {fits} of the {workers} {kind} it would have used: each needs about {each / 1e9:.2g} GB "
        f"for {readings:,} readings and {free / 1e9:.3g} GB of memory were free, so more would have run this machine "
        "out of memory (with more memory free, or on a Dask cluster with --scheduler, it runs faster)"
    )


#: Priorities of a :class:`Pool`'s work (lower first): fits on the longest chain (refits and the held-out fits
#: they lead to), fits every candidate waits for, and evidence that is only read at the end.
CHAIN, SHARED, FILLER = 0, 1, 2

#: Prefix of the shared-memory segments' names (``/dev/shm/magcal_<pid>_<hex>`` on Linux).
SEGMENT_PREFIX = "magcal_"
#: A segment's whole name: the prefix, the number of the process that made it, 16 hex digits.
SEGMENT_NAME = re.compile(re.escape(SEGMENT_PREFIX) + r"(?P<pid>[0-9]+)_[0-9a-f]+")


def cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _workers(n_calls=None, cap=MAX_THREADS):
    workers = PARALLEL_FITS or min(cores(), cap)
    return workers if n_calls is None else min(n_calls, workers)


def in_parallel(calls, pool=None):
    """The results of ``calls`` (functions of no argument), in order, run on up to :data:`PARALLEL_FITS` threads,
    and, with ``pool``, on no more than the pool has workers (a diagnosis asked to use one core runs them one after
    the other: ``--workers 1`` is one core).

    An exception raised by a call is raised here, after the others have finished.
    """
    workers = _workers(len(calls)) if pool is None else min(_workers(len(calls)), max(1, int(pool.workers)))
    if workers <= 1:
        return [call() for call in calls]
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="magcal-fit") as pool:
        return list(pool.map(lambda call: call(), calls))


def own_effects(*things) -> bool:
    """Whether every effect of the given models (or effect classes) is magcal's own: a worker process can import
    its class (a user's effects file cannot be imported there)."""
    for thing in things:
        if isinstance(thing, type):
            if not thing.__module__.startswith("magcal."):
                return False
            continue
        for e in getattr(thing, "effects", ()) or ():
            if not type(e).__module__.startswith("magcal."):
                return False
    return True


#: What a diagnosis says when a scheduler was given but a user's effect keeps its fits here.
ELSEWHERE_NOTE = (
    "the diagnosis's fits ran on this machine, not on the Dask cluster: a candidate effect comes from your own "
    "effects file, whose classes the cluster's workers cannot load"
)


def backend_for(dataset, workers=None, scheduler=None, effects=(), readings=None) -> str:
    """``"dask"``, ``"processes"`` or ``"threads"``: where a diagnosis of ``dataset`` runs its fits.

    A scheduler means Dask, unless an effect is not magcal's own (a user's effects file: the cluster's workers
    could not unpickle its class; :data:`ELSEWHERE_NOTE`), which keeps the fits on this machine's threads.
    Otherwise :data:`BACKEND` when set; else processes when there is more than one worker, the record holds at
    least :data:`PROCESS_MIN_READINGS` readings (:data:`PROCESS_MIN_READINGS_MANY` with :data:`MANY_WORKERS` workers
    or more) and every effect is magcal's own (:func:`own_effects`: ``effects``, models or effect classes); threads
    otherwise. Without a dataset, ``readings`` (sensors x samples, an estimate: the file is not read yet) decides.
    """
    if scheduler is not None:
        return "dask" if own_effects(*effects) else "threads"
    mine = own_effects(*effects) and not _in_daemon()
    if BACKEND is not None:
        return BACKEND if (BACKEND == "threads" or mine) else "threads"
    workers = _workers(cap=MAX_PROCESSES) if workers is None else int(workers)
    if dataset is not None:
        readings = dataset.n_sensors * dataset.n_samples
    if workers <= 1 or readings is None or not mine:
        return "threads"
    least = PROCESS_MIN_READINGS_MANY if workers >= MANY_WORKERS else PROCESS_MIN_READINGS
    return "processes" if readings >= least else "threads"


def _in_daemon() -> bool:
    """Whether this is a daemonic process (a worker of another pool), which may not start processes."""
    import multiprocessing

    return bool(multiprocessing.current_process().daemon)


# -- the readings in shared memory ----------------------------------------------------------------------------------
_ALIGN = 64


def _aligned(n: int) -> int:
    return (n + _ALIGN - 1) // _ALIGN * _ALIGN


#: Where POSIX shared memory lives on Linux (a tmpfs; Docker gives a container 64 MB of it unless told more).
SHM_DIR = "/dev/shm"


def shared_memory_free_bytes():
    """Bytes free where the shared-memory segments live (:data:`SHM_DIR`), or None where that cannot be read."""
    try:
        st = os.statvfs(SHM_DIR)
    except (OSError, AttributeError):
        return None
    return st.f_bavail * st.f_frsize


def remove_stale_segments() -> str | None:
    """Unlink the shared-memory segments of diagnoses whose process no longer runs (killed outright, their
    resource tracker with them: nothing else would ever remove them), and the run folders of processes of magcal
    killed with their fork server (:func:`magcal.core.leftovers.remove_stale_run_dirs`); returns the line that says
    what was removed, or None (:func:`magcal.core.leftovers.remove_stale`)."""
    segments = leftovers.removed_text(
        leftovers.remove_stale(SHM_DIR, SEGMENT_NAME), "shared-memory segment", "diagnosis"
    )
    folders = leftovers.removed_text(leftovers.remove_stale_run_dirs(), "temporary folder", "run of magcal")
    return "; ".join(x for x in (segments, folders) if x) or None


class SharedMemoryFull(MagcalError):
    """The shared memory has no room for the record (:class:`SharedDataset`); the fits stay on threads."""

    def __init__(self, needed: int, free):
        self.needed, self.free = int(needed), free
        room = "too little" if free is None else _megabytes(free)
        super().__init__(
            f"the diagnosis ran its fits on threads, not in worker processes: those share the record through shared "
            f"memory ({SHM_DIR}), which has {room} free where the record needs {_megabytes(needed)} (in a "
            "container, give it more, e.g. docker run --shm-size=2g)"
        )


def _megabytes(nbytes) -> str:
    return f"{nbytes / 1e6:,.0f} MB" if nbytes >= 10e6 else f"{nbytes / 1e6:.2g} MB"


class SharedDataset:
    """A dataset's arrays in one shared-memory segment, written once, for worker processes to map read-only.

    The segment starts with the dataset's other fields and the arrays' layout (pickled, a few hundred bytes), then
    the arrays themselves, each aligned to 64 bytes. :meth:`close` unlinks it (also on leaving a ``with``).

    The segment's pages are reserved as it is made (``posix_fallocate``), so that a shared memory too small for it
    (a container's 64 MB ``/dev/shm``) raises :class:`SharedMemoryFull` here; written without, the first page past
    the room would have killed the process with a bus error.

    Parameters
    ----------
    dataset : Dataset

    Raises
    ------
    SharedMemoryFull
        The shared memory has no room for the record.
    """

    def __init__(self, dataset):
        from multiprocessing import shared_memory

        arrays, fields, extra = {}, {}, {}
        for f in dataclasses.fields(dataset):
            value = getattr(dataset, f.name)
            if f.name == "extra":
                for key, a in value.items():
                    if isinstance(a, np.ndarray) and a.dtype.kind != "O":
                        arrays[f"extra/{key}"] = a
                    else:
                        extra[key] = a
            elif isinstance(value, np.ndarray) and value.dtype.kind != "O":
                arrays[f.name] = value
            else:
                fields[f.name] = value
        fields["extra"] = extra
        layout, offset = [], 0
        for key, a in arrays.items():
            layout.append((key, offset, a.shape, a.dtype.str))
            offset += _aligned(a.nbytes)
        header = pickle.dumps((fields, layout), protocol=pickle.HIGHEST_PROTOCOL)
        start = _aligned(8 + len(header))
        self.name = f"{SEGMENT_PREFIX}{os.getpid()}_{uuid.uuid4().hex[:16]}"
        self.nbytes = start + offset
        free = shared_memory_free_bytes()
        if free is not None and free < self.nbytes:
            self._shm = None
            raise SharedMemoryFull(self.nbytes, free)
        self._shm = shared_memory.SharedMemory(name=self.name, create=True, size=max(self.nbytes, 1))
        try:
            fd = getattr(self._shm, "_fd", -1)  # POSIX: the segment's file; reserve its pages now
            if fd >= 0 and hasattr(os, "posix_fallocate"):
                try:
                    os.posix_fallocate(fd, 0, max(self.nbytes, 1))
                except OSError as exc:
                    if exc.errno not in (errno.ENOSPC, errno.ENOMEM):
                        raise
                    raise SharedMemoryFull(self.nbytes, shared_memory_free_bytes()) from None
            buf = self._shm.buf
            buf[:8] = len(header).to_bytes(8, "little")
            buf[8 : 8 + len(header)] = header
            for (_, off, shape, dtype), a in zip(layout, arrays.values()):
                view = np.ndarray(shape, dtype, buffer=buf, offset=start + off)
                view[...] = a
                del view  # no view may outlive the segment's mapping
        except BaseException:
            self.close()
            raise

    def close(self):
        """Unmap and unlink the segment (once; later calls do nothing)."""
        shm, self._shm = self._shm, None
        if shm is not None:
            try:
                shm.close()
            finally:
                shm.unlink()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


#: The segments this worker process has mapped: name -> (segment, dataset). One at a time: a worker serves one
#: diagnosis.
_ATTACHED: dict = {}
#: Subsets of an attached or scattered dataset by mask (a worker's kept samples), the most recent few, held so that
#: :meth:`~magcal.data.dataset.Dataset.masked` gives the same one to the next task: id -> dataset.
_SUBSETS: dict = {}


def attach(name):
    """The dataset in shared-memory segment ``name`` (:class:`SharedDataset`), mapped read-only once per process."""
    hit = _ATTACHED.get(name)
    if hit is not None:
        return hit[1]
    from multiprocessing import shared_memory

    _ATTACHED.clear()
    _SUBSETS.clear()
    shm = shared_memory.SharedMemory(name=name)
    n = int.from_bytes(bytes(shm.buf[:8]), "little")
    fields, layout = pickle.loads(bytes(shm.buf[8 : 8 + n]))
    start = _aligned(8 + n)
    extra = dict(fields.pop("extra"))
    for key, off, shape, dtype in layout:
        a = np.ndarray(shape, dtype, buffer=shm.buf, offset=start + off)
        a.flags.writeable = False  # the dataset keeps a read-only array as it is: no copy
        if key.startswith("extra/"):
            extra[key[len("extra/") :]] = a
        else:
            fields[key] = a
    dataset = Dataset(**fields, extra=extra)
    _ATTACHED[name] = (shm, dataset)
    return dataset


def subset(dataset, mask):
    """``dataset`` restricted to ``mask`` (None: all of it), made once per worker for the same mask
    (:meth:`~magcal.data.dataset.Dataset.masked`, held here between tasks)."""
    if mask is None:
        return dataset
    kept = dataset.masked(mask)
    _SUBSETS.pop(id(kept), None)
    _SUBSETS[id(kept)] = kept  # the most recent last
    while len(_SUBSETS) > 4:
        _SUBSETS.pop(next(iter(_SUBSETS)))
    return kept


def _portable(result):
    """A task's result as it travels back: a fit without its ``problem`` (which holds the dataset)."""
    if dataclasses.is_dataclass(result) and any(f.name == "problem" for f in dataclasses.fields(result)):
        return dataclasses.replace(result, problem=None)
    return result


_LIMITS = None


#: Environment variables that set the BLAS and OpenMP threads of a library loaded after them.
_ONE_THREAD = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def _init_worker(owner_pid=None):
    """A worker process's start: it ends when ``owner_pid`` (the process that started its pool) ends
    (:func:`magcal.core.leftovers.exit_with`: a diagnosis killed outright leaves no worker, and then no fork
    server nor resource tracker, behind); BLAS on one thread (the workers share the cores): the libraries loaded
    so far (numpy's) limited by threadpoolctl, and those loaded later (scipy's own OpenBLAS) by the
    environment."""
    global _LIMITS
    if owner_pid is not None:
        leftovers.exit_with(owner_pid)
    from threadpoolctl import threadpool_limits

    # a fork server started by Dask passes on its MALLOC_TRIM_THRESHOLD_; and a large record's temporaries (above
    # 32 MB) are served from the heap, not each a fresh mmap faulted in page by page
    memory.keep_large_blocks(every_size=True)
    for name in _ONE_THREAD:
        os.environ[name] = "1"
    import scipy.linalg  # noqa: F401  (its BLAS loaded now, so that the limit below reaches it too)

    _LIMITS = threadpool_limits(limits=1)


def _process_task(name, fn, args):
    return _portable(fn(attach(name), *args))


def _dask_task(fn, dataset, args):
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        return _portable(fn(dataset, *args))


def _ready(*functions):
    """Nothing: a worker's first task, whose functions (unpickled, so their modules imported) warm it up."""
    return os.getpid()


_MAIN_LOCK = threading.Lock()


@contextlib.contextmanager
def _main_left_alone():
    """While worker processes start: the caller's script is not run again in them.

    ``spawn`` (and the fork server, for each worker it forks) runs the ``__main__`` script again in every new
    process (as ``__mp_main__``), which a script without
    an ``if __name__ == "__main__":`` guard does not survive (it would start its own diagnosis there). The workers
    only run magcal's functions on magcal's objects (:func:`own_effects`), so they do not need the script: its
    file and spec are hidden from :mod:`multiprocessing` while the processes are started, then put back."""
    main = sys.modules.get("__main__")
    with _MAIN_LOCK:
        saved = {k: main.__dict__[k] for k in ("__file__", "__spec__") if main is not None and k in main.__dict__}
        try:
            if main is not None:
                main.__dict__.pop("__file__", None)
                if "__spec__" in saved:
                    main.__spec__ = None
            yield
        finally:
            if main is not None:
                main.__dict__.update(saved)


#: Modules the fork server imports once, before it forks the workers (:func:`process_context`): those of the
#: workers' tasks and what their start needs; :mod:`magcal.core.leftovers` first, which has the server remove the
#: run folder as it ends.
WORKER_MODULES = (
    "magcal.core.leftovers",
    "threadpoolctl",
    "scipy.linalg",
    "magcal.diagnosis.scores",
    "magcal.diagnosis.verdict",
)


def process_context():
    """The :mod:`multiprocessing` context of the worker processes: ``forkserver`` where the platform has it, else
    ``spawn``.

    ``spawn`` starts every worker as a new interpreter that imports numpy, scipy and magcal (1.2 s and 1.4 s of a
    core each on the 2-core development machine, for every pool); a fork server imports them once per program (the
    first pool, 1.2 s) and then forks each worker in milliseconds (a second pool of two workers ready in 0.03 s;
    the workers' processor time 0.06 s against 2.9 s). Forking the fork server is safe where forking this process
    would not be (it runs no thread of ours: the workbench's, the pool's, BLAS's). A program that has already
    started the fork server with other modules keeps it; ours are then imported by each worker's first task."""
    import multiprocessing

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(WORKER_MODULES))
    return ctx


def start_workers(dataset=None, workers=None, scheduler=None, effects=(), readings=None) -> bool:
    """Start now, in the background, what a diagnosis of ``dataset`` will fork its worker processes from.

    The fork server (:func:`process_context`) imports numpy, scipy and magcal once per program: 0.8-1.0 s on the
    2-core development machine before the first pool's first worker can start, time the diagnosis would otherwise
    spend waiting. The workbench calls this when a session opens a record: those imports then run while the user
    looks at the page, and the first Diagnose finds the server ready (first worker in 0.03 s instead of 0.8 s).
    ``magcal diagnose`` calls it before it reads the file, with ``readings`` estimated from the file's size, so
    that the imports run beside the reading (started only as the calibration began, its BLAS threads shared the
    cores with them: on 2 cores the calibration 0.6 -> 1.45 s for 1 s gained in the diagnosis;
    ``benchmarks/process_start.py --parts early,cli``).

    Does nothing (and returns False) where the diagnosis would run its fits on threads or a Dask cluster
    (:func:`backend_for` with the same arguments), or where the platform has no fork server; starting it twice
    starts it once.

    Returns
    -------
    bool
        Whether the fork server is running (started now or before).
    """
    if backend_for(dataset, workers, scheduler, effects, readings) != "processes":
        return False
    return start_fork_server()


def start_fork_server(preload=WORKER_MODULES) -> bool:
    """Start this program's fork server (:func:`process_context`) with ``preload`` imported in it, unless it runs
    already; returns whether it runs (False: the platform has none).

    The server removes the run folder (:func:`magcal.core.leftovers.run_dir`) as it ends, when ``preload`` starts
    with :mod:`magcal.core.leftovers`. A Dask local cluster started afterwards with the ``forkserver`` method
    forks its workers from it too (``magcal apply``).
    """
    if process_context().get_start_method() != "forkserver":
        return False
    import multiprocessing
    from multiprocessing import forkserver

    multiprocessing.get_context("forkserver").set_forkserver_preload(list(preload))
    # the server would otherwise import the caller's script (see there), and start BLAS's threads for every core
    with _main_left_alone(), _one_thread_environment():
        forkserver.ensure_running()  # a few milliseconds: the server imports its modules in its own process
    return True


def one_blas_thread(active=True):
    """BLAS (and OpenMP) on one thread in this process while the block runs, when ``active``
    (:func:`magcal.core.blas.one_blas_thread`: one limit for the whole process, shared with the fits).

    A diagnosis's pool runs its fits side by side, on its threads or in worker processes that already run one BLAS
    thread each (:func:`_init_worker`); the calling process's own BLAS calls (the pool's threads, the score tests'
    and the evidence's matrix products) would otherwise each start one thread per core on cores the fits already
    keep busy. With one worker (``workers=1``) the diagnosis runs on the one core asked for.

    Measured on the 2-core development machine (``benchmarks/process_start.py --parts blas``, quiet): 4 x 5e4
    samples on two threads 3.55 s with OpenBLAS's default threads, 1.98 s with one; 4 x 1e5 on two worker processes
    4.14 s against 3.64 s (the calling process's processor time 3.49 s against 1.87 s); on one core 6.03 s (using
    both cores) against 5.13 s.
    """
    return blas.one_blas_thread(active)


_ENV_LOCK = threading.Lock()


@contextlib.contextmanager
def _one_thread_environment():
    """While the worker processes (and the fork server) start: BLAS and OpenMP told to use one thread, so that the
    libraries they load start that way, and the fork server told the run folder it removes as it ends
    (:func:`magcal.core.leftovers.fork_server_environment`); this process's own settings are put back after."""
    with _ENV_LOCK:
        told = {name: "1" for name in _ONE_THREAD} | leftovers.fork_server_environment()
        saved = {name: os.environ.get(name) for name in told}
        os.environ.update(told)
        try:
            yield
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value


class _Executor(ProcessPoolExecutor):
    """:class:`~concurrent.futures.ProcessPoolExecutor` whose every worker process starts with the caller's script
    hidden (:func:`_main_left_alone`) and BLAS told one thread (:func:`_one_thread_environment`).

    The executor does not start its workers all at once: a task submitted while one is idle starts none, so some
    start later, when a task of the diagnosis finds every worker busy (seen with 16 workers: a worker had finished
    its first task before the last was asked for). Those late starts need the same care as the first: a script
    without a ``__main__`` guard was otherwise run again in them. The executor starts each worker in its
    ``_spawn_process`` (CPython 3.9 and later); tests/diagnosis/test_parallel_scale_out.py checks every start.
    """

    def _spawn_process(self):
        with _main_left_alone(), _one_thread_environment():
            super()._spawn_process()


class _Processes:
    """Worker processes (:func:`process_context`) sharing one :class:`SharedDataset`."""

    def __init__(self, dataset, workers, warm=()):
        self.workers = int(workers)
        self.shared = SharedDataset(dataset)
        try:
            self.executor = _Executor(
                max_workers=self.workers,
                mp_context=process_context(),
                initializer=_init_worker,
                initargs=(os.getpid(),),  # each worker ends when this process does, however it ends
            )
            for _ in range(self.workers):  # workers start now, while the score tests run (some later: _Executor)
                self.executor.submit(_ready, *warm)
        except BaseException:
            self.shared.close()
            raise

    def submit(self, fn, args) -> Future:
        return self.executor.submit(_process_task, self.shared.name, fn, args)

    def close(self, cancel=False):
        try:
            self.executor.shutdown(wait=True, cancel_futures=cancel)
        finally:
            self.shared.close()


#: Seconds to wait for a Dask scheduler.
CONNECT_TIMEOUT_S = 10.0


class _Dask:
    """A ``dask.distributed`` cluster (an address or a Client); the dataset scattered to every worker once."""

    def __init__(self, dataset, scheduler):
        try:
            import distributed
        except ImportError:
            raise MagcalError(
                'a diagnosis on Dask needs dask.distributed: pip install "magcal-workbench[survey]"'
            ) from None
        self._own = not isinstance(scheduler, distributed.Client)
        if self._own:
            try:
                self.client = distributed.Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
            except (OSError, TimeoutError) as exc:
                raise MagcalError(
                    f"--scheduler {scheduler}: cannot reach the Dask scheduler within {CONNECT_TIMEOUT_S:g} s "
                    f"({exc}); is it running, and is the address right?"
                ) from None
        else:
            self.client = scheduler
        try:
            self.data = self.client.scatter(dataset, broadcast=True, hash=False)
            self.workers = max(1, sum(self.client.nthreads().values()))
        except BaseException:
            self.close()
            raise

    def submit(self, fn, args) -> Future:
        out: Future = Future()
        out.set_running_or_notify_cancel()

        def done(f):
            try:
                out.set_result(f.result())
            except BaseException as exc:
                out.set_exception(exc)

        self.client.submit(_dask_task, fn, self.data, args, pure=False).add_done_callback(done)
        return out

    def close(self, cancel=False):
        data, self.data = getattr(self, "data", None), None
        if data is not None:
            try:
                data.release()
            except Exception:  # the cluster is gone: nothing to release
                pass
        if self._own:
            self.client.close()


class Pool:
    """Threads that run submitted calls by priority, then in the order submitted; with a dataset, the fits
    handed to :meth:`remote` run in worker processes or on a Dask cluster (module docstring).

    A call may submit further calls (its follow-ups). With one thread and no workers every call runs at once, in
    the caller's thread, at :meth:`submit`. Use as a context manager: leaving it waits for every call submitted,
    then stops the workers and unlinks the shared memory.

    Parameters
    ----------
    dataset : Dataset, optional
        The record the remote fits receive as their first argument.
    scheduler : str or distributed.Client, optional
        A Dask scheduler's address (``tcp://host:8786``) or a client: the fits run on that cluster.
    effects : sequence, optional
        Models or effect classes the fits will use (:func:`backend_for`: a user's effect keeps them on threads).
    warm : sequence of functions, optional
        The remote functions to come: worker processes import their modules as they start.
    workers : int, optional
        Threads or worker processes (default :data:`PARALLEL_FITS`, else one per core).
    """

    def __init__(self, dataset=None, scheduler=None, effects=(), warm=(), workers=None):
        asked = workers
        self.dataset = dataset
        self.backend = (
            "threads" if dataset is None and scheduler is None else backend_for(dataset, workers, scheduler, effects)
        )
        self._remote = None
        #: What the pool says to the user, or None: fewer workers than asked for, for want of memory.
        self.note = None
        #: What the pool removed as it started, or None: segments of diagnoses killed before they could unlink
        #: them (:func:`remove_stale_segments`).
        self.removed = remove_stale_segments() if dataset is not None else None
        if dataset is not None and self.backend != "dask":
            wanted = workers or _workers(cap=MAX_PROCESSES if self.backend == "processes" else MAX_THREADS)
            workers, self.note = workers_for_memory(dataset, wanted, self.backend)
            if self.note and self.backend == "processes" and workers < 2:
                self.backend = "threads"  # room for one fit at a time: in this process
        self._blas = contextlib.ExitStack()
        self._queue: queue.PriorityQueue = queue.PriorityQueue()
        self._order = itertools.count()
        self._threads: list = []
        self.concurrent = False
        try:  # a pool half made (a worker that does not start, no thread left) is closed again: nothing leaks
            if self.backend == "processes":
                try:
                    self._remote = _Processes(dataset, workers or _workers(cap=MAX_PROCESSES), warm)
                except SharedMemoryFull as full:  # the fits run here instead, and the diagnosis says why
                    self.backend, self.note = "threads", str(full)
                    workers = asked or min(workers, _workers())
            elif self.backend == "dask":
                self._remote = _Dask(dataset, scheduler)
            # with workers elsewhere, enough threads here to keep each busy and still run the local work
            threads = (workers or _workers()) if self._remote is None else self._remote.workers + 2
            self.workers = threads if self._remote is None else self._remote.workers
            # the fits side by side here or in this machine's worker processes (or one after the other on the one
            # core asked for): this process's BLAS on one thread while the pool lives
            self._blas.enter_context(one_blas_thread(self.backend != "dask"))
            #: Whether submitted calls run beside the caller (on threads), not at once in its thread: work that may
            #: turn out unneeded is worth handing over ahead only then.
            self.concurrent = threads > 1
            if threads > 1:
                for k in range(threads):
                    thread = threading.Thread(target=self._work, name=f"magcal-fit_{k}", daemon=True)
                    thread.start()
                    self._threads.append(thread)
        except BaseException:
            self.close(cancel=True)
            raise

    def submit(self, call, priority=CHAIN) -> Future:
        """A :class:`~concurrent.futures.Future` of ``call()`` (a function of no argument)."""
        future: Future = Future()
        if not self._threads:
            _run(call, future)
        else:
            self._queue.put((priority, next(self._order), call, future))
        return future

    def remote_future(self, fn, *args, local=None) -> Future:
        """A Future of ``fn(dataset, *args)`` run by a worker (``fn`` a module-level function, its arguments
        picklable); without workers, of ``local()`` (or ``fn(dataset, *args)``) run here, at once."""
        if self._remote is not None:
            return self._remote.submit(fn, args)
        future: Future = Future()
        _run(local if local is not None else (lambda: fn(self.dataset, *args)), future)
        return future

    def remote(self, fn, *args, local=None):
        """``fn(dataset, *args)`` run by a worker and waited for (:meth:`remote_future`)."""
        return self.remote_future(fn, *args, local=local).result()

    @property
    def is_remote(self) -> bool:
        """Whether the fits run in other processes (or on a cluster)."""
        return self._remote is not None

    def _work(self):
        while True:
            _, _, call, future = self._queue.get()
            if call is None:
                return
            _run(call, future)

    def close(self, cancel=False):
        """Wait for every call submitted, then stop the threads and the workers; with ``cancel``, calls not yet
        started are cancelled instead (their futures raise :class:`~concurrent.futures.CancelledError`)."""
        try:
            if cancel:
                while True:
                    try:
                        *_, future = self._queue.get_nowait()
                    except queue.Empty:
                        break
                    future.cancel()
            for _ in self._threads:
                self._queue.put((FILLER + 1, next(self._order), None, None))
            for thread in self._threads:
                thread.join()
            self._threads = []
        finally:
            remote, self._remote = self._remote, None
            try:
                if remote is not None:
                    remote.close(cancel)
            finally:
                self._blas.close()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.close(cancel=exc_type is not None)  # after an error (or Ctrl-C) nothing more is started


def _run(call, future):
    if future.set_running_or_notify_cancel():
        try:
            future.set_result(call())
        except BaseException as exc:
            future.set_exception(exc)
