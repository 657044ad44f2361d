!> Input validation shared by every entry point of the core.
module arpy_checks
  use, intrinsic :: ieee_arithmetic, only: ieee_is_finite
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_DIM, ARPY_ERR_NONFINITE_X, &
       ARPY_ERR_BAD_RC, ARPY_ERR_BAD_SKIN, ARPY_ERR_LIST, ARPY_ERR_RANGE, ARPY_ERR_SIZE, RANGE_EXP
  use arpy_threads, only: team_size, MIN_PARALLEL_ROWS
  implicit none
  private

  public :: check_particles, check_csr

  real(dp), parameter :: big = 2.0_dp**RANGE_EXP, small = 2.0_dp**(-RANGE_EXP)

contains

  !> Check dimension, positions (finite) and cutoffs (finite, > 0), skin
  !> (finite, >= 0), then that lengths lie in the core's range
  !> (ARPY_ERR_RANGE): |x|, skin <= 2**RANGE_EXP, 2**-RANGE_EXP <= rc <= 2**RANGE_EXP.
  !> bad returns the 1-based index of the first offending particle (0 if none
  !> or if the dimension/skin is at fault).
  subroutine check_particles(d, n, x, rc, skin, info, bad)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), rc(n), skin
    integer, intent(out) :: info, bad
    integer :: p, nout
    info = ARPY_OK
    bad = 0
    if (d /= 2 .and. d /= 3) then
       info = ARPY_ERR_DIM
       return
    end if
    if (.not. ieee_is_finite(skin) .or. skin < 0.0_dp) then
       info = ARPY_ERR_BAD_SKIN
       return
    end if
    if (skin > big) then
       info = ARPY_ERR_RANGE
       return
    end if
    ! every particle in parallel; only if one fails, the serial passes below name the first.  The
    ! comparisons are false for NaN, and infinities lie beyond big: they test finiteness too.
    nout = 0
    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_ROWS) reduction(+: nout)
    do p = 1, n
       nout = nout + merge(0, 1, abs(x(1, p)) <= big .and. abs(x(2, p)) <= big .and. abs(x(d, p)) <= big &
            .and. rc(p) >= small .and. rc(p) <= big)
    end do
    !$omp end parallel do
    if (nout == 0) return
    do p = 1, n
       if (.not. all(ieee_is_finite(x(:, p)))) then
          info = ARPY_ERR_NONFINITE_X
          bad = p
          return
       end if
       if (.not. ieee_is_finite(rc(p)) .or. .not. (rc(p) > 0.0_dp)) then
          info = ARPY_ERR_BAD_RC
          bad = p
          return
       end if
    end do
    do p = 1, n
       if (maxval(abs(x(:, p))) > big .or. rc(p) < small .or. rc(p) > big) then
          info = ARPY_ERR_RANGE
          bad = p
          return
       end if
    end do
  end subroutine check_particles

  !> Check a CSR list handed in by the caller: offsets 0 = off(1) <= ...
  !> <= off(nrow+1) = nnz and 0-based entries in [0, ncols).  bad: the
  !> first row whose offsets decrease (0 otherwise).
  subroutine check_csr(nrow, ncols, nnz, off, idx, info, bad)
    integer, intent(in) :: nrow, ncols
    integer(i8), intent(in) :: nnz, off(nrow + 1)
    integer, intent(in) :: idx(nnz)
    integer, intent(out) :: info, bad
    integer :: i
    info = ARPY_OK
    bad = 0
    if (off(1) /= 0 .or. off(nrow + 1) /= nnz) then
       info = ARPY_ERR_LIST
       return
    end if
    do i = 1, nrow
       if (off(i + 1) < off(i)) then
          info = ARPY_ERR_LIST
          bad = i
          return
       end if
    end do
    if (any(idx < 0) .or. any(idx >= ncols)) info = ARPY_ERR_LIST
  end subroutine check_csr

end module arpy_checks
