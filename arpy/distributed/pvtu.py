"""Output at large scale: one ``.vtu`` piece per rank and a ``.pvtu`` file naming them (:func:`write_pvtu`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .comm import Comm

__all__ = ["write_pvtu"]


def write_pvtu(comm: Comm, path: str | Path, x: np.ndarray, **point_data: np.ndarray) -> Path:
    """Write the particles of every rank as one parallel VTK file (output at large scale): each rank
    writes its own piece ``<stem>/<stem>_<rank>.vtu`` (:func:`arpy.io.write_vtu`, with the array
    ``rank``), and rank 0 writes ``path`` (``.pvtu``) naming the pieces and their arrays, which
    ParaView and VisIt open as one data set.  Collective.

    Parameters
    ----------
    comm : Comm
    path : str or Path
        The ``.pvtu`` file.
    x : array (n, 2) or (n, 3)
        This rank's positions.
    **point_data : arrays (n,) or (n, k)
        This rank's particle quantities (the same names on every rank).

    Returns
    -------
    Path
        ``path``.
    """
    from xml.etree import ElementTree as ET

    from ..io import write_vtu

    path = Path(path)
    x = np.asarray(x, dtype=np.float64)
    data = {**{k: np.asarray(v, dtype=np.float64) for k, v in point_data.items()},
            "rank": np.full(x.shape[0], float(comm.rank))}
    layout = sorted((k, 1 if v.ndim == 1 else int(v.shape[1])) for k, v in data.items())
    if any(other != layout for other in comm.allgather(layout)):
        raise ValueError("write_pvtu: every rank must give the same arrays with the same components")
    piece_dir = path.parent / path.stem
    if comm.rank == 0:
        piece_dir.mkdir(parents=True, exist_ok=True)
    comm.allgather(None)                                       # the directory exists before any piece
    write_vtu(piece_dir / f"{path.stem}_{comm.rank}.vtu", x, **data)
    comm.allgather(None)                                       # every piece is written
    if comm.rank == 0:
        root = ET.Element("VTKFile", type="PUnstructuredGrid", version="0.1", byte_order="LittleEndian")
        grid = ET.SubElement(root, "PUnstructuredGrid", GhostLevel="0")
        pdata = ET.SubElement(grid, "PPointData")
        for name, comps in layout:
            ET.SubElement(pdata, "PDataArray", type="Float64", Name=name, NumberOfComponents=str(comps))
        pts = ET.SubElement(grid, "PPoints")
        ET.SubElement(pts, "PDataArray", type="Float64", NumberOfComponents="3")
        for r in range(comm.size):
            ET.SubElement(grid, "Piece", Source=f"{path.stem}/{path.stem}_{r}.vtu")
        ET.ElementTree(root).write(path, xml_declaration=True, encoding="utf-8")
    comm.allgather(None)
    return path
