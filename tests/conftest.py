"""Shared fixtures and helpers: particle sets that stress neighbour searches, a cKDTree
reference for pairs under the min rule, hypothesis profiles and point sets with ties.

Hypothesis profiles (the property tests in test_properties.py and test_ar_cells.py
set only ``deadline=None``; the number of examples comes from the profile):

* ``ci`` (the default): ``derandomize=True`` -- the examples are drawn from a seed
  fixed by each test's source, so every run (CI, a developer, a re-run) tests the
  same examples, and no example database is read or written; 150 examples per test.
* ``long``: fresh random examples on every run, 3000 per test, with the example
  database in .hypothesis/ (a failing example is replayed first next time).  Ask
  for it with ``ARPY_HYPOTHESIS=long``::

      ARPY_HYPOTHESIS=long bash .ci/setup test -k "properties"

``ARPY_HYPOTHESIS`` may name any registered profile; pytest's own
``--hypothesis-profile NAME`` overrides it.
"""

from __future__ import annotations

import os

# one thread per test worker (pytest-xdist runs one worker per core); the tests of threads ask for
# two with arpy.num_threads.  Set before numpy and arpy load their thread pools.
os.environ.setdefault("OMP_NUM_THREADS", "1")
# a team of two on cores the other workers keep busy: its threads wait at the loops' barriers asleep,
# not spinning (spinning made the two-thread runs of test_threads 10 to 30 times slower there)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial import cKDTree

settings.register_profile("ci", derandomize=True, database=None, max_examples=150, deadline=None,
                          print_blob=True)
settings.register_profile("long", derandomize=False, max_examples=3000, deadline=None, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("ARPY_HYPOTHESIS", "ci"))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20121121)


def uniform_points(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    """n points uniformly random in [0, 1]^d."""
    return rng.random((n, d))


def clustered_points(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    """n points in a few tight Gaussian clusters plus a sparse background."""
    centres = rng.random((5, d))
    k = rng.integers(0, 5, size=n)
    x = centres[k] + rng.normal(scale=rng.choice([0.003, 0.02, 0.1], size=(n, 1)), size=(n, d))
    x[: n // 10] = rng.random((n // 10, d))
    return x


def points_with_ties(draw, bound: float, n_min: int, n_max: int, pool_max: int) -> np.ndarray:
    """For a hypothesis ``@st.composite`` strategy: n_min..n_max points in d = 2 or 3
    dimensions, coordinates in [-bound, bound], many of them drawn from a pool of at most
    ``pool_max`` values, which makes coincident points and exact ties likely."""
    coords = st.floats(min_value=-bound, max_value=bound, allow_nan=False, allow_infinity=False, width=64)
    d = draw(st.sampled_from([2, 3]))
    n = draw(st.integers(min_value=n_min, max_value=n_max))
    pool = draw(st.lists(coords, min_size=1, max_size=pool_max))
    return draw(arrays(np.float64, (n, d), elements=st.sampled_from(pool) | coords))


def kdtree_pairs(x: np.ndarray, rc, skin: float = 0.0, boxsize=None) -> tuple[np.ndarray, np.ndarray]:
    """Pairs under the min rule |x_p - x_q| <= min(rc_p, rc_q) + skin found with scipy's cKDTree,
    a reference independent of arpy: each particle queries its own radius, and a pair is kept
    once (i < j, sorted) if it also lies within the other particle's radius.  ``boxsize``: a
    periodic box [0, boxsize) (cKDTree's own minimum image)."""
    r = np.broadcast_to(np.asarray(rc, dtype=np.float64), (len(x),)) + skin
    if len(x) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    found = cKDTree(x, boxsize=boxsize).query_ball_point(x, r, return_sorted=False)
    i = np.repeat(np.arange(len(x), dtype=np.int64), [len(f) for f in found])
    j = np.concatenate([np.asarray(f, np.int64) for f in found])
    i, j = i[j > i], j[j > i]
    rm = np.minimum(r[i], r[j])
    e = x[i] - x[j]
    if boxsize is not None:
        e -= boxsize * np.round(e / boxsize)
    keep = (e ** 2).sum(axis=1) <= rm * rm
    order = np.lexsort((j[keep], i[keep]))
    return i[keep][order], j[keep][order]


def lattice_points(d: int, m: int = 9, h: float = 0.125) -> np.ndarray:
    """A Cartesian lattice of spacing h (exact in binary): with cutoff 2h many
    points sit exactly on cell faces, and pair distances equal the cutoff exactly."""
    axis = np.arange(m) * h
    return np.stack(np.meshgrid(*([axis] * d), indexing="ij"), axis=-1).reshape(-1, d)


def fitted_root(extent: float, rc, max_level: int) -> float:
    """The AR root edge D_m that arpy fits to the smallest cutoff (computed here from logarithms,
    then made exact): r 2^K, r the double just above min(rc), K >= 0 the least with r 2^K >= extent;
    the extent itself (max(rc) if 0) when K would exceed max_level."""
    import math

    r = math.nextafter(float(np.min(rc)), math.inf)
    K = max(0, math.ceil(math.log2(extent / r))) if extent > r else 0
    while math.ldexp(r, K) < extent:
        K += 1
    while K > 0 and math.ldexp(r, K - 1) >= extent:
        K -= 1
    if K > max_level:
        return extent if extent > 0 else float(np.max(rc))
    return math.ldexp(r, K)


#: Modules whose tests take longest, in that order.
LONG_FIRST = ("test_simulation.py", "test_cli_and_benchmarks.py", "test_mpi.py", "test_distributed.py",
              "test_burgers.py", "test_surface.py", "test_checkpoint.py", "test_docs.py", "test_typing.py")
#: The module of the tests that run ``mpiexec`` (dealt to one worker).
MPI_MODULE = "test_mpi.py"


def pytest_collection_modifyitems(config, items) -> None:
    """Longest first on every worker.  pytest-xdist's work stealing deals the collected tests out in
    contiguous blocks, one per worker, and an idle worker steals from the end of another's block.  So
    the tests of LONG_FIRST are dealt alternately to the start of each block, the others fill the
    blocks' ends (what is stolen, and what is left over last, is short)."""
    rank = {name: i for i, name in enumerate(LONG_FIRST)}
    long = sorted((item for item in items if item.path.name in rank), key=lambda item: rank[item.path.name])
    rest = [item for item in items if item.path.name not in rank]
    blocks = max(int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")), 1)      # (set in xdist's workers)
    size = -(-len(items) // blocks)                       # the block xdist gives each worker
    # the mpiexec tests all in the first block, one after the other: each runs 2-4 ranks, and two at once
    # on the two workers oversubscribed the cores (ranks waiting on each other's time slices)
    mpi = [item for item in long if item.path.name == MPI_MODULE]
    others = [item for item in long if item.path.name != MPI_MODULE]
    dealt = [mpi + others[0::blocks]] + [others[b::blocks] for b in range(1, blocks)] if blocks > 1 else [long]
    out: list = []
    for b in range(blocks):
        mine = dealt[b]
        fill = rest[: max(size - len(mine), 0)]
        rest = rest[len(fill):]
        out += mine + fill
    items[:] = out + rest


class Held:
    """A communicator (wrapping ``comm``) that adds up the numbers its exchanges brought this rank from
    the other ranks (``numbers``: array elements, each field of a record counted)."""

    def __init__(self, comm):
        self.comm, self.rank, self.size, self.numbers = comm, comm.rank, comm.size, 0

    def __getattr__(self, name):
        return getattr(self.comm, name)

    def sparse_alltoall(self, values):
        return self._noted(self.comm.sparse_alltoall(values))

    def allgather(self, value):
        return self._noted(self.comm.allgather(value))

    def alltoall(self, values):
        return self._noted(self.comm.alltoall(values))

    def _noted(self, got):
        for r, g in enumerate(got):
            if g is not None and r != self.rank:
                self.numbers += sum(int(np.size(a)) * len(np.asarray(a).dtype.names or (0,))
                                    for a in (g if isinstance(g, tuple) else (g,)))
        return got
