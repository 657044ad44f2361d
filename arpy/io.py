"""Writing particle data: VTK XML files (``.vtu``: ParaView, VisIt, meshio) and NumPy archives.

The archives (:func:`save_results`) hold their arrays and, as JSON, what made them; each is written
with its JSON sidecar as one unit (temporary files moved in place), and read back
(:func:`load_results`) with one clear error, :class:`StateFileError`, for a file that is not one.
The results of a run carry its record (:func:`run_record`): the summary, the options and seed, the
ranks and threads it ran on and the versions of the packages that computed it."""

from __future__ import annotations

import json
import os
import secrets
import zipfile
import zlib
from pathlib import Path
from typing import Any, BinaryIO, Callable, Mapping, Sequence

import numpy as np

from ._version import __version__

__all__ = ["StateFileError", "json_default", "load_results", "load_run", "npz_path", "replace_atomically", "run_record",
           "save_results", "save_run", "storable", "unreadable", "versions", "write_vtu"]


class StateFileError(ValueError):
    """A file that cannot be read as the arpy file it should be (a simulation's state, a particle set,
    results): missing, empty, truncated, corrupted, or written by something else.  The message names
    the file and what is wrong with it, e.g. ``run/checkpoint.npz is not a readable arpy state file:
    it is not a NumPy archive (.npz): truncated, or another kind of file``."""


def unreadable(path: str | Path, what: str, exc: BaseException | str) -> StateFileError:
    """The :class:`StateFileError` of the file ``path`` that is not a readable ``what`` because of
    ``exc`` (a missing entry, a failed check, the reader's exception, or a text)."""
    if isinstance(exc, str):
        reason = exc
    elif isinstance(exc, FileNotFoundError):
        reason = "it does not exist"
    elif isinstance(exc, KeyError):
        reason = f"it has no entry {exc.args[0]!r}" if exc.args else "an entry is missing"
    elif type(exc) in (ValueError, TypeError):                 # (arpy's own checks say what is wrong)
        reason = str(exc)
    elif isinstance(exc, (zipfile.BadZipFile, zlib.error)):
        reason = f"it is damaged ({type(exc).__name__}: {exc})"
    else:
        reason = f"{type(exc).__name__}: {exc}"
    return StateFileError(f"{path} is not a readable {what}: {reason}")


def npz_path(path: str | Path) -> Path:
    """The file a NumPy archive written to ``path`` is: ``path`` if it ends in ``.npz``, else ``path``
    with ``.npz`` appended, as :func:`numpy.savez` does (``run.1`` -> ``run.1.npz``)."""
    path = Path(path)
    return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")


def storable(name: str, value: Any) -> np.ndarray:
    """``value`` as an array that a NumPy archive stores and loads back without pickling; TypeError
    naming ``name`` if it is not one (an object array: dicts, None, ragged rows, arbitrary objects),
    since :func:`load_results` does not unpickle."""
    try:
        array = np.asarray(value)
    except ValueError as exc:                              # (ragged rows)
        raise TypeError(f"{name} cannot be stored: it is not a regular array of numbers, booleans or strings "
                        f"({exc})") from None
    if array.dtype.hasobject:
        kind = type(value).__name__ + (f" of {type(value[0]).__name__}" if isinstance(value, (list, tuple)) and value
                                       else "")
        raise TypeError(f"{name} cannot be stored: a {kind} makes an array of Python objects, which a NumPy "
                        "archive only pickles and arpy does not load; give an array of numbers, booleans or strings")
    return array


def replace_atomically(writes: Mapping[Path, Callable[[BinaryIO], object]]) -> None:
    """Write files as one unit: each through a temporary file beside it (``writes[path](file)``
    writes its bytes; then flushed and fsynced), and only once all are written, each moved in place
    by :func:`os.replace`, in the order given.  A reader finds each file as it was or complete,
    never in part; on a failure the temporary files are removed and no file is replaced."""
    temps: dict[Path, Path] = {}
    try:
        for path, write in writes.items():
            tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)      # (mode as the umask allows)
            temps[path] = tmp
            with os.fdopen(fd, "wb") as f:
                write(f)
                f.flush()
                os.fsync(f.fileno())
        for path, tmp in temps.items():
            os.replace(tmp, path)
    finally:
        for tmp in temps.values():
            tmp.unlink(missing_ok=True)


def versions() -> dict[str, str | None]:
    """The versions of Python and of the packages that compute arpy's results: arpy, NumPy, SciPy and
    mpi4py (None where it is not installed).  A package not imported yet is not imported for this:
    its installed version is read from its metadata."""
    import platform
    import sys
    from importlib import metadata

    def version(module: str) -> str | None:
        loaded = sys.modules.get(module)
        if loaded is not None and isinstance(getattr(loaded, "__version__", None), str):
            return loaded.__version__
        try:
            return metadata.version(module)
        except metadata.PackageNotFoundError:
            return None

    return {"arpy": __version__, "python": platform.python_version(),
            **{name: version(name) for name in ("numpy", "scipy", "mpi4py")}}


def run_record(parameters: dict, summary: Mapping[str, Any] | None = None, *, comm: Any = None,
               columns: Mapping[str, Sequence[str]] | None = None) -> dict[str, Any]:
    """What the results of a run record about it, as JSON values: the one record of every output of
    ``arpy run`` (the sidecar of each ``.npz``, ``--json``).

    Parameters
    ----------
    parameters : dict
        The options the run was started with (JSON values); its ``seed``, if any, is also given
        at the top.
    summary : mapping, optional
        The run's results: errors, particle counts, steps, wall time in seconds (``wall_s``).
    comm : Comm, optional
        The communicator of a distributed run (None: one process).
    columns : mapping, optional
        For each two-dimensional array of the results, the names of its columns.

    Returns
    -------
    dict
        ``arpy_version``, ``parameters``, ``seed``, ``summary``, ``columns``, ``ranks`` (the number
        of processes), ``threads`` (the core's OpenMP threads per process: :func:`arpy.get_num_threads`)
        and ``versions`` (:func:`versions`).
    """
    from .threads import get_num_threads

    return {"arpy_version": __version__, "parameters": parameters, "seed": parameters.get("seed"),
            "summary": dict(summary or {}), "columns": {k: list(v) for k, v in (columns or {}).items()},
            "ranks": 1 if comm is None else int(comm.size), "threads": get_num_threads(), "versions": versions()}


def save_results(path: str | Path, parameters: dict, **arrays: np.ndarray) -> Path:
    """Write ``arrays`` to the NumPy archive ``path`` (``.npz`` appended if it lacks it, see
    :func:`npz_path`) together with what made them: the ``parameters`` (JSON-serialisable values)
    and the arpy version, in the archive's ``parameters`` entry (JSON text), which is what
    :func:`load_results` reads, and a copy of that text in a JSON sidecar for people and tools
    (the archive's name with .json: ``run.1.npz``, ``run.1.json``).  Both are written as one unit
    (:func:`replace_atomically`).  Arrays of Python objects are refused (:func:`storable`).
    Returns the archive's path, the file written."""
    return _save(path, {"arpy_version": __version__, "parameters": parameters}, arrays)


def save_run(path: str | Path, record: Mapping[str, Any], **arrays: np.ndarray) -> Path:
    """Write the results of a run as :func:`save_results` does, with the whole ``record`` of the run
    (:func:`run_record`: the options, the summary, ranks, threads, versions) as its JSON text, in the
    archive and in the sidecar; :func:`load_results` reads the options as ``parameters``.  Returns
    the archive's path."""
    if not isinstance(record.get("parameters"), dict):
        raise ValueError("record must hold the run's parameters (a dict), as run_record() makes it")
    return _save(path, {**record, "arpy_version": __version__}, arrays)


def _save(path: str | Path, meta: Mapping[str, Any], arrays: Mapping[str, Any]) -> Path:
    """The archive ``path`` of ``arrays`` and its sidecar, both with ``meta`` as JSON text."""
    path = npz_path(path)
    text = json.dumps(meta, indent=1, sort_keys=True, default=json_default)
    if "parameters" in arrays:
        raise ValueError("no array can be called 'parameters' (the entry of the JSON text)")
    entries: dict[str, Any] = {name: storable(f"the array {name!r}", a) for name, a in arrays.items()}
    entries["parameters"] = np.array(text)
    replace_atomically({path: lambda f: np.savez(f, **entries),
                        path.with_suffix(".json"): lambda f: f.write((text + "\n").encode())})
    return path


def json_default(value: object) -> object:
    """NumPy scalars and arrays as the Python numbers and lists JSON takes."""
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def load_results(path: str | Path, what: str = "arpy results file") -> tuple[dict, dict[str, np.ndarray]]:
    """The ``(parameters, arrays)`` of a file written by :func:`save_results`, every entry checked
    against its checksum.  A file that is missing, empty, truncated,
    corrupted or not written by :func:`save_results` raises one :class:`StateFileError` naming it
    (as not a readable ``what``)."""
    meta, arrays = load_run(path, what)
    return meta["parameters"], arrays


def load_run(path: str | Path, what: str = "arpy results file") -> tuple[dict, dict[str, np.ndarray]]:
    """As :func:`load_results`, with the whole JSON text of the file: the run's record of a file of
    :func:`save_run` (:func:`run_record`), ``{"arpy_version", "parameters"}`` of :func:`save_results`."""
    path = Path(path)
    try:
        if path.stat().st_size == 0:
            raise unreadable(path, what, "it is empty")
        if not zipfile.is_zipfile(path):
            raise unreadable(path, what, "it is not a NumPy archive (.npz): truncated, or another kind of file")
        with zipfile.ZipFile(path) as archive:
            damaged = archive.testzip()             # (every entry read whole against its checksum)
        if damaged is not None:
            raise unreadable(path, what, f"it is damaged (the checksum of its entry {damaged!r} fails)")
        with np.load(path, allow_pickle=False) as data:
            if "parameters" not in data.files:
                raise unreadable(path, what, f"it has no 'parameters' entry (not written by arpy; its entries: "
                                             f"{', '.join(data.files[:8]) or 'none'})")
            meta = json.loads(str(data["parameters"]))
            arrays = {k: data[k] for k in data.files if k != "parameters"}
        if not (isinstance(meta, dict) and isinstance(meta.get("parameters"), dict)):
            raise unreadable(path, what, "its 'parameters' entry is not the JSON object arpy writes")
    except StateFileError:
        raise
    except Exception as exc:            # (whatever a damaged archive makes zipfile, NumPy's header parser or json raise)
        raise unreadable(path, what, exc) from exc
    return meta, arrays


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
