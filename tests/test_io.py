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
