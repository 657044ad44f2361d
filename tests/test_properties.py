"""Property-based tests (hypothesis): the Fortran lists equal the NumPy brute force on arbitrary small sets."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import arpy
from arpy.reference import brute_force_pairs
from conftest import points_with_ties


@st.composite
def particle_sets(draw):
    x = points_with_ties(draw, bound=4.0, n_min=0, n_max=60, pool_max=12)
    n = len(x)
    per_particle = draw(st.booleans())
    radii = st.floats(min_value=1e-3, max_value=3.0, allow_nan=False)
    rc = draw(arrays(np.float64, (n,), elements=radii)) if per_particle else draw(radii)
    skin = draw(st.sampled_from([0.0, 0.1]))
    return x, rc, skin


@settings(deadline=None)                 # examples: the profile (tests/conftest.py)
@given(particle_sets(), st.sampled_from(["brute", "cell"]), st.booleans())
def test_lists_match_numpy_brute_force(case, method, full):
    x, rc, skin = case
    nl = arpy.neighbor_list(x, rc, method=method, full=full, skin=skin)
    i, j = nl.pairs()
    ei, ej = brute_force_pairs(x, rc, skin)
    np.testing.assert_array_equal(i, ei)
    np.testing.assert_array_equal(j, ej)
    assert len(nl) == ei.size * (2 if full else 1)


def _fsum_or_error(values):
    import math

    try:
        return math.fsum(list(values)), None
    except (OverflowError, ValueError) as err:
        return None, type(err)


@settings(deadline=None)
@given(st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e3, 1e3),
                          st.sampled_from([1.0, -1.0, 2.0 ** -53, -(2.0 ** -53), 2.0 ** -105, 1e308, -1e308,
                                           0.0, -0.0, 5e-324])), max_size=60))
def test_exact_sum_is_math_fsum(values):
    """arpy.distributed.exact_sum of one process (the core's exact partials for finite terms) gives
    math.fsum's value, the sign of a zero included, and math.fsum's answer (or error) for non-finite
    terms and overflow."""
    from arpy.distributed import exact_sum

    def fsum(v):
        return exact_sum(None, v)

    want, err = _fsum_or_error(values)
    if err is not None:
        try:
            fsum(np.array(values, dtype=np.float64))
        except err:
            return
        raise AssertionError(f"expected {err.__name__}")
    got = fsum(np.array(values, dtype=np.float64))
    if np.isnan(want):
        assert np.isnan(got)
    else:
        assert got == want and np.copysign(1.0, got) == np.copysign(1.0, want)
