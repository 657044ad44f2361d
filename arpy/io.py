"""Writing particle data: legacy VTK files (ParaView, VisIt) and NumPy archives."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ._version import __version__

__all__ = ["load_results", "save_results", "write_vtk"]


def save_results(path: str | Path, parameters: dict, **arrays: np.ndarray) -> Path:
    """Write ``arrays`` to the NumPy archive ``path`` (.npz) together with what made them: the
    ``parameters`` (JSON-serialisable values) and the arpy version, also in a JSON sidecar next to it
    (same name, .json).  The archive's ``parameters`` entry holds that JSON text.  Returns the path."""
    path = Path(path)
    meta = {"arpy_version": __version__, "parameters": parameters}
    text = json.dumps(meta, indent=1, sort_keys=True, default=_plain)
    np.savez(path, **arrays, parameters=np.array(text))
    path.with_suffix(".json").write_text(text + "\n")
    return path


def _plain(value):
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


def write_vtk(path: str | Path, x: np.ndarray, **scalars: np.ndarray) -> Path:
    """Write particles as a legacy-format VTK polydata file (ASCII): one vertex
    per particle and one point-data array per keyword (each of shape (n,)).

    x : (n, 2) or (n, 3) positions (2D points get z = 0).  Returns the path.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] not in (2, 3):
        raise ValueError("x must have shape (n, 2) or (n, 3)")
    n = x.shape[0]
    pts = np.zeros((n, 3))
    pts[:, : x.shape[1]] = x
    path = Path(path)
    with open(path, "w") as fh:
        fh.write("# vtk DataFile Version 3.0\narpy particles\nASCII\nDATASET POLYDATA\n")
        fh.write(f"POINTS {n} double\n")
        np.savetxt(fh, pts, fmt="%.17g")
        fh.write(f"VERTICES {n} {2 * n}\n")
        np.savetxt(fh, np.stack([np.ones(n, int), np.arange(n)], axis=1), fmt="%d")
        if scalars:
            fh.write(f"POINT_DATA {n}\n")
        for name, values in scalars.items():
            v = np.asarray(values, dtype=np.float64)
            if v.shape != (n,):
                raise ValueError(f"{name} must have shape ({n},)")
            fh.write(f"SCALARS {name} double 1\nLOOKUP_TABLE default\n")
            np.savetxt(fh, v, fmt="%.17g")
    return path
