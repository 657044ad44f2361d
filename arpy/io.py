"""Writing particle data: VTK XML files (``.vtu``: ParaView, VisIt, meshio) and NumPy archives."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ._version import __version__

__all__ = ["json_default", "load_results", "save_results", "write_vtu"]


def save_results(path: str | Path, parameters: dict, **arrays: np.ndarray) -> Path:
    """Write ``arrays`` to the NumPy archive ``path`` (.npz) together with what made them: the
    ``parameters`` (JSON-serialisable values) and the arpy version, also in a JSON sidecar next to it
    (same name, .json).  The archive's ``parameters`` entry holds that JSON text.  Returns the path."""
    path = Path(path)
    meta = {"arpy_version": __version__, "parameters": parameters}
    text = json.dumps(meta, indent=1, sort_keys=True, default=json_default)
    entries: dict[str, Any] = {**arrays, "parameters": np.array(text)}   # (no array can be called parameters)
    np.savez(path, **entries)
    path.with_suffix(".json").write_text(text + "\n")
    return path


def json_default(value: object) -> object:
    """NumPy scalars and arrays as the Python numbers and lists JSON takes."""
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def load_results(path: str | Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The ``(parameters, arrays)`` of a file written by :func:`save_results`."""
    with np.load(Path(path)) as data:
        if "parameters" not in data.files:
            raise ValueError(f"{path} was not written by arpy.io.save_results (no 'parameters' entry)")
        meta = json.loads(str(data["parameters"]))
        return meta["parameters"], {k: data[k] for k in data.files if k != "parameters"}


def write_vtu(path: str | Path, x: np.ndarray, **point_data: np.ndarray) -> Path:
    """Write particles as a VTK XML unstructured grid (``.vtu``, binary, zlib-compressed) through
    meshio: one vertex cell per particle and every keyword as a point-data array.  ParaView, VisIt,
    VTK and ``meshio.read`` read it with all its arrays.

    Parameters
    ----------
    path : str or Path
        The file to write (the suffix should be ``.vtu``).
    x : array, shape (n, 2) or (n, 3)
        Positions; 2D points get z = 0.
    **point_data : array, shape (n,) or (n, k)
        One array per particle quantity (e.g. ``f=``, ``D=``), written as float64.

    Returns
    -------
    Path
        ``path``.

    Examples
    --------
    >>> import numpy as np, tempfile, pathlib, meshio
    >>> x = np.random.default_rng(0).random((5, 2))
    >>> path = write_vtu(pathlib.Path(tempfile.mkdtemp()) / "p.vtu", x, f=x[:, 0])
    >>> bool(np.array_equal(meshio.read(path).point_data["f"], x[:, 0]))
    True
    """
    import meshio

    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] not in (2, 3):
        raise ValueError(f"x must have shape (n, 2) or (n, 3), got {x.shape}")
    n = x.shape[0]
    pts = np.zeros((n, 3))
    pts[:, : x.shape[1]] = x
    data = {}
    for name, values in point_data.items():
        v = np.asarray(values, dtype=np.float64)
        if v.ndim not in (1, 2) or v.shape[0] != n:
            raise ValueError(f"{name} must have shape ({n},) or ({n}, k), got {v.shape}")
        data[name] = v
    mesh = meshio.Mesh(pts, [("vertex", np.arange(n, dtype=np.int64).reshape(n, 1))], point_data=data)
    path = Path(path)
    meshio.write(path, mesh, file_format="vtu", binary=True, compression="zlib")
    return path
