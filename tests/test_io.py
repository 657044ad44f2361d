"""Particle files: binary VTU read back through meshio, and its XML header as VTK expects it."""

import numpy as np
import pytest

from arpy.io import write_vtu

meshio = pytest.importorskip("meshio")


@pytest.mark.parametrize("d", [2, 3])
def test_vtu_reads_back_with_every_array_bitwise(tmp_path, d):
    rng = np.random.default_rng(d)
    x = rng.standard_normal((1000, d)) * 10.0 ** rng.integers(-200, 200, (1000, 1))
    f, D, g = rng.standard_normal(1000), rng.random(1000), rng.standard_normal((1000, 3))
    path = write_vtu(tmp_path / "p.vtu", x, f=f, D=D, grad=g)
    mesh = meshio.read(path)
    np.testing.assert_array_equal(mesh.points[:, :d], x)
    assert np.all(mesh.points[:, d:] == 0) and mesh.points.shape == (1000, 3)
    assert set(mesh.point_data) == {"f", "D", "grad"}
    for name, v in {"f": f, "D": D, "grad": g}.items():
        assert mesh.point_data[name].dtype == np.float64
        np.testing.assert_array_equal(mesh.point_data[name], v)
    (block,) = mesh.cells
    assert block.type == "vertex"
    np.testing.assert_array_equal(block.data[:, 0], np.arange(1000))
    head = path.read_bytes()[:400].decode("ascii", "replace")
    assert 'type="UnstructuredGrid"' in head and 'compressor="vtkZLibDataCompressor"' in head


def test_vtu_is_binary_and_smaller_than_text(tmp_path):
    x = np.random.default_rng(0).random((20000, 2))
    path = write_vtu(tmp_path / "p.vtu", x, f=x[:, 0])
    text_bytes = 3 * 20000 * 25                       # three coordinates at %.17g, at least
    assert path.stat().st_size < text_bytes / 2


def test_vtu_refuses_bad_shapes(tmp_path):
    x = np.zeros((7, 2))
    with pytest.raises(ValueError, match="f must have shape"):
        write_vtu(tmp_path / "q.vtu", x, f=np.ones(3))
    with pytest.raises(ValueError, match="x must have shape"):
        write_vtu(tmp_path / "q.vtu", np.zeros((7, 4)))


def test_entries_read_rows_as_numpy_reads_the_whole_arrays(tmp_path):
    """open_results reads no array: each is an Entry whose rows lo .. hi - 1 (every block, the empty ones
    included) and whole read equal NumPy's whole load, sliced, in bits, dtype and shape, for C- and
    Fortran-ordered arrays of 1-3 dimensions, strings, booleans, a 0-d array, no rows, and a compressed
    archive; a file written again at the path after it was opened is refused, naming it."""
    import json

    from arpy.io import StateFileError, load_results, open_results, save_results

    rng = np.random.default_rng(3)
    arrays = dict(x=rng.random((6, 3)), keys=np.arange(6) * 7, s=np.array(["ab", "c", "def"]), z=np.float64(2.5),
                  fo=np.asfortranarray(rng.random((6, 4))), fo3=np.asfortranarray(rng.integers(0, 9, (5, 2, 3))),
                  b=np.array([True, False]), none=np.zeros((0, 2)), i3=rng.integers(0, 9, (5, 2, 3)))
    path = save_results(tmp_path / "a.npz", {"k": 1}, **arrays)
    np.savez_compressed(tmp_path / "c.npz", x=arrays["x"], parameters=np.array(json.dumps({"parameters": {}})))
    for p in (path, tmp_path / "c.npz"):
        meta, entries = open_results(p)
        whole = load_results(p)[1]
        assert meta == load_results(p)[0] and sorted(entries) == sorted(whole)
        for name, a in whole.items():
            e = entries[name]
            assert (e.shape, e.dtype) == (a.shape, a.dtype) and e.read().tobytes() == a.tobytes()
            for lo in range(a.shape[0] + 1 if a.ndim else 0):
                for hi in range(lo, a.shape[0] + 1):
                    got = e.rows(lo, hi)
                    assert got.dtype == a.dtype and got.shape == a[lo:hi].shape and np.array_equal(got, a[lo:hi])
    assert entries["x"].offset is None and open_results(path)[1]["fo"].fortran       # (the compressed one)
    e = open_results(path)[1]["x"]
    save_results(path, {"k": 1}, x=arrays["x"] + 1)
    with pytest.raises(StateFileError, match=f"{path} is not a readable .* written again"):
        e.rows(0, 2)
