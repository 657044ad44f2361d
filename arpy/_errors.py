"""The one place where status codes of the Fortran core become Python exceptions."""

from __future__ import annotations

from ._codes import STATUS

__all__ = ["ArpyError", "TreeDepthError", "raise_for_info"]


class ArpyError(RuntimeError):
    """An internal failure of the arpy core (allocation, hand-off) rather than bad input."""


class TreeDepthError(ValueError):
    """The cutoffs need more levels than the AR tree's 64-bit cell keys hold (30 in 2D, 20 in 3D):
    the largest extent over the smallest cutoff is too large for the adaptive-resolution cell list.
    The uniform cell list (``method="cell"``) has no such limit."""


# status code -> (exception class, message template); {bad} is a 0-based particle index.
_CODES: dict[int, tuple[type[Exception], str]] = {
    STATUS["ERR_DIM"]: (ValueError, "positions must have d = 2 or d = 3 columns"),
    STATUS["ERR_NONFINITE_X"]: (ValueError, "position of particle {bad} is not finite (NaN or Inf)"),
    STATUS["ERR_BAD_RC"]: (ValueError, "cutoff radius of particle {bad} is not a finite positive number"),
    STATUS["ERR_ALLOC"]: (MemoryError, "the arpy core could not allocate memory"),
    STATUS["ERR_NO_RESULT"]: (ArpyError, "no result is waiting to be collected from the arpy core"),
    STATUS["ERR_SIZE"]: (ArpyError, "result size mismatch between the arpy core and Python"),
    STATUS["ERR_BAD_SKIN"]: (ValueError, "skin must be a finite number >= 0"),
    STATUS["ERR_DEPTH"]: (TreeDepthError, "adaptive-resolution tree too deep: the cutoffs need more levels than the adaptive-resolution tree's 64-bit cell keys "
                        "hold (30 in 2D, 20 in 3D: extent / smallest cutoff up to ~2**30 or 2**20); "
                        "use the uniform cell list (method='cell' or 'auto')"),
    STATUS["ERR_OUTSIDE"]: (ValueError, "particle {bad} lies outside the given domain"),
    STATUS["ERR_METHOD"]: (ValueError, "unknown method code passed to the arpy core"),
    STATUS["ERR_LIST"]: (ValueError, "inconsistent neighbour list (offsets not increasing or indices out of range)"),
    STATUS["ERR_OPERATOR"]: (ValueError, "invalid DC-PSE operator request (order, multi-index or form)"),
    STATUS["ERR_RANGE"]: (ValueError, "a length lies outside the range the core computes with (|coordinates| <= 2**500, "
                     "cutoffs in [2**-500, 2**500]) even after arpy's exact power-of-two scaling"),
}


def raise_for_info(info: int, bad: int = 0, context: str = "") -> None:
    """Raise the exception that matches a core status code; return if ``info == 0``.

    Parameters
    ----------
    info : status code returned by a core routine.
    bad : 1-based index of the offending particle as reported by the core (0 = none).
    context : optional prefix naming the operation, e.g. ``"neighbor_list"``.
    """
    if info == STATUS["OK"]:
        return
    cls, template = _CODES.get(int(info), (ArpyError, f"arpy core returned unknown status {int(info)}"))
    message = template.format(bad=int(bad) - 1)
    raise cls(f"{context}: {message}" if context else message)
