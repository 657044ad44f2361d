!> Input validation shared by every entry point of the core.
module arpy_checks
  use, intrinsic :: ieee_arithmetic, only: ieee_is_finite, ieee_value, ieee_quiet_nan, ieee_positive_inf
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_DIM, ARPY_ERR_NONFINITE_X, &
       ARPY_ERR_BAD_RC, ARPY_ERR_BAD_SKIN, ARPY_ERR_LIST, ARPY_ERR_RANGE, ARPY_ERR_SIZE, RANGE_EXP
  use arpy_threads, only: team_size, block_range, MIN_PARALLEL_ROWS
  implicit none
  private

  public :: check_particles, check_csr, column_extremes

  !> What the check of a particle set finds on the way: the bounding box lo(1:d) .. hi(1:d) of the
  !> positions (0 beyond d) and the smallest and largest cutoff (without the skin).
  type, public :: particle_extremes
     real(dp) :: lo(3) = 0.0_dp, hi(3) = 0.0_dp, rlo = 0.0_dp, rhi = 0.0_dp
  end type particle_extremes

  real(dp), parameter :: big = 2.0_dp**RANGE_EXP, small = 2.0_dp**(-RANGE_EXP)

contains

  !> Check dimension, positions (finite) and cutoffs (finite, > 0), skin
  !> (finite, >= 0), then that lengths lie in the core's range
  !> (ARPY_ERR_RANGE): |x|, skin <= 2**RANGE_EXP, 2**-RANGE_EXP <= rc <= 2**RANGE_EXP.
  !> bad returns the 1-based index of the first offending particle (0 if none
  !> or if the dimension/skin is at fault).  ext (n >= 1, the particles valid):
  !> their extremes, from the same pass.
  subroutine check_particles(d, n, x, rc, skin, info, bad, ext)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), rc(n), skin
    integer, intent(out) :: info, bad
    type(particle_extremes), intent(out), optional :: ext
    integer :: p, nout
    real(dp) :: l(3), h(3), rl, rh
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
    ! every particle in parallel (outside); only if one fails, the serial passes below name the first
    nout = 0
    if (present(ext) .and. n > 0) then       ! (minima and maxima are exact: any number of threads)
       l = huge(1.0_dp)
       h = -huge(1.0_dp)
       rl = huge(1.0_dp)
       rh = 0.0_dp
       !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_ROWS) reduction(+: nout) &
       !$omp& reduction(min: l, rl) reduction(max: h, rh)
       do p = 1, n
          nout = nout + outside(x(1, p), x(2, p), x(d, p), rc(p))
          l(1) = min(l(1), x(1, p))
          h(1) = max(h(1), x(1, p))
          l(2) = min(l(2), x(2, p))
          h(2) = max(h(2), x(2, p))
          l(3) = min(l(3), x(d, p))
          h(3) = max(h(3), x(d, p))
          rl = min(rl, rc(p))
          rh = max(rh, rc(p))
       end do
       !$omp end parallel do
       ext%lo(1:d) = l(1:d)
       ext%hi(1:d) = h(1:d)
       ext%rlo = rl
       ext%rhi = rh
    else
       !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_ROWS) reduction(+: nout)
       do p = 1, n
          nout = nout + outside(x(1, p), x(2, p), x(d, p), rc(p))
       end do
       !$omp end parallel do
    end if
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

  !> 1 if a particle at (x1, x2, x3) with cutoff r is not finite or outside the core's range, else 0
  !> (the comparisons are false for NaN, and infinities lie beyond big).
  elemental integer function outside(x1, x2, x3, r)
    real(dp), intent(in) :: x1, x2, x3, r
    outside = merge(0, 1, abs(x1) <= big .and. abs(x2) <= big .and. abs(x3) <= big .and. r >= small .and. r <= big)
  end function outside

  !> The least and largest entry of each row k of x(d, n) (a column of the caller's (n, d) array;
  !> n >= 1), NaN for a row that holds a NaN.  In parallel blocks from MIN_PARALLEL_ROWS entries:
  !> minima and maxima are exact in any order.
  subroutine column_extremes(d, n, x, lo, hi)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n)
    real(dp), intent(out) :: lo(d), hi(d)
    real(dp) :: bl(d, 64), bh(d, 64)
    integer :: bnan(d, 64)
    integer :: nb, b, p0, p1
    nb = min(team_size(), 64)
    if (n < MIN_PARALLEL_ROWS) nb = 1
    !$omp parallel do num_threads(nb) schedule(static, 1) private(p0, p1)
    do b = 1, nb
       call block_range(n, nb, b, p0, p1)
       call block_extremes(x(:, p0:p1), p1 - p0 + 1, bl(:, b), bh(:, b), bnan(:, b))
    end do
    !$omp end parallel do
    do b = 1, d
       lo(b) = minval(bl(b, 1:nb))
       hi(b) = maxval(bh(b, 1:nb))
       if (sum(bnan(b, 1:nb)) > 0) then
          lo(b) = ieee_value(lo(b), ieee_quiet_nan)
          hi(b) = lo(b)
       end if
    end do

  contains

    !> One block's extremes and NaN counts, row by row: four independent minima and maxima per row
    !> (the processor overlaps them), joined at the end.
    subroutine block_extremes(y, m, l, h, nan)
      integer, intent(in) :: m
      real(dp), intent(in) :: y(d, m)
      real(dp), intent(out) :: l(d), h(d)
      integer, intent(out) :: nan(d)
      real(dp) :: a(4), z(4), inf
      integer :: k, p, c(4), j
      inf = ieee_value(inf, ieee_positive_inf)         ! (not huge: an array of -inf has maximum -inf)
      do k = 1, d
         a = inf
         z = -inf
         c = 0
         do p = 1, m - 3, 4
            do j = 1, 4
               a(j) = min(a(j), y(k, p + j - 1))
               z(j) = max(z(j), y(k, p + j - 1))
               c(j) = c(j) + merge(1, 0, y(k, p + j - 1) /= y(k, p + j - 1))
            end do
         end do
         do p = 4 * (m / 4) + 1, m
            a(1) = min(a(1), y(k, p))
            z(1) = max(z(1), y(k, p))
            c(1) = c(1) + merge(1, 0, y(k, p) /= y(k, p))
         end do
         l(k) = minval(a)
         h(k) = maxval(z)
         nan(k) = sum(c)
      end do
    end subroutine block_extremes

  end subroutine column_extremes

  !> Check a CSR list handed in by the caller: offsets 0 = off(1) <= ...
  !> <= off(nrow+1) = nnz and 0-based entries in [0, ncols).  bad: the
  !> first row whose offsets decrease (0 otherwise).  Each array in one pass without early exits
  !> (a count, an or of sign bits: loops the compiler vectorizes); only a failing list is searched
  !> for its first bad row.
  subroutine check_csr(nrow, ncols, nnz, off, idx, info, bad)
    integer, intent(in) :: nrow, ncols
    integer(i8), intent(in) :: nnz, off(nrow + 1)
    integer, intent(in) :: idx(nnz)
    integer, intent(out) :: info, bad
    integer(i8) :: k
    integer :: i, down, signs
    info = ARPY_OK
    bad = 0
    if (off(1) /= 0 .or. off(nrow + 1) /= nnz) then
       info = ARPY_ERR_LIST
       return
    end if
    down = 0
    do i = 1, nrow
       down = down + merge(1, 0, off(i + 1) < off(i))
    end do
    if (down > 0) then
       info = ARPY_ERR_LIST
       do i = 1, nrow
          if (off(i + 1) < off(i)) then
             bad = i
             return
          end if
       end do
    end if
    ! an entry outside [0, ncols) has the sign bit set in itself or in ncols - 1 - itself
    signs = 0
    do k = 1, nnz
       signs = ior(signs, ior(idx(k), (ncols - 1) - idx(k)))
    end do
    if (signs < 0) info = ARPY_ERR_LIST
  end subroutine check_csr

end module arpy_checks
