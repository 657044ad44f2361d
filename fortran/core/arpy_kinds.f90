!> Kinds, status codes and neighbour-list method codes shared by the arpy core.
!>
!> Every public routine of the core returns one of the ARPY_* codes below in
!> its `info` argument; `arpy/_errors.py` is the one place that turns them
!> into Python exceptions.
module arpy_kinds
  use, intrinsic :: iso_fortran_env, only: real64, int64
  implicit none
  private

  integer, parameter, public :: dp = real64   !< working precision
  integer, parameter, public :: i8 = int64    !< index kind for counts that can exceed 2**31

  integer, parameter, public :: ARPY_OK = 0
  integer, parameter, public :: ARPY_ERR_DIM = 1          !< d not in {2, 3}
  integer, parameter, public :: ARPY_ERR_NONFINITE_X = 2  !< NaN or Inf in a position
  integer, parameter, public :: ARPY_ERR_BAD_RC = 3       !< cutoff not finite and > 0
  integer, parameter, public :: ARPY_ERR_ALLOC = 4        !< allocation failed
  integer, parameter, public :: ARPY_ERR_NO_RESULT = 5    !< nothing to hand back
  integer, parameter, public :: ARPY_ERR_SIZE = 6         !< caller's array has the wrong size
  integer, parameter, public :: ARPY_ERR_BAD_SKIN = 7     !< skin not finite and >= 0
  integer, parameter, public :: ARPY_ERR_DEPTH = 8        !< AR tree deeper than int64 keys allow
  integer, parameter, public :: ARPY_ERR_OUTSIDE = 9      !< particle outside the given domain
  integer, parameter, public :: ARPY_ERR_METHOD = 10      !< unknown method code
  integer, parameter, public :: ARPY_ERR_LIST = 11        !< inconsistent neighbour list
  integer, parameter, public :: ARPY_ERR_OPERATOR = 12    !< invalid operator request
  integer, parameter, public :: ARPY_ERR_RANGE = 13       !< a length outside the core's range (RANGE_EXP)

  !> Neighbour-list methods (the `method` of arpy_neighbors and arpy_build_only)
  integer, parameter, public :: METHOD_BRUTE = 0   !< brute force
  integer, parameter, public :: METHOD_CELL = 1    !< uniform cell list
  integer, parameter, public :: METHOD_AR = 2      !< adaptive-resolution cell list

  !> Cutoff rules of the neighbour lists (the `rule` of arpy_neighbors and friends): p and q are
  !> neighbours iff |x_p - x_q| <= reach(p, q), with reach = min(rc_p, rc_q) + skin (RULE_MIN, the
  !> adaptive-resolution gather rule), max(rc_p, rc_q) + skin (RULE_MAX, SPH) or
  !> (rc_p + rc_q) + skin (RULE_SUM, contacts), each evaluated in that order in double precision.
  integer, parameter, public :: RULE_MIN = 0
  integer, parameter, public :: RULE_MAX = 1
  integer, parameter, public :: RULE_SUM = 2

  !> Lengths the core works on lie in its range: |coordinates|, skins and
  !> domain corners <= 2**RANGE_EXP, cutoffs in [2**-RANGE_EXP, 2**RANGE_EXP].
  !> Then squared distances and cutoffs neither overflow nor lose digits to
  !> underflow (a coordinate below 2**-RANGE_EXP only rounds far below any
  !> cutoff).  Python brings other inputs into this range by an exact
  !> power-of-two scaling (arpy/neighbors.py, core_exponent).
  integer, parameter, public :: RANGE_EXP = 500
end module arpy_kinds
