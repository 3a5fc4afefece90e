"""BLAS on one thread while a block runs (magcal.core.blas), and the large fits that hold it."""

import threading

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from magcal.core import blas


def _blas_threads() -> set:
    return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}


@pytest.fixture
def two_threads():
    """BLAS on two threads around the test (the default of a 2-core machine), whatever this machine has."""
    if not _blas_threads():
        pytest.skip("no BLAS library that threadpoolctl can limit")
    with threadpool_limits(limits=2):
        assert _blas_threads() == {2}
        yield


def test_one_thread_inside_the_block_and_the_setting_put_back(two_threads):
    with blas.one_blas_thread():
        assert _blas_threads() == {1}
        assert blas.holders() == 1
    assert _blas_threads() == {2}
    assert blas.holders() == 0
    with blas.one_blas_thread(active=False):
        assert _blas_threads() == {2}


def test_a_second_user_leaving_first_keeps_the_limit_until_the_last_leaves(two_threads):
    """A fit and a diagnosis at once (the diagnosis's limit is the same one): the first to leave must not lift the
    other's limit, and the last puts back the process's own setting (two separate limiters would leave one thread
    behind). The last to leave is this (the main) thread: OpenBLAS ignores a thread count set from another thread
    once the main thread has set one (see :mod:`magcal.core.blas`)."""
    from magcal.diagnosis._parallel import one_blas_thread as diagnosis_limit

    seen = []

    def other():
        with diagnosis_limit():
            seen.append((blas.holders(), _blas_threads()))

    with blas.one_blas_thread():
        worker = threading.Thread(target=other)
        worker.start()
        worker.join(10)
        assert seen == [(2, {1})]
        assert blas.holders() == 1
        assert _blas_threads() == {1}  # still held here
    assert _blas_threads() == {2}
    assert blas.holders() == 0


def test_a_large_fit_runs_on_one_blas_thread_and_a_small_one_as_set(two_threads, monkeypatch):
    from magcal.data.simulation import chi2017_truth, simulate
    from magcal.fitting import fitter

    during = []
    equations = fitter.Problem.normal_equations

    def spy(self, *args, **kwargs):
        during.append((self.n_samples, _blas_threads()))
        return equations(self, *args, **kwargs)

    monkeypatch.setattr(fitter.Problem, "normal_equations", spy)
    limit = fitter.ONE_BLAS_THREAD_READINGS
    large = simulate(chi2017_truth(4), n_samples=limit // 4 + 10, noise_nT=3.0, seed=2)
    result = fitter.fit(large)
    assert result.success and during and all(threads == {1} for _, threads in during)
    assert _blas_threads() == {2}
    during.clear()
    small = simulate(chi2017_truth(4), n_samples=limit // 8, noise_nT=3.0, seed=2)
    mask = np.ones(small.n_samples, bool)
    fitter.fit(small, mask=mask)
    assert during and all(threads == {2} for _, threads in during)
