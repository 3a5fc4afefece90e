"""Row-wise vector operations (magcal.core.rows) against numpy's general forms."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from magcal.core.rows import basis_times, cross_rows, row_norm, unit_rows

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)


@pytest.mark.parametrize("shape", [(3,), (7, 3), (4, 5, 3), (0, 3)])
def test_row_norm_is_numpys_norm_over_the_last_axis(shape):
    v = np.random.default_rng(0).normal(0, 5e4, shape)
    np.testing.assert_allclose(row_norm(v), np.linalg.norm(v, axis=-1), rtol=1e-15, atol=0)


@settings(max_examples=50, deadline=None)
@given(a=arrays(float, (6, 3), elements=finite), b=arrays(float, (6, 3), elements=finite))
def test_cross_rows_is_numpys_cross(a, b):
    expected = np.cross(a, b)
    np.testing.assert_allclose(cross_rows(a, b), expected, rtol=1e-12, atol=1e-12 * (1 + np.abs(expected).max()))


def test_cross_rows_broadcasts_one_vector_against_many():
    a = np.random.default_rng(1).normal(size=(5, 3))
    np.testing.assert_allclose(cross_rows(a, [0.0, 0.0, 1.0]), np.cross(a, [0.0, 0.0, 1.0]))


def test_unit_rows_have_unit_length_and_keep_direction():
    v = np.random.default_rng(2).normal(0, 3e4, (50, 3))
    u = unit_rows(v)
    np.testing.assert_allclose(row_norm(u), 1.0, rtol=1e-15)
    np.testing.assert_allclose(np.sum(u * v, axis=1), row_norm(v), rtol=1e-12)


@pytest.mark.parametrize("n, q", [(0, 3), (1, 1), (500, 3), (500, 12)])
def test_basis_times_is_numpys_batched_matmul(n, q):
    rng = np.random.default_rng(n + q)
    basis, theta = rng.normal(size=(n, 3, q)), rng.normal(size=q)
    np.testing.assert_allclose(basis_times(basis, theta), basis @ theta, rtol=1e-12, atol=1e-12)
    view = rng.normal(size=(2 * n, 3, q))[::2]  # a strided view of rows, as an effect's cached basis may be
    np.testing.assert_allclose(basis_times(view, theta), view @ theta, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("axes", [[0, 1, 2], [0, 1], [2, 0, 1, 0, 1, 2]])
def test_basis_times_of_a_single_axis_basis_is_the_dense_product(axes):
    from magcal.model.terms import SingleAxisBasis

    rng = np.random.default_rng(len(axes))
    basis = SingleAxisBasis(rng.normal(size=(50, len(axes))), axes)
    theta = rng.normal(size=len(axes))
    dense = np.asarray(basis).copy()
    np.testing.assert_allclose(basis_times(basis, theta), dense @ theta, rtol=1e-13, atol=1e-12)
    assert basis[3:7].axes is None  # a view is a plain basis


@pytest.mark.parametrize("axes", [[0, 1, 2], [2, 0, 1, 0, 1, 2]])
def test_a_copied_single_axis_basis_keeps_its_axes(axes):
    """Effects are deep-copied with their cached bases (every fit copies its model): the copy keeps the axes, so
    the fitter still projects it by products, and equals the original; a view copies to a plain array."""
    import copy

    from magcal.model.terms import SingleAxisBasis

    basis = SingleAxisBasis(np.random.default_rng(1).normal(size=(20, len(axes))), axes)
    clone = copy.deepcopy(basis)
    assert isinstance(clone, SingleAxisBasis) and clone.axes.tolist() == list(axes)
    np.testing.assert_array_equal(clone, basis)
    np.testing.assert_array_equal(clone.axis_values, basis.axis_values)
    assert not np.shares_memory(clone, basis)
    view = copy.deepcopy(basis[2:5])
    assert type(view) is np.ndarray
    np.testing.assert_array_equal(view, basis[2:5])
