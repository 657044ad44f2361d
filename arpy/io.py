"""Writing particle data: VTK XML files (``.vtu``: ParaView, VisIt, meshio) and NumPy archives.

The archives (:func:`save_results`) hold their arrays and, as JSON, what made them; each is written
with its JSON sidecar as one unit (temporary files moved in place), and read back
(:func:`load_results`) with one clear error, :class:`StateFileError`, for a file that is not one;
:func:`open_results` checks a file the same way but reads its arrays only when asked, by blocks of
rows (:class:`Entry`: memory for the rows read, not the arrays).
The results of a run carry its record (:func:`run_record`): the summary, the options and seed, the
ranks and threads it ran on and the versions of the packages that computed it."""

from __future__ import annotations

import contextlib
import io
import json
import os
import secrets
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Callable, Iterator, Mapping, Sequence

import numpy as np

from ._version import __version__

__all__ = ["Entry", "StateFileError", "Stored", "json_default", "load_results", "load_run", "npz_path", "open_results",
           "replace_atomically", "run_record", "save_results", "save_run", "storable", "unreadable", "versions",
           "write_vtu"]


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
    return _load(path, what, lazy=False)


def open_results(path: str | Path, what: str = "arpy results file") -> tuple[dict, dict[str, "Entry"]]:
    """As :func:`load_results` (the same checks, the checksums included), without reading the arrays:
    ``(parameters, entries)``, each array an :class:`Entry` that reads its rows, or all of it, when
    asked (memory: what is read)."""
    meta, entries = _load(path, what, lazy=True)
    return meta["parameters"], entries


def _load(path: str | Path, what: str, lazy: bool) -> tuple[dict, dict[str, Any]]:
    """The JSON text and the arrays (``lazy``: their :class:`Entry`) of a checked archive of :func:`_save`,
    all from one opening of the file (the entries are those of the file whose checksums were checked)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            if os.fstat(f.fileno()).st_size == 0:
                raise unreadable(path, what, "it is empty")
            if not zipfile.is_zipfile(f):
                raise unreadable(path, what, "it is not a NumPy archive (.npz): truncated, or another kind of file")
            with zipfile.ZipFile(f) as archive:
                damaged = archive.testzip()             # (every entry read against its checksum, streaming)
                if damaged is not None:
                    raise unreadable(path, what, f"it is damaged (the checksum of its entry {damaged!r} fails)")
                arrays = _entries(path, f, archive, what) if lazy else {}
            f.seek(0)
            with np.load(f, allow_pickle=False) as data:
                if "parameters" not in data.files:
                    raise unreadable(path, what, f"it has no 'parameters' entry (not written by arpy; its entries: "
                                                 f"{', '.join(data.files[:8]) or 'none'})")
                meta = json.loads(str(data["parameters"]))
                if not lazy:
                    arrays = {k: data[k] for k in data.files if k != "parameters"}
        if not (isinstance(meta, dict) and isinstance(meta.get("parameters"), dict)):
            raise unreadable(path, what, "its 'parameters' entry is not the JSON object arpy writes")
    except StateFileError:
        raise
    except Exception as exc:            # (whatever a damaged archive makes zipfile, NumPy's header parser or json raise)
        raise unreadable(path, what, exc) from exc
    return meta, arrays


def _stamp(f: BinaryIO) -> tuple[int, ...]:
    """What tells an open file from another written at its path since: device, inode, size, mtime."""
    st = os.fstat(f.fileno())
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


def _entries(path: Path, f: io.BufferedReader, archive: zipfile.ZipFile, what: str) -> dict[str, "Entry"]:
    """The arrays (``.npy`` members but ``parameters``) of the ``archive`` in the open file ``f`` (at
    ``path``) as :class:`Entry`, from their headers: ValueError for an array of Python objects or one
    whose bytes do not fit its header."""
    out = {}
    stamp = _stamp(f)
    for info in archive.infolist():
        name = info.filename[:-4]
        if not info.filename.endswith(".npy") or name == "parameters":
            continue
        f.seek(info.header_offset)                      # (the member's local header: 30 bytes, name, extra)
        local = f.read(30)
        if local[:4] != b"PK\x03\x04":
            raise ValueError(f"its entry {name!r} has no local header")
        start = info.header_offset + 30 + int.from_bytes(local[26:28], "little") + \
            int.from_bytes(local[28:30], "little")
        stored = info.compress_type == zipfile.ZIP_STORED and not info.flag_bits & 1
        with contextlib.nullcontext(f) if stored else archive.open(info) as member:
            if stored:
                f.seek(start)
            version = np.lib.format.read_magic(member)
            if version not in ((1, 0), (2, 0)):
                raise ValueError(f"its entry {name!r} is in the .npy format {version}, arpy writes 1.0 and 2.0")
            header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                np.lib.format.read_array_header_2_0
            shape, fortran, dtype = header(member)
            data = member.tell() - (start if stored else 0)
        if dtype.hasobject:
            raise ValueError(f"its entry {name!r} is an array of Python objects, which arpy does not load")
        if stored and data + int(np.prod(shape)) * dtype.itemsize != info.file_size:
            raise ValueError(f"its entry {name!r} holds {info.file_size - data} bytes of data, its header "
                             f"says {shape} {dtype}")
        out[name] = Entry(path, name, tuple(shape), dtype, bool(fortran), start + data if stored else None,
                          stamp, what)
    return out


@dataclass(frozen=True)
class Entry:
    """An array of an archive checked by :func:`open_results`, not read yet: its shape and dtype (from
    its header), and where its bytes are.  :meth:`rows` reads a block of its rows, :meth:`read` all of
    it; a stored (uncompressed, as arpy writes) member is read by seeking to the rows' bytes (memory:
    the rows read), another one whole through NumPy, then sliced.  A file written again at ``path``
    since it was checked is refused (:class:`StateFileError`)."""

    path: Path
    """The archive."""
    name: str
    """The array's name in it."""
    shape: tuple[int, ...]
    """Its shape: (N, ...) for N rows."""
    dtype: np.dtype
    """Its dtype."""
    fortran: bool
    """Whether its bytes are in Fortran order."""
    offset: int | None
    """Where its first byte is in the file (None: a member read through NumPy)."""
    stamp: tuple[int, ...]
    """The file it was found in (:func:`_stamp`)."""
    what: str
    """What the file is (in the message of a :class:`StateFileError`)."""

    def read(self) -> np.ndarray:
        """The whole array."""
        return self.rows(0, self.shape[0]) if self.shape else self.rows(0, 1)

    def rows(self, lo: int, hi: int) -> np.ndarray:
        """Rows lo .. hi - 1 (0 <= lo <= hi <= N), shape (hi - lo, ...); a 0-d array whole for (0, 1)."""
        n = self.shape[0] if self.shape else 1
        if not 0 <= lo <= hi <= n:
            raise ValueError(f"rows {lo} .. {hi} of the {n} rows of {self.name!r}")
        with open(self.path, "rb") as f:
            if _stamp(f) != self.stamp:
                raise unreadable(self.path, self.what, "it was written again since it was checked")
            if self.offset is None:
                with np.load(f, allow_pickle=False) as data:
                    whole = data[self.name]
                return whole if not self.shape else whole[lo:hi]
            rest = self.shape[1:]
            if not self.fortran:                                # (C order: the rows are one block)
                out = np.empty((hi - lo, *rest) if self.shape else (), self.dtype)
                self._fill(f, lo * int(np.prod(rest)), out)
                return out
            columns = np.empty((int(np.prod(rest)), hi - lo), self.dtype)   # (Fortran order: a block per column)
            for j, column in enumerate(columns):
                self._fill(f, j * n + lo, column)
            return columns.T.reshape((hi - lo, *rest), order="F")

    def _fill(self, f: io.BufferedReader, first: int, out: np.ndarray) -> None:
        """Read into the contiguous array ``out`` the array's elements from its element ``first`` (in the
        order of its bytes) on."""
        assert self.offset is not None
        f.seek(self.offset + first * self.dtype.itemsize)
        view = out.reshape(-1).view(np.uint8).data
        while view.nbytes:
            got = f.readinto(view)
            if not got:
                raise unreadable(self.path, self.what, f"its entry {self.name!r} ends early")
            view = view[got:]


class Stored(Mapping[str, np.ndarray]):
    """Arrays of an archive by name (:class:`Entry`), each read whole from the file when looked up
    (and not kept)."""

    def __init__(self, entries: Mapping[str, Entry]) -> None:
        self.entries = dict(entries)

    def __getitem__(self, name: str) -> np.ndarray:
        return self.entries[name].read()

    def __iter__(self) -> Iterator[str]:
        return iter(self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def __repr__(self) -> str:
        return f"Stored({', '.join(self.entries)})"


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
