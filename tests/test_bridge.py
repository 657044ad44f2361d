"""The one bridge to the Fortran core (arpy._bridge): points cross to the core without a copy.

f2py passes an array argument to Fortran as it is when its type and order conform, and copies it
otherwise.  Positions are C-ordered float64 (n, d) in Python and ``x(d, n)`` in the core: their
transposed view is Fortran-ordered, so it conforms.  NumPy reports its allocations to tracemalloc,
a copy by f2py among them, so the peak traced during a call shows whether the points were copied.
"""

from __future__ import annotations

import tracemalloc

import numpy as np

from arpy import _bridge


def _peak(fn) -> int:
    """The peak of the memory NumPy and Python allocate during fn() (bytes)."""
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_c_ordered_positions_reach_the_core_without_a_copy():
    x = np.random.default_rng(0).random((400_000, 3))
    view = _bridge.core_view(x)
    assert view.shape == (3, x.shape[0]) and view.flags.f_contiguous and np.shares_memory(view, x)
    small = x.nbytes // 20
    assert _peak(lambda: _bridge.column_extremes(x)) < small
    assert _peak(lambda: _bridge.knn(x, x[:10], 2, np.zeros(3))) < small
    assert _peak(lambda: _bridge.min_distance(x[:5000], np.zeros(3))) < small
    # the measurement sees a copy: f2py copies a C-ordered (d, n) array into Fortran order
    assert _peak(lambda: _bridge._core.arpy_column_extremes(np.ascontiguousarray(x.T))) >= x.nbytes


def test_points_come_back_as_c_ordered_rows():
    """Points the core returns as (d, m) come back as (m, d) C-ordered views, not copies."""
    a = np.asfortranarray(np.arange(12.0).reshape(3, 4))          # as f2py returns a (d, m) result
    rows = _bridge.from_core(a)
    assert rows.shape == (4, 3) and rows.flags.c_contiguous and np.shares_memory(rows, a)
