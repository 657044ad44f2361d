"""Fuzzing the surfaces of a simulation with hypothesis: right-hand sides, wall conditions, state
files and the inputs that the ranks must agree on.

As in :mod:`test_fuzz`, most inputs are valid and must give the answer of an independent oracle
(one Euler step by hand, the faces a condition names, the arrays that were written, one process);
the others carry one defect and must be refused with a documented exception that says what is wrong.
Each test counts the examples that reach its check (:class:`test_fuzz.Reach`) and requires most
of them to.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import arpy
from arpy.dcpse.boundary import Dirichlet, Neumann, conditions, face_names
from arpy.distributed import run_threads
from arpy.io import StateFileError
from test_fuzz import FUZZ, Reach

BOX = arpy.Domain([1.0, 1.0], periodic=True)


def lattice(m: int = 8, seed: int = 0) -> arpy.Particles:
    """m x m jittered particles in the periodic unit box, core sizes 3 / m (about 28 neighbours)."""
    g = (np.stack(np.meshgrid(np.arange(m), np.arange(m), indexing="ij"), -1).reshape(-1, 2) + 0.5) / m
    x = g + np.random.default_rng(seed).uniform(-0.2, 0.2, g.shape) / m
    return arpy.Particles(x, np.full(m * m, 1.0 / m), 3.0, domain=BOX)


PS = lattice()
F0 = {"u": np.sin(2 * np.pi * PS.x[:, 0]), "v": np.cos(2 * np.pi * PS.x[:, 1])}
DT = 0.01
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@st.composite
def rhs_outputs(draw):
    """(kind, what the right-hand side returns)."""
    n = PS.n
    kind = draw(st.sampled_from(["valid"] * 7 + ["not finite", "shape", "name", "type"]))
    rate = np.array(draw(st.lists(finite, min_size=n, max_size=n)))
    if kind == "not finite":
        rate[draw(st.integers(0, n - 1))] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    if kind == "shape":
        rate = rate[:draw(st.integers(0, n - 1))]
    name = draw(st.sampled_from(["u", "v"])) if kind != "name" else draw(st.sampled_from(["w", "", "U"]))
    return kind, ([name, rate] if kind == "type" else {name: rate})


def test_simulation_rhs_fuzz():
    """A right-hand side returning rates by hand: a valid one gives exactly F + dt r (Euler, no
    motion, no re-organization), or NonFiniteError naming the field if that overflows; a rate that is
    not finite is named with its field and particle; wrong shapes, names and types are refused (with a
    fixed dt the simulation calls a new rhs already at construction, to bound its operators)."""
    reach = Reach()

    @FUZZ
    @given(rhs_outputs())
    def check(case):
        reach.example()
        kind, out = case
        def run():
            arpy.Simulation(PS, F0, rhs=lambda t, x, fields, ops: out, D0=1 / 8, dt=DT, reorganize_every=0).step()

        if kind == "valid":
            sim = arpy.Simulation(PS, F0, rhs=lambda t, x, fields, ops: out, D0=1 / 8, dt=DT, reorganize_every=0)
            (name, rate), = out.items()
            j = sim.names.index(name)
            with np.errstate(all="ignore"):
                want = sim.F.copy()
                want[:, j] = want[:, j] + DT * rate
            if not np.all(np.isfinite(want)):
                with pytest.raises(arpy.NonFiniteError, match=rf"step 1 .*the field\(s\) '{name}' not finite"):
                    sim.step()
                reach.note("the step overflowed")
                return
            sim.step()
            np.testing.assert_array_equal(sim.F, want)
            reach.check()
        elif kind == "not finite":
            (name, rate), = out.items()
            first = int(np.flatnonzero(~np.isfinite(rate))[0])
            with pytest.raises(arpy.NonFiniteError, match=rf"rates \(rhs\) of '{name}' not finite .*\(index {first}\)"):
                run()
            reach.check()
        else:
            with pytest.raises(ValueError, match="rhs"):
                run()
            reach.check()

    check()
    reach.assert_most()


values = st.one_of(finite, finite, finite, st.sampled_from([np.nan, np.inf, "one", None]))


@st.composite
def wall_specs(draw):
    """(a Domain, a condition spec of faces -> Dirichlet/Neumann of raw values, or one condition)."""
    d = draw(st.sampled_from([2, 3]))
    periodic = draw(st.lists(st.booleans(), min_size=d, max_size=d))
    domain = arpy.Domain([1.0] * d, periodic=periodic)
    kinds = st.sampled_from([Dirichlet, Neumann])
    if draw(st.integers(0, 5)) == 0:
        return domain, (draw(kinds), draw(values))
    faces = draw(st.lists(st.sampled_from(face_names(d) + ("w-",)), unique=True, max_size=2 * d))
    return domain, {f: (draw(kinds), draw(values)) for f in faces}


def test_wall_conditions_fuzz():
    """Conditions on boxes with periodic and wall axes: values that are not finite numbers, faces that
    do not exist or are periodic, and a condition on a box without walls are refused, naming the
    value or face; the others give exactly the Dirichlet faces named (one condition: every wall)."""
    reach = Reach()

    @FUZZ
    @given(wall_specs())
    def check(case):
        reach.example()
        domain, raw = case
        items = [raw] if isinstance(raw, tuple) else list(raw.values())
        if any(v is None or isinstance(v, str) or not np.isfinite(v) for _, v in items):
            with pytest.raises(ValueError, match="must be a finite number or a callable"):
                [kind(v) for kind, v in items]
            reach.check()
            return
        walls = [(a, s) for a in range(domain.d) for s in (0, 1) if not domain.periodic[a]]
        names = face_names(domain.d)
        if isinstance(raw, tuple):
            spec, dirichlet = raw[0](raw[1]), {w for w in walls} if raw[0] is Dirichlet else set()
            bad = None if walls else "no walls"
        else:
            spec = {f: kind(v) for f, (kind, v) in raw.items()}
            unknown = [f for f in spec if f not in names]
            periodic = [f for f in spec if f in names and domain.periodic[names.index(f) // 2]]
            bad = "unknown faces" if unknown else (re.escape(f"face '{periodic[0]}' is periodic") if periodic else None)
            dirichlet = {(names.index(f) // 2, names.index(f) % 2) for f, c in spec.items()
                         if isinstance(c, Dirichlet) and not unknown}
        if bad is not None:
            with pytest.raises(ValueError, match=bad):
                conditions(spec, domain)
            reach.check()
            return
        got = conditions(spec, domain)
        assert {(int(a), int(s)) for a, s in np.argwhere(got.dirichlet_faces)} == dirichlet
        assert got.has_dirichlet == bool(dirichlet)
        reach.check()

    check()
    reach.assert_most()


@pytest.fixture(scope="module")
def state_file(tmp_path_factory) -> tuple[Path, arpy.Simulation]:
    sim = arpy.Simulation(PS, F0, nu=0.01, D0=1 / 8, reorganize_every=0)
    sim.step()
    path = sim.save_state(tmp_path_factory.mktemp("state") / "state.npz")
    return path, sim


def test_state_file_fuzz(state_file, tmp_path_factory):
    """A state file cut short, with bytes changed or appended, or emptied: load_state either raises
    one StateFileError naming the file or continues from exactly the state written."""
    path, sim = state_file
    data = path.read_bytes()
    where = tmp_path_factory.mktemp("damaged")
    reach = Reach()

    @settings(FUZZ, max_examples=60)
    @given(st.sampled_from(["cut", "flip", "append", "empty"]), st.integers(0, len(data) - 1),
           st.integers(1, 255))
    def check(how, at, byte):
        reach.example()
        bad = {"cut": data[:at], "empty": b"", "append": data + bytes([byte]) * (at % 64 + 1),
               "flip": data[:at] + bytes([data[at] ^ byte]) + data[at + 1:]}[how]
        target = where / "state.npz"
        shutil.copy(path.with_suffix(".json"), target.with_suffix(".json"))
        target.write_bytes(bad)
        back = arpy.Simulation(PS, F0, nu=0.01, D0=1 / 8, reorganize_every=0)
        try:
            back.load_state(target)
        except StateFileError as exc:
            assert str(target) in str(exc)
            reach.note("refused")
        else:
            np.testing.assert_array_equal(back.x, sim.x)
            np.testing.assert_array_equal(back.F, sim.F)
            assert (back.t, back.steps) == (sim.t, sim.steps)
        reach.check()

    check()
    reach.assert_most()


PARAMETERS = {"D0": (1 / 8, 0.2), "dt": (0.01, 0.02), "nu": (0.01, 0.03), "reorganize_every": (0, 3),
              "integrator": ("euler", "rk4")}


def test_inputs_the_ranks_must_agree_on_fuzz():
    """Two thread ranks given the same simulation but for one parameter (or none): every rank refuses
    with the parameter's name and both values, or (none differs) both run the step of one process."""
    reach = Reach()
    one = arpy.Simulation(PS, F0, nu=0.01, D0=1 / 8, dt=0.01, reorganize_every=0)
    one.step()

    @settings(FUZZ, max_examples=15)
    @given(st.sampled_from([None, *PARAMETERS]))
    def check(differs):
        reach.example()

        def rank(comm):
            kw = {k: v[0] for k, v in PARAMETERS.items()}
            if differs is not None and comm.rank == 1:
                kw[differs] = PARAMETERS[differs][1]
            try:
                sim = arpy.Simulation(PS, F0, comm=comm, **kw)
            except ValueError as exc:
                return str(exc)
            sim.step()
            return sim.gather()[3]

        got = run_threads(2, rank)
        if differs is None:
            for F in got:
                np.testing.assert_array_equal(F, one.F)
        else:
            for message in got:
                assert isinstance(message, str) and f"same {differs}" in message, message
        reach.check()

    check()
    reach.assert_most()
