"""Inputs that must be the same on every rank: :func:`agree` checks that they are (one small collective of
their fingerprints, :func:`fingerprint`), so that ranks given different ones fail together, naming the
difference, instead of mixing them."""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Any, Mapping, Sequence

import numpy as np

from ..domain import Domain
from .comm import Comm, rank_list

__all__ = ["FINGERPRINT_MAX", "agree", "disagreement", "fingerprint"]

#: Fingerprints longer than this (in characters) are shortened to their start and a digest, so that
#: the check of :func:`agree` stays one small collective.
FINGERPRINT_MAX = 160


def _digest(data: Any) -> str:
    """A short hex digest of bytes (or a contiguous buffer)."""
    return hashlib.blake2b(data, digest_size=8).hexdigest()


def _canonical(value: Any) -> str:
    """The text of :func:`fingerprint`, at full length: exact for numbers (``repr`` of the double, so
    NaN equals NaN and -0.0 differs from 0.0), arrays by dtype, shape and a digest of their bytes,
    containers by their items, callables by their qualified name, dataclasses by their fields, other
    objects by their type (never an address, which differs between processes)."""
    if value is None or isinstance(value, (bool, np.bool_, str)):
        return repr(value.item() if isinstance(value, np.bool_) else value)
    if isinstance(value, (int, np.integer)):
        return repr(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, (complex, np.complexfloating)):
        return repr(complex(value))
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            return f"object array {value.shape} {_canonical(value.tolist())}"
        if value.size <= 4:
            return f"{value.dtype} array {value.shape} {value.tolist()}"
        data = np.ascontiguousarray(value)
        return f"{value.dtype} array {value.shape} #{_digest(data.view(np.uint8).reshape(-1).data)}"
    if isinstance(value, Domain):
        return repr(value)
    if isinstance(value, Mapping):
        items = sorted((_canonical(k), _canonical(v)) for k, v in value.items())
        return "{" + ", ".join(f"{k}: {v}" for k, v in items) + "}"
    if isinstance(value, (list, tuple)):
        inner = ", ".join(_canonical(v) for v in value)
        return f"[{inner}]" if isinstance(value, list) else f"({inner}{',' if len(value) == 1 else ''})"
    if isinstance(value, (set, frozenset)):
        return "{" + ", ".join(sorted(_canonical(v) for v in value)) + "}"
    if callable(value):                     # (by name only: its state may be the rank's own, e.g. its samples)
        name = getattr(value, "__qualname__", type(value).__qualname__)
        return f"<callable {getattr(value, '__module__', None) or ''}.{name}>"
    if dataclasses.is_dataclass(value):
        fields = ", ".join(f"{f.name}={_canonical(getattr(value, f.name))}" for f in dataclasses.fields(value))
        return f"{type(value).__qualname__}({fields})"
    return f"<{type(value).__module__}.{type(value).__qualname__}>"


def fingerprint(value: Any) -> str:
    """A short text, the same on two ranks exactly when their values are (up to a digest collision),
    and readable in a message: numbers and small arrays as they are, large arrays as dtype, shape and
    a digest of their bytes, a :class:`arpy.Domain` as its ``repr``, containers and dataclasses by
    their items, callables by their qualified name only (a function cannot be compared between
    processes).  At most :data:`FINGERPRINT_MAX` characters (a longer text: its start and a digest)."""
    text = _canonical(value)
    if len(text) > FINGERPRINT_MAX:
        text = f"{text[:FINGERPRINT_MAX - 40]}... #{_digest(text.encode())}"
    return text


def disagreement(every: Sequence[Mapping[str, str]]) -> list[tuple[str, str]]:
    """The values on which the ranks' fingerprints (one mapping per rank, in rank order) differ: (name,
    'A on ranks ..; B on rank ..'); a name a rank did not give is '(not given)' there."""
    out = []
    for name in dict.fromkeys(k for fp in every for k in fp):
        ranks: dict[str, list[int]] = {}
        for r, fp in enumerate(every):
            ranks.setdefault(fp.get(name, "(not given)"), []).append(r)
        if len(ranks) > 1:
            out.append((name, "; ".join(f"{v} on {rank_list(rs)}" for v, rs in ranks.items())))
    return out


def agree(comm: Comm | None, where: str, **values: Any) -> None:
    """Check that every rank of ``comm`` was given the same ``values``: the inputs of a collective
    entry point that must be global (the domain, parameters, field names, a set given whole on every
    rank).  One allgather of their fingerprints (:func:`fingerprint`); nothing on one process.

    Raises ValueError on every rank, naming ``where`` (the entry point), each value that differs and
    its fingerprint on each rank, e.g. ``Simulation(comm=): every rank must be given the same dt, but
    dt = 0.001 on rank 0; 0.002 on rank 1``."""
    if comm is None or comm.size == 1:
        return
    differ = disagreement(comm.allgather({name: fingerprint(v) for name, v in values.items()}))
    if differ:
        raise ValueError(f"{where}: every rank must be given the same {', '.join(n for n, _ in differ)}, but "
                         + " | ".join(f"{name} = {text}" for name, text in differ))
