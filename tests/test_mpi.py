"""The distributed layer under MPI: ``mpiexec -n P`` (P = 1, 2, 4) runs tests/mpi_scenario.py in
subprocesses with a timeout; its boxes, ownership and neighbour rows must equal the serial ones
computed here.  MPI comes with the test environment (mpi4py and the mpich wheel): a missing MPI
fails these tests, it does not skip them."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import arpy
from arpy.distributed import bisect

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from mpi_scenario import scenario  # noqa: E402


def mpiexec() -> str:
    """The mpiexec beside this interpreter (the mpich wheel's), else the one on PATH."""
    local = Path(sys.executable).parent / "mpiexec"
    found = str(local) if local.exists() else shutil.which("mpiexec")
    assert found, "no mpiexec: install the test extra (mpi4py and mpich) or an MPI with mpiexec"
    return found


@pytest.mark.parametrize("periodic", [False, True])
def test_mpi_ranks_decompose_migrate_and_exchange_like_the_serial_rules(periodic):
    x, rc, keys, box = scenario(7, periodic)
    serial = arpy.neighbor_list(x, rc, symmetric=False, domain=box if periodic else None)
    want = {int(keys[p]): np.sort(keys[serial.neighbors(p)]).tolist() for p in range(len(x))}
    env = dict(os.environ, OMP_NUM_THREADS="1")
    for parts in (1, 2, 4):
        run = subprocess.run([mpiexec(), "-n", str(parts), sys.executable, str(HERE / "mpi_scenario.py"), "7",
                              "periodic" if periodic else "free"], capture_output=True, text=True, timeout=120,
                             env=env)
        assert run.returncode == 0, run.stderr[-3000:]
        got = json.loads(run.stdout)
        dec, owner = bisect(x, parts, domain=box)
        assert got["lo"] == dec.lo.tolist() and got["hi"] == dec.hi.tolist()
        assert [sorted(k) for k in got["keys"]] == [sorted(keys[owner == r].tolist()) for r in range(parts)]
        assert {int(k): v for k, v in got["rows"].items()} == want
