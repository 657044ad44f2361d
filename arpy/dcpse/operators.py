"""The DC-PSE operators a simulation hands to a right-hand side: one assembly per stage, every term.

:class:`Operators` wraps one :class:`arpy.dcpse.domain.DomainDCPSE` on the particles of a stage (or,
at a re-organization with forward Euler, from the old particles to the new ones: variant (ii)
of §2.2) and applies its operators to the simulation's fields by name, each field with its own
boundary conditions (:mod:`arpy.dcpse.boundary`).  The matrices are assembled once, on first use, and
shared by every term and field; a simulation remembers which operators its right-hand side
asked for and assembles them all in one pass from the next stage on.
"""

from __future__ import annotations

from typing import Callable, Mapping, Sequence, Union

import numpy as np
import scipy.sparse as sp

from .boundary import Conditions
from .domain import DomainDCPSE
from .kernel import gradient_indices
from .rows import abs_row_sums

__all__ = ["Operators", "Reused"]

#: What an operator acts on: a field's name, an array at the operator's source particles, or a
#: callable ``(x (m, d), fields) -> (m,)`` evaluated at the sources (ghosts included).
Operand = Union[str, np.ndarray, Callable[[np.ndarray, Mapping[str, np.ndarray]], np.ndarray]]


class Operators:
    """DC-PSE operators at the particles of one stage, applied to fields by name.

    Built by :class:`arpy.Simulation` for its right-hand side ``rhs(t, x, fields, ops)``; the
    results are values at the particles ``x`` (n,).

    An operand is a field's name (its values on the sources with its boundary conditions: the
    usual case), an array at the source particles (``source_x``; ghosts carry the values of their
    particles, i.e. homogeneous Neumann at walls), or a callable ``(x, fields) -> values`` that is
    evaluated at every source, ghosts included, with the fields' values there (e.g. a diffusivity
    k(x) or k(f)).  At the stages of a step the sources are the particles themselves; at a
    re-organization with forward Euler they are the old particles (``source_x``,
    ``source_fields``), so names and callables are the operands that work at every stage.

    Attributes
    ----------
    t : float
        The stage time.
    x : array (n, d)
        The points where the right-hand side is wanted (the particles).
    fields : dict of arrays (n,)
        The fields at x.
    source_x : array (n_src, d)
        The particles the operators read (without ghosts).
    source_fields : dict of arrays (n_src,)
        The fields there.
    """

    def __init__(self, build: Callable[[list, Conditions | None], DomainDCPSE], wanted: list, *, t: float,
                 x: np.ndarray, fields: dict[str, np.ndarray], source_x: np.ndarray,
                 source_fields: dict[str, np.ndarray], bcs: dict[str, Conditions | None]) -> None:
        self.t, self.x, self.fields = t, x, fields
        self.source_x, self.source_fields = source_x, source_fields
        self._build, self._wanted, self._bcs = build, wanted, bcs
        self._ops: dict[bytes | None, DomainDCPSE] = {}
        self._mats: dict[tuple, sp.csr_matrix] = {}
        self._ext: dict[str, np.ndarray] = {}
        self._norms: dict[tuple, float] = {}
        self._bcs_of: dict[bytes | None, Conditions | None] = {}
        self._bare: set[bytes | None] = set()        # the groups whose Laplacian was applied as laplacian(f)
        self._terms: list[tuple[float, bytes | None]] = []    # diffusion(k, f): max|k| and the group
        #: The largest absolute coefficient of a pointwise linear term of the rates (the conservative
        #: ``-f div u``: ``max |div u|``), part of :meth:`radius`.
        self.pointwise = 0.0

    # ------------------------------------------------------------------ plumbing
    def _group(self, name: str | None) -> tuple[bytes | None, Conditions | None]:
        """The operator set a field reads: one per pattern of Dirichlet faces (their boundary
        particles and one-sided stencils), the plain one for the other fields and every other operand."""
        bc = None if name is None else self._bcs.get(name)
        if bc is None or not bc.has_dirichlet:
            return None, None
        return bc.dirichlet_faces.tobytes(), bc

    def _op(self, name: str | None = None) -> DomainDCPSE:
        key, bc = self._group(name)
        if key not in self._ops:
            self._ops[key] = self._build(list(self._wanted), bc)
            self._bcs_of[key] = bc
        return self._ops[key]

    @property
    def op(self) -> DomainDCPSE:
        """The DC-PSE operator set of the fields without Dirichlet faces (built on first use with every
        operator asked for so far)."""
        return self._op()

    @property
    def built(self) -> list[DomainDCPSE]:
        """The operator sets built so far."""
        return list(self._ops.values())

    @property
    def d(self) -> int:
        return int(self.x.shape[1])

    def _matrix(self, key: str | tuple[int, ...], name: str | None) -> sp.csr_matrix:
        """The operator "laplacian" or d^alpha (alpha a tuple) of the field's operator set, assembled once."""
        group = self._group(name)[0]
        if (key, group) not in self._mats:
            if key not in self._wanted:
                self._wanted.append(key)
            op = self._op(name)
            self._mats[key, group] = op.laplacian() if isinstance(key, str) else op.derivative(key)
        return self._mats[key, group]

    def row_norm(self, key: str | tuple[int, ...], name: str | None = None) -> float:
        """The largest sum of absolute weights over the rows of an operator ("laplacian" or d^alpha) of
        the field's operator set (its infinity norm, the largest Gershgorin radius; 0 without rows)."""
        return float(abs_row_sums(self._matrix(key, name)).max(initial=0.0))

    @property
    def diffusivity(self) -> float:
        """The largest ``max|k|`` of the terms of :meth:`diffusion` applied (0 without), length^2 / time."""
        return max((k for k, _ in self._terms), default=0.0)

    def radius(self, nu: float) -> float:
        """A bound on the spectral radius of the linear terms these operators were applied in, from the
        row norms (Gershgorin) of their matrices: the largest of ``nu ||L||`` over the Laplacians applied
        by :meth:`laplacian` (nu: their largest coefficient, which only the caller knows) and ``max|k|
        ||L||`` over the terms of :meth:`diffusion` (their ``grad k . grad f`` part is not covered); plus
        :attr:`pointwise`.  Unit 1 / time with nu and k in length^2 / time."""
        rho = max([nu * self._norm("laplacian", group) for group in self._bare] +
                  [k * self._norm("laplacian", group) for k, group in self._terms], default=0.0)
        return rho + self.pointwise

    def _norm(self, key: str | tuple[int, ...], group: bytes | None) -> float:
        """:meth:`row_norm` of an assembled matrix by its group, once per stage; with Dirichlet faces, of
        its part acting on the free values: without the rows of the particles on those faces (their
        rates are held at 0) and the columns of the boundary particles and their images (the walls'
        values, data)."""
        if (key, group) not in self._norms:
            m = self._mats[key, group]
            if group is None:                           # (the Laplacian's, as its operator set weighed it)
                sums = self._ops[group].laplacian_row_sums() if key == "laplacian" else abs_row_sums(m)
            else:
                op, bc = self._ops[group], self._bcs_of[group]
                assert bc is not None                   # (a group with Dirichlet faces has its conditions)
                data = op.wall_columns
                free = sp.csr_matrix((np.where(data[m.indices], 0.0, m.data), m.indices, m.indptr), shape=m.shape)
                sums = abs_row_sums(free)
                sums[bc.on_walls(self.x, self.t)[0]] = 0.0
            self._norms[key, group] = float(sums.max(initial=0.0))
        return self._norms[key, group]

    def _values(self, f: Operand) -> tuple[str | None, np.ndarray]:
        """(the field's name or None, the operand's values on every source of its operator set)."""
        if isinstance(f, str):
            if f not in self.source_fields:
                raise KeyError(f"no field {f!r}; the fields are {sorted(self.source_fields)}")
            if f not in self._ext:
                self._ext[f] = self._op(f).extend(self.source_fields[f], self._bcs.get(f), self.t)
            return f, self._ext[f]
        op = self.op
        if callable(f):
            out = np.asarray(f(op.sources, self._every_field()), dtype=np.float64)
            if out.shape != (op.sources.shape[0],):
                raise ValueError(f"an operand callable must return shape ({op.sources.shape[0]},), got {out.shape}")
            return None, out
        arr = np.asarray(f, dtype=np.float64)
        if arr.shape != (self.source_x.shape[0],):
            raise ValueError(f"an operand array must have the sources' shape ({self.source_x.shape[0]},), "
                             f"got {arr.shape}; at a re-organization the sources are the old particles: "
                             "give a field name or a callable")
        return None, op.extend(arr)

    def _every_field(self) -> dict[str, np.ndarray]:
        """Every field on the plain operator set's sources (ghosts by each field's conditions; across a
        Dirichlet face, odd images)."""
        op = self.op
        return {name: self._values(name)[1] if self._group(name)[0] is None else
                op.extend(v, self._bcs.get(name), self.t) for name, v in self.source_fields.items()}

    def at_points(self, f: Operand) -> np.ndarray:
        """An operand's values at the points x (n,): a field's values, a callable evaluated there,
        an array interpolated from the sources."""
        if isinstance(f, str):
            return self.fields[f]
        if callable(f):
            out = np.asarray(f(self.x, self.fields), dtype=np.float64)
            if out.shape != (self.x.shape[0],):
                raise ValueError(f"an operand callable must return shape ({self.x.shape[0]},), got {out.shape}")
            return out
        _, arr = self._values(f)
        return arr[:self.x.shape[0]] if self.source_x is self.x else self.op.interpolation() @ arr

    def interpolate(self, name: str, bounded: bool = False) -> np.ndarray:
        """A field's source values at the points x (n,) by the interpolating kernel (a
        re-organization's old -> new; see :meth:`arpy.dcpse.domain.DomainDCPSE.interpolate`)."""
        return self._op(name).interpolate(self.source_fields[name], bounded=bounded, bc=self._bcs.get(name),
                                          t=self.t)

    # ------------------------------------------------------------------ operators
    def laplacian(self, f: Operand) -> np.ndarray:
        """The Laplacian of f at the points, (n,), unit f / length^2."""
        name, v = self._values(f)
        self._bare.add(self._group(name)[0])
        return self._matrix("laplacian", name) @ v

    def derivative(self, alpha: Sequence[int], f: Operand) -> np.ndarray:
        """The derivative d^alpha f (alpha a multi-index of d ints) at the points, (n,)."""
        alpha = tuple(int(a) for a in alpha)
        if len(alpha) != self.d or min(alpha) < 0:
            raise ValueError(f"alpha must be {self.d} integers >= 0, got {alpha}")
        name, v = self._values(f)
        return self._matrix(alpha, name) @ v

    def gradient(self, f: Operand) -> np.ndarray:
        """The gradient of f at the points, (n, d), unit f / length."""
        name, v = self._values(f)
        return np.stack([self._matrix(a, name) @ v for a in gradient_indices(self.d)], axis=1)

    def divergence(self, v: np.ndarray | Callable[[np.ndarray, Mapping[str, np.ndarray]], np.ndarray]) -> np.ndarray:
        """The divergence of a vector field at the points, (n,).

        v: an array (n_src, d) at the source particles, whose ghosts take the slip-wall image (the
        component normal to a wall odd, the others even; periodic images unchanged), or a callable
        ``(x, fields) -> (m, d)`` evaluated at every source."""
        op = self.op
        if callable(v):
            vs = np.asarray(v(op.sources, self._every_field()), np.float64)
            if vs.shape != op.sources.shape:
                raise ValueError(f"a vector callable must return shape {op.sources.shape}, got {vs.shape}")
        else:
            vs = op.slip(v)
        return sum(self._matrix(a, None) @ vs[:, k] for k, a in enumerate(gradient_indices(self.d)))

    def diffusion(self, k: float | Operand, f: Operand) -> np.ndarray:
        """div(k grad f) at the points, (n,): ``k lap f + grad k . grad f`` with k a number or an
        operand (a variable diffusivity, unit length^2 / time)."""
        name, v = self._values(f)
        group = self._group(name)[0]
        lap = self._matrix("laplacian", name) @ v
        if not isinstance(k, (str, np.ndarray)) and not callable(k):
            self._terms.append((abs(float(k)), group))
            return float(k) * lap
        kp, gk = self.at_points(k), self.gradient(k)
        self._terms.append((float(np.abs(kp).max(initial=0.0)), group))
        return kp * lap + (gk * self.gradient(f)).sum(axis=1)


class Reused:
    """Operator sets kept from one stage to the next while nothing they are built from changes.

    Particles that do not move between re-organizations (diffusion without a flow, fixed-particle
    stepping) give the same operator sets at every stage: the same positions, core sizes and keys
    on every rank, and the same build options, build bitwise the same sets, so the last stage's are
    used again instead.  :meth:`at` starts a stage; :meth:`get` hands out a set by its key, built once
    per run of equal stages."""

    def __init__(self) -> None:
        self._of: tuple[tuple[np.ndarray, ...], tuple] | None = None
        self._sets: dict[object, DomainDCPSE] = {}

    def at(self, arrays: Sequence[np.ndarray], options: tuple, agree: Callable[[bool], bool]) -> "Reused":
        """Start a stage whose sets are built from ``arrays`` (compared bit for bit with the last
        stage's) and ``options`` (compared with ==): the last stage's sets stay when both are the same
        on every rank (``agree(same)``: whether they are on all of them; a collective call on ranks),
        else they are dropped.  Returns self."""
        held = self._of
        same = held is not None and held[1] == options and len(held[0]) == len(arrays) and all(
            a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes() for a, b in zip(arrays, held[0]))
        if not agree(same):
            self._of, self._sets = (tuple(np.array(a, copy=True) for a in arrays), options), {}
        return self

    def get(self, key: object, build: Callable[[], DomainDCPSE]) -> DomainDCPSE:
        """The set of ``key`` (e.g. its operators and conditions), ``build()`` the first time in a stage
        whose sets were dropped."""
        if key not in self._sets:
            self._sets[key] = build()
        return self._sets[key]

    def clear(self) -> None:
        """Drop every set (the particles are about to change)."""
        self._of, self._sets = None, {}
