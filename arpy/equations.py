"""What a simulation solves: :class:`Equations`, its fields, their right-hand side, the motion of the
particles and the conditions at the walls.

:class:`arpy.Simulation` advances the particles and re-organizes them (how the equations are solved);
this module says what the equations are: the names of the fields, their rates from DC-PSE operators
(``nu lap f``, or the user's ``rhs(t, x, fields, ops)``, with ``-f div u`` for conserved densities),
the velocity or flow map, and per field the Dirichlet values or Neumann fluxes at the walls (particles
near a Dirichlet face are snapped onto it and carry its value).
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

import numpy as np

from ._validate import non_finite_rows
from .dcpse.boundary import Condition, Conditions, conditions
from .dcpse.operators import Operators
from .domain import Domain

__all__ = ["SNAP", "STABILITY", "Equations", "NonFiniteError", "StabilityError", "check_finite", "rk4_step", "unstable"]

#: Particles closer than SNAP times their core size to a Dirichlet face are moved onto it (see the
#: ``boundary`` parameter of :class:`arpy.Simulation`).
SNAP = 0.2

#: Per integrator, the largest ``|lambda| dt`` on the negative real axis inside its region of absolute
#: stability (forward Euler: ``|1 + z| <= 1``; classical RK4: ``|1 + z + z^2/2 + z^3/6 + z^4/24| <= 1``).
STABILITY = {"euler": 2.0, "rk4": 2.785}


class NonFiniteError(FloatingPointError):
    """A value of a simulation (a field, a rate, a position) became NaN or infinite."""


class StabilityError(ValueError):
    """A given time step lies above the stability bound of the operators the right-hand side uses (the
    message gives the bound); the step was not taken."""

    @classmethod
    def refusing(cls, why: str, bound: float) -> "StabilityError":
        """The error refusing a given step: ``why`` (:func:`unstable`) and what to give instead."""
        return cls(f"{why}: give dt <= {bound:.3g}, max_dt instead of dt (steps of at most that, at the bound "
                   f"where it is lower), or allow_unstable_dt=True to take it anyway")


def unstable(where: str, integrator: str, bound: float) -> str:
    """Why a step is refused: ``where`` it is, and the stability bound (time unit) of ``integrator`` it
    exceeds."""
    return (f"{where}: dt is above the stability bound {bound:.3g} of {integrator} for the operators of the "
            f"right-hand side (their spectral radius is at most {STABILITY[integrator] / bound:.3g} by "
            f"Gershgorin, see Equations.spectral_radius; {STABILITY[integrator]} / that)")


def check_finite(values: np.ndarray, what: str, where: str, x: np.ndarray, keys: np.ndarray | None = None,
                 names: tuple[str, ...] | None = None) -> None:
    """Raise :class:`NonFiniteError` if ``values`` ((n,), or (n, k) with columns ``names``) holds NaN or
    inf: the message names ``what`` (with the columns that hold them), ``where`` (the step, the
    time), how many particles and the first of them (smallest key; its position)."""
    rows = non_finite_rows(values.reshape(values.shape[0], -1))
    if not rows.size:
        return
    first = rows[np.argmin(keys[rows])] if keys is not None else rows[0]
    if names is not None and values.ndim == 2:
        cols = [names[j] for j in np.flatnonzero(~np.isfinite(values[rows]).all(axis=0))]
        what = f"{what} {', '.join(repr(c) for c in cols)}"
    who = f"key {keys[first]}" if keys is not None else f"index {first}"
    raise NonFiniteError(f"{where}: {what} not finite (NaN or inf) at {rows.size} particle(s), the first ({who}) at "
                         f"x = {np.array2string(x[first], precision=6)}")


class Equations:
    """The fields of a simulation and what changes them (the parameters of :class:`arpy.Simulation`
    of the same names).

    Attributes
    ----------
    names : tuple of str
        The fields' names (one field: ``("f",)``).
    single : bool
        One field given as an array or callable (not a mapping of names).
    bcs : dict
        Per field its resolved wall conditions (None: homogeneous Neumann at every wall).
    walls : list of Conditions
        The conditions with Dirichlet faces (their particles are snapped and pinned).
    wanted : list
        The operators the right-hand side asks for, assembled in one pass from the next stage on.
    """

    def __init__(self, f: np.ndarray | Callable | Mapping, domain: Domain, *, rhs: Callable | None,
                 velocity: Callable | None, flow: Callable | None, nu: float,
                 boundary: Condition | Mapping | None, conservative: bool) -> None:
        if rhs is not None and not callable(rhs):
            raise TypeError("rhs must be a callable rhs(t, x, fields, ops)")
        if conservative and velocity is None:
            raise ValueError("conservative=True needs a velocity (the -f div u term)")
        self.single = not isinstance(f, Mapping)
        self.given: dict[str, Any] = {"f": f} if self.single else dict(f)       # type: ignore[arg-type]
        if not self.given or not all(isinstance(k, str) and k for k in self.given):
            raise ValueError("the fields must be a non-empty mapping of names (str) to values")
        self.names = tuple(self.given)
        self.rhs, self.velocity, self.flow, self.nu = rhs, velocity, flow, float(nu)
        self.conservative = bool(conservative)
        self.domain = domain
        self.bcs = self._conditions(boundary)
        self.walls = [c for c in self.bcs.values() if c is not None and c.has_dirichlet]
        self.wanted: list = ["laplacian"] if rhs is None else []

    def _conditions(self, boundary: Condition | Mapping | None) -> dict[str, Conditions | None]:
        """Per field its resolved conditions (None: homogeneous Neumann at every wall)."""
        if boundary is None:
            per = {}
        elif self.single:
            per = {"f": boundary}
        else:
            if not isinstance(boundary, Mapping) or not set(boundary) <= set(self.names):
                raise ValueError(f"for a system, boundary maps field names {list(self.names)} to conditions, "
                                 f"got {boundary!r}")
            per = dict(boundary)
        out: dict[str, Conditions | None] = {}
        for name in self.names:
            c = conditions(per.get(name), self.domain)
            out[name] = None if c.homogeneous else c
        return out

    def initial(self, x: np.ndarray) -> np.ndarray:
        """The initial values at the particles x (n, d), one column per field, (n, k)."""
        n = x.shape[0]
        columns = []
        for name, v in self.given.items():
            col = np.asarray(v(x) if callable(v) else v, dtype=np.float64)
            what = "f" if self.single else f"field {name!r}"
            if col.shape != (n,):
                raise ValueError(f"{what} must have one value per particle, shape ({n},), got {col.shape}")
            check_finite(col, f"{what}'s initial values are", "at the start", x)
            columns.append(col)
        return np.stack(columns, axis=1)

    @property
    def moves(self) -> bool:
        """Whether anything changes the fields (a right-hand side, diffusion or the conservative term)."""
        return self.rhs is not None or self.nu > 0 or self.conservative

    def named(self, F: np.ndarray) -> dict[str, np.ndarray]:
        """The columns of F (n, k) by field name."""
        return {name: F[:, j] for j, name in enumerate(self.names)}

    def u(self, x: np.ndarray, t: float, F: np.ndarray) -> np.ndarray:
        """The velocity at the particles x (n, d) at time t with the fields F (n, k); zeros without
        one.  The velocity takes the array (n,) of one field, else the dict of the fields."""
        if self.velocity is None:
            return np.zeros_like(x)
        u = np.asarray(self.velocity(x, t, F[:, 0] if self.single else self.named(F)), dtype=np.float64)
        if u.shape != x.shape:
            raise ValueError(f"velocity must return shape {x.shape}, got {u.shape}")
        return u

    def moved(self, x: np.ndarray, t: float, dt: float) -> np.ndarray:
        """The positions (n, d) the flow map gives the particles x (n, d) from t to t + dt."""
        assert self.flow is not None
        out = np.asarray(self.flow(x, t, dt), dtype=np.float64)
        if out.shape != x.shape:
            raise ValueError(f"flow(x, t, dt) must return the new positions, shape {x.shape}, got {out.shape}")
        return out

    def spectral_radius(self, ops: Operators) -> float:
        """A bound on the spectral radius of the rates' linear terms at one stage (Gershgorin discs of the
        operators the rates used: this rank's rows; the stability bound of a step is ``STABILITY /
        that``).  The largest of: ``nu max_p sum_q |L_pq|`` over the Laplacians applied as
        ``ops.laplacian(f)`` (nu: the diffusivity of the built-in right-hand side, or the largest one an
        ``rhs`` declares; 0 leaves them out), and ``max|k| ||L||`` of each ``ops.diffusion(k, f)``; plus
        ``max_p |div u|_p`` with ``conservative`` (the term ``-f div u``).  Not covered (their
        coefficients are the user's): reaction terms, the ``grad k . grad f`` part of a diffusion term,
        and derivatives an ``rhs`` applies with ``ops.gradient``, ``ops.derivative`` or ``ops.divergence``."""
        return ops.radius(self.nu)

    def snap(self, x: np.ndarray, eps: np.ndarray) -> np.ndarray:
        """x with the particles closer than SNAP times their core size eps to a Dirichlet face on it."""
        for walls in self.walls:
            x = walls.snap(x, eps, SNAP)
        return x

    def pin(self, F: np.ndarray, x: np.ndarray, t: float, rates: bool = False) -> np.ndarray:
        """F with the particles on each field's Dirichlet faces set to the faces' values at t (rates:
        set to 0 instead)."""
        out = F
        for j, name in enumerate(self.names):
            bc = self.bcs[name]
            if bc is not None and bc.has_dirichlet:
                idx, vals = bc.on_walls(x, t)
                if idx.size:
                    out = F.copy() if out is F else out
                    out[idx, j] = 0.0 if rates else vals
        return out

    def operators(self, op_of: Callable, t: float, x: np.ndarray, F: np.ndarray, source_x: np.ndarray,
                  source_F: np.ndarray) -> Operators:
        """The DC-PSE operators at the points x with the fields F there, over the sources at source_x
        with the fields source_F (``op_of(wanted, conditions)`` builds them)."""
        named = self.named(F)
        src = named if source_F is F else self.named(source_F)
        return Operators(op_of, self.wanted, t=t, x=x, fields=named, source_x=source_x, source_fields=src,
                         bcs=self.bcs)

    def rates(self, ops: Operators, F: np.ndarray, u: np.ndarray | None) -> np.ndarray:
        """The right-hand side (n, k) from the operators (and -F div u, conservative)."""
        if self.rhs is None:                           # (diffusion of every field)
            rates = np.zeros_like(F)
            if self.nu > 0:
                for j, name in enumerate(self.names):
                    rates[:, j] = self.nu * ops.laplacian(name)
        else:
            given = self.rhs(ops.t, ops.x, ops.fields, ops)
            if self.single and not isinstance(given, Mapping):
                given = {"f": given}
            if not isinstance(given, Mapping) or not set(given) <= set(self.names):
                raise ValueError(f"rhs must return a mapping of some of the field names {list(self.names)} to "
                                 f"rates, got {type(given).__name__}")
            rates = np.zeros_like(F)
            for name, r in given.items():
                r = np.asarray(r, dtype=np.float64)
                if r.shape != (F.shape[0],):
                    raise ValueError(f"rhs: the rate of {name!r} must have shape ({F.shape[0]},), got {r.shape}")
                rates[:, self.names.index(name)] = r
        if self.conservative and u is not None:
            div = ops.divergence(u)
            ops.pointwise = float(np.abs(div).max(initial=0.0))
            rates = rates - F * div[:, None]
        if self.rhs is not None:
            check_finite(rates, "the rates (rhs) of", f"t = {ops.t:.6g}", ops.x, names=self.names)
        return rates


def rk4_step(rates: Callable[[np.ndarray, np.ndarray, float], tuple[np.ndarray, np.ndarray]], x: np.ndarray,
             f: np.ndarray, t: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """One classical RK4 step of dx/dt = u, df/dt = r with ``(u, r) = rates(x, f, t)``; returns the new
    positions (not wrapped into a periodic box) and values."""
    u1, k1 = rates(x, f, t)
    u2, k2 = rates(x + dt / 2 * u1, f + dt / 2 * k1, t + dt / 2)
    u3, k3 = rates(x + dt / 2 * u2, f + dt / 2 * k2, t + dt / 2)
    u4, k4 = rates(x + dt * u3, f + dt * k3, t + dt)
    return x + dt / 6 * (u1 + 2 * u2 + 2 * u3 + u4), f + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
