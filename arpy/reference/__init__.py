"""Pure NumPy reference implementations, written from the papers for clarity.

They exist to be compared against: every Fortran kernel of arpy is
cross-validated against its reference in the test suite, and the references
themselves are checked against brute force or analytic results.
"""

from .bisection import weighted_bisection
from .neighbors import brute_force_cross_pairs, brute_force_pairs, cell_list_pairs, morton_order, pair_reach

__all__ = ["brute_force_cross_pairs", "brute_force_pairs", "cell_list_pairs", "morton_order", "pair_reach",
           "weighted_bisection"]
