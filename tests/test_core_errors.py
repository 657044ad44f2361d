"""Every status code of the Fortran core that a caller can provoke, produced through the
real core (arpy._core) and its Python wrappers, and mapped by arpy._errors to the
documented exception class and message; the core serves correct lists afterwards."""

from __future__ import annotations

import itertools
import os
import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import arpy
from arpy import _core
from arpy.lists import search as nbmod
from arpy.adapt import forces
from arpy.adapt import resolution as res
from arpy._errors import _CODES, ArpyError, raise_for_info
from arpy.reference import brute_force_pairs

#: the order array of arpy_neighbors when the list is asked in particle order (not written)
NO_ORDER = np.empty(0, np.int64)

def message(code: int) -> str:
    """The message template of a status code, as a regular expression (no {bad} in these)."""
    return re.escape(_CODES[code][1])


def assert_core_still_works() -> None:
    x = np.random.default_rng(3).random((300, 2))
    rc = np.random.default_rng(4).uniform(0.01, 0.08, 300)
    for method in ("brute", "cell", "ar"):
        i, j = arpy.neighbor_list(x, rc, method=method).pairs()
        ei, ej = brute_force_pairs(x, rc)
        np.testing.assert_array_equal(i, ei)
        np.testing.assert_array_equal(j, ej)


def test_unknown_status_is_an_arpy_error():
    """An unknown code becomes an ArpyError naming it (that every code of the core has its own
    message is checked against the Fortran source in test_codes.py)."""
    with pytest.raises(ArpyError, match="unknown status 99"):
        raise_for_info(99)
    assert issubclass(ArpyError, RuntimeError) and not issubclass(ArpyError, ValueError)


# ---------------------------------------------------------------- 4: allocation
ALLOC_SCRIPT = textwrap.dedent("""
    import resource, sys
    import numpy as np
    import arpy
    from arpy.reference import brute_force_pairs

    def vm_size():
        for line in open("/proc/self/status"):
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024

    x = np.zeros((20000, 2))               # all in one point: 2e8 pairs, 800 MB of indices
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = vm_size() + 64 * 2 ** 20        # 64 MB more address space than now
    out = []
    for method in sys.argv[1:]:
        resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
        try:
            arpy.neighbor_list(x, 1.0, method=method)
            out.append(method + ": no error")
        except MemoryError as err:
            out.append(method + ": MemoryError: " + str(err))
        except Exception as err:
            out.append(method + ": " + type(err).__name__ + ": " + str(err))
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
    # the core recovers: a correct list right after
    y = np.random.default_rng(0).random((500, 2))
    i, j = arpy.neighbor_list(y, 0.05).pairs()
    assert i.size == brute_force_pairs(y, 0.05)[0].size
    out.append("recovered")
    print("\\n".join(out))
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs RLIMIT_AS and /proc")
def test_code_4_allocation_failure_is_a_clean_memory_error():
    """Code 4: a list of 2e8 pairs under an address-space limit 64 MB above the process's
    current size: the core's growing list fails to allocate, returns ARPY_ERR_ALLOC and
    Python raises MemoryError (in a child process, so the limit stays there)."""
    methods = ["cell", "ar", "brute"]
    run = subprocess.run([sys.executable, "-c", ALLOC_SCRIPT, *methods], capture_output=True, text=True,
                         env={**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"},
                         timeout=300)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.split("\n")
    expected = "MemoryError: neighbor_list: " + _CODES[4][1]
    assert _CODES[4][0] is MemoryError
    for method, line in zip(methods, lines):
        assert line == f"{method}: {expected}", line
    assert lines[len(methods)] == "recovered"


# ---------------------------------------------------------------- 5, 6: the hand-off store
def test_code_5_take_with_no_result_waiting():
    for handle in (0, -3, 10 ** 6):
        with pytest.raises(ArpyError, match="neighbor_list: " + message(5)):
            nbmod.collect_list(handle, 10, 0, full=False)
        # straight from the core: the same code
        info = _core.arpy_result_take(handle, np.empty(11, np.int64), np.empty(0, np.int32))
        assert info == 5
    # a result is taken once: a second take finds nothing
    x = np.random.default_rng(0).random((50, 2))
    handle, nnz, info, _ = _core.arpy_neighbors(x.T, np.full(50, 0.2), 0.0, nbmod.METHODS["cell"], 0, 1, 0, NO_ORDER)
    assert info == 0 and nnz > 0
    nbmod.collect_list(handle, 50, nnz, full=False)
    with pytest.raises(ArpyError, match=message(5)):
        nbmod.collect_list(handle, 50, nnz, full=False)
    # a dropped result is gone too
    handle, nnz, info, _ = _core.arpy_neighbors(x.T, np.full(50, 0.2), 0.0, nbmod.METHODS["cell"], 0, 1, 0, NO_ORDER)
    _core.arpy_result_free(handle)
    with pytest.raises(ArpyError, match=message(5)):
        nbmod.collect_list(handle, 50, nnz, full=False)
    # a freed AR tree: its handle names no tree
    tree = arpy.ARCellList(x, 0.2)
    tree.__del__()
    with pytest.raises(ArpyError, match="verlet_list: " + message(5)):
        tree.verlet_list()
    assert_core_still_works()


def test_code_6_result_size_mismatch():
    x = np.random.default_rng(1).random((80, 3))
    rc = np.full(80, 0.3)
    ei, ej = brute_force_pairs(x, rc)
    for wrong in ((80, +1), (80, -1), (79, 0), (81, 0)):
        handle, nnz, info, _ = _core.arpy_neighbors(x.T, rc, 0.0, nbmod.METHODS["cell"], 0, 1, 0, NO_ORDER)
        assert info == 0 and nnz == ei.size
        with pytest.raises(ArpyError, match="neighbor_list: " + message(6)):
            nbmod.collect_list(handle, wrong[0], nnz + wrong[1], full=False)
        # a refused take frees the list: it is not left behind
        with pytest.raises(ArpyError, match=message(5)):
            nbmod.collect_list(handle, 80, nnz, full=False)
        handle, nnz, info, _ = _core.arpy_neighbors(x.T, rc, 0.0, nbmod.METHODS["cell"], 0, 1, 0, NO_ORDER)
        nl = nbmod.collect_list(handle, 80, nnz, full=False)
        i, j = nl.pairs()
        np.testing.assert_array_equal(i, ei)
        np.testing.assert_array_equal(j, ej)
    # a list in cell order whose order array is not one per particle: nothing is published
    for m in (0, 79, 81):
        handle, nnz, info, _ = _core.arpy_neighbors(x.T, rc, 0.0, nbmod.METHODS["ar"], 0, 1, 1, np.empty(m, np.int64))
        assert (handle, nnz, info) == (0, -1, 6)
    # tables of a kept tree asked for with the wrong sizes
    handle, nleaf, nkey, _, _, info, _ = _core.arpy_ar_create(x.T, rc, 0.0, 0, np.zeros(3), np.zeros(3))
    try:
        assert info == 0
        for n, nl_, nk in ((81, nleaf, nkey), (80, nleaf + 1, nkey), (80, nleaf, nkey - 1)):
            *_, info = _core.arpy_ar_tables(handle, n, nl_, nk)
            with pytest.raises(ArpyError, match=message(6)):
                raise_for_info(info)
        *_, info = _core.arpy_ar_tables(handle, 80, nleaf, nkey)
        assert info == 0
    finally:
        _core.arpy_ar_free(handle)
    assert_core_still_works()


# ---------------------------------------------------------------- 10: method codes
@pytest.mark.parametrize("name", ["brute", "cell", "ar"])
def test_code_10_unknown_method_code(monkeypatch, name):
    x = np.random.default_rng(2).random((40, 2))
    monkeypatch.setitem(nbmod.METHODS, name, 7)
    with pytest.raises(ValueError, match="neighbor_list: " + message(10)):
        arpy.neighbor_list(x, 0.1, method=name)
    monkeypatch.undo()
    for code in (-1, 3, 99):
        assert _core.arpy_neighbors(x.T, np.full(40, 0.1), 0.0, code, 0, 1, 0, NO_ORDER)[2] == 10
        assert _core.arpy_build_only(x.T, np.full(40, 0.1), code)[0] == 10
    assert _core.arpy_build_only(x.T, np.full(40, 0.1), 0)[0] == 10      # brute force has no structure
    tree = arpy.ARCellList(x, 0.1)
    for op in (0, 6):
        with pytest.raises(ValueError, match="ARCellList: " + message(10)):
            tree._ops(op, [1])
    # potential kinds of the energy
    nl = arpy.neighbor_list(x, 0.1)
    for kind, grad in itertools.product((0, 5), (0, 1)):
        *_, info, _ = _core.arpy_so_energy(x.T, np.full(40, 0.05), np.zeros((2, 40)), np.zeros(2), nl.offsets,
                                           nl.indices, kind, 0.0, grad)
        assert info == 10
    assert_core_still_works()


# ---------------------------------------------------------------- 11: lists handed in
def _bad_lists(n: int, nl: arpy.NeighborList):
    """(what, offsets, indices) of lists the core must refuse."""
    off, idx = nl.offsets.copy(), nl.indices.copy()
    dec = off.copy()
    dec[1] = off[-1]                                    # row 0 claims every entry: row 1 ends before it starts
    assert np.any(np.diff(dec) < 0) and dec[0] == 0 and dec[-1] == len(idx)
    high, neg = idx.copy(), idx.copy()
    high[len(idx) // 2] = n
    neg[0] = -1
    first = off.copy()
    first[0] = 1
    return [("offsets decrease", dec, idx), ("index = n", off, high), ("index < 0", off, neg),
            ("first offset not 0", first, idx)]


def test_code_11_inconsistent_lists_through_energy_scan_and_dcpse():
    rng = np.random.default_rng(5)
    x = rng.random((60, 2))
    D = np.full(60, 0.08)
    nl = arpy.neighbor_list(x, res.r_star(2) * D)
    W, _ = forces.energy(x, D, nl)
    for what, off, idx in _bad_lists(60, nl):
        bad = arpy.NeighborList(off, idx)
        with pytest.raises(ValueError, match="energy: " + message(11)):
            forces.energy(x, D, bad)
        out = _core.arpy_so_ratios(x.T, D, np.zeros(2), off, idx)
        assert out[-2] == 11, what
    # the last offset must equal the number of entries
    short = nl.offsets.copy()
    short[-1] -= 1
    assert _core.arpy_so_ratios(x.T, D, np.zeros(2), short, nl.indices)[-2] == 11
    with pytest.raises(ValueError, match="energy: " + message(11)):
        forces.energy(x, D, arpy.NeighborList(short, nl.indices))
    # fusion pairs out of range or of one particle
    for a, b in (([0, 60], [1, 2]), ([0, -1], [1, 2]), ([3, 4], [5, 4])):
        out = _core.arpy_so_fuse(x.T, np.zeros(2), np.array(a, np.int32), np.array(b, np.int32))
        assert out[-2:] == (11, 1)
    assert forces.energy(x, D, nl)[0] == W                              # and the core is fine after
    # DC-PSE with a full list whose offsets decrease (the Python side checks only the indices)
    full = arpy.neighbor_list(x, 0.3, full=True)
    _, off, idx = _bad_lists(60, full)[0]
    with pytest.raises(ValueError, match="DCPSE: " + message(11)):
        arpy.DCPSE(x, np.full(60, 0.3), order=3, neighbors=arpy.NeighborList(off, idx, full=True))
    assert_core_still_works()


# ---------------------------------------------------------------- 12: DC-PSE requests
def test_code_12_invalid_dcpse_requests():
    rng = np.random.default_rng(6)
    x = rng.random((400, 2))
    y = 0.2 + 0.6 * rng.random((30, 2))
    eps = np.full(400, 0.15)
    off = arpy.DCPSE(x, eps, y, order=4)
    # c and max_cond out of range: refused by DCPSE with their names, and by the core
    for kwargs, word in ((dict(c=0.0), "c must"), (dict(c=-1.0), "c must"), (dict(c=np.nan), "c must"),
                         (dict(max_cond=1.0), "max_cond"), (dict(max_cond=0.5), "max_cond")):
        with pytest.raises(ValueError, match=word):
            arpy.DCPSE(x, eps, y, **kwargs)
        c, max_cond = kwargs.get("c", 2.0), kwargs.get("max_cond", 1e12)
        nl = off.neighbors
        out = _core.arpy_dcpse(x.T, off.a, y.T, np.full(30, 0.15), nl.offsets, nl.indices, 4, c, 0,
                               np.zeros(1, np.int32), np.asfortranarray([[1], [0]], np.int32), max_cond)
        with pytest.raises(ValueError, match=message(12)):
            raise_for_info(out[-2])
    on = arpy.DCPSE(x, eps, order=2, strict=False)
    # requests the public methods refuse before the core: the core refuses them too
    for op, alphas in ((off, [(4, 0)]), (off, [(2, 3)]), (off, [(-1, 1)]), (on, [(0, 0)]), (on, ["laplacian"]),
                       (on, ["interpolation"])):
        with pytest.raises(ValueError, match="DCPSE: " + message(12)):
            op._compute(alphas)
    # straight from the core: order m < 1, an unknown form, an unknown operator kind
    nl = off.neighbors
    args = (x.T, off.a, y.T, np.full(30, 0.15), nl.offsets, nl.indices)
    for m, form, kinds in ((0, 0, [0]), (4, 2, [0]), (4, 0, [3]), (4, 0, [-1])):
        alpha = np.zeros((2, len(kinds)), np.int32, order="F")
        alpha[0] = 1
        out = _core.arpy_dcpse(*args, m, 1.0, form, np.asarray(kinds, np.int32), alpha, 1e12)
        assert out[-2] == 12, (m, form, kinds)
    # and the valid request right after gives the exact derivative of a cubic
    f = x[:, 0] ** 3 - 2 * x[:, 0] * x[:, 1]
    np.testing.assert_allclose(off.derivative((1, 0)) @ f, 3 * y[:, 0] ** 2 - 2 * y[:, 1], rtol=1e-8, atol=1e-8)
