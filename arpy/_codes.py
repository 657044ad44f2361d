"""The codes the Fortran core and Python exchange, each table once (the Fortran names in comments).

``tests/test_codes.py`` reads the named parameters of ``fortran/`` and checks that every table
here agrees with them.
"""

from __future__ import annotations

__all__ = ["AR_OPS", "DCPSE_FORMS", "DCPSE_OPERATORS", "METHODS", "POTENTIALS", "RANGE_EXP", "RULES", "STATUS",
           "STENCIL_STATUS"]

#: Status codes of every core routine's ``info`` (``ARPY_OK``, ``ARPY_ERR_*`` in arpy_kinds.f90);
#: :mod:`arpy._errors` turns them into exceptions.
STATUS: dict[str, int] = {
    "OK": 0, "ERR_DIM": 1, "ERR_NONFINITE_X": 2, "ERR_BAD_RC": 3, "ERR_ALLOC": 4, "ERR_NO_RESULT": 5,
    "ERR_SIZE": 6, "ERR_BAD_SKIN": 7, "ERR_DEPTH": 8, "ERR_OUTSIDE": 9, "ERR_METHOD": 10, "ERR_LIST": 11,
    "ERR_OPERATOR": 12, "ERR_RANGE": 13,
}

#: The core's length range (``RANGE_EXP`` in arpy_kinds.f90): |coordinates| and skins <= 2**RANGE_EXP,
#: cutoffs in [2**-RANGE_EXP, 2**RANGE_EXP].
RANGE_EXP = 500

#: Neighbour-list methods of ``arpy_neighbors`` and ``arpy_build_only`` (``METHOD_*`` in arpy_kinds.f90).
METHODS: dict[str, int] = {"brute": 0, "cell": 1, "ar": 2}

#: Cutoff rules of the neighbour lists (``RULE_*`` in arpy_kinds.f90): p and q are neighbours iff
#: |x_p - x_q| <= min(rc_p, rc_q) + skin ("min"), max(rc_p, rc_q) + skin ("max") or
#: (rc_p + rc_q) + skin ("sum").
RULES: dict[str, int] = {"min": 0, "max": 1, "sum": 2}

#: The AR tree's cell operations Op1-Op5 of Awile et al. (2012), §2.2, in ``arpy_ar_ops`` (``AR_OP_*`` in
#: arpy_arops.f90):
#: the cell of a point at a level, the particles of a cell, its children, its parent, its neighbours.
AR_OPS: dict[str, int] = {"find_cell": 1, "lookup": 2, "children": 3, "parent": 4, "neighbors": 5}

#: DC-PSE operator kinds of ``arpy_dcpse`` (``OP_*`` in arpy_dcpse.f90).
DCPSE_OPERATORS: dict[str, int] = {"derivative": 0, "laplacian": 1, "interpolation": 2}

#: DC-PSE operator forms of ``arpy_dcpse`` (``FORM_*`` in arpy_dcpse.f90): "a" off-particle, sum_q eta_q f_q;
#: "b" at the source particles, sum_q eta_q (f_q - f_p).
DCPSE_FORMS: dict[str, int] = {"a": 0, "b": 1}

#: Per-point stencil status of ``arpy_dcpse`` (``DC_*`` in arpy_dcpse.f90), with its meaning.
STENCIL_STATUS: dict[int, str] = {1: "too few neighbours", 2: "singular moment matrix",
                                  3: "ill-conditioned moment matrix"}

#: Pair potentials of the self-organization (``POT_*`` in arpy_selforg.f90): V1, V2 with the fusion
#: core below r = 0.5 (the paper's modified potentials); "V1-PURE", "V2-PURE" without it.
POTENTIALS: dict[str, int] = {"V1": 1, "V2": 2, "V1-PURE": 3, "V2-PURE": 4}
