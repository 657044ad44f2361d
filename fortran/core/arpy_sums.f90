!> Sums rounded once: the partials of Shewchuk (Discrete Comput. Geom. 18, 1997) that hold a
!> running sum exactly, rounded to the nearest double (ties to even) as Python's math.fsum rounds
!> them, so the result is math.fsum's whatever the order of the terms.
module arpy_sums
  use arpy_kinds, only: dp
  implicit none
  private

  !> nonoverlapping partials of doubles: at most about 40 (2098 bits of exponent range / 53)
  integer, parameter :: MAXP = 64

  public :: exact_sum

contains

  !> s = the sum of x(1:n) rounded once; ok = .false. (s = 0) if a term is not finite or a partial
  !> sum overflows (the caller's math.fsum then answers as it does for those).
  pure subroutine exact_sum(n, x, s, ok)
    integer, intent(in) :: n
    real(dp), intent(in) :: x(n)
    real(dp), intent(out) :: s
    logical, intent(out) :: ok
    real(dp) :: p(MAXP), v, y, t, hi, lo, yr
    integer :: np, i, j, k
    s = 0.0_dp
    ok = .false.
    np = 0
    do k = 1, n
       v = x(k)
       if (.not. abs(v) <= huge(v)) return                ! NaN or an infinity
       i = 0
       do j = 1, np                                        ! v + the partials, exactly
          y = p(j)
          if (abs(v) < abs(y)) then
             t = v
             v = y
             y = t
          end if
          hi = v + y
          yr = hi - v
          lo = y - yr
          if (lo /= 0.0_dp) then
             i = i + 1
             p(i) = lo
          end if
          v = hi
       end do
       if (.not. abs(v) <= huge(v)) return                ! an intermediate overflow
       np = i
       if (v /= 0.0_dp) then
          if (np == MAXP) return
          np = np + 1
          p(np) = v
       end if
    end do
    hi = 0.0_dp
    if (np > 0) then
       hi = p(np)                                          ! from the top, while the sum is exact
       np = np - 1
       lo = 0.0_dp
       do while (np > 0)
          v = hi
          y = p(np)
          np = np - 1
          hi = v + y
          yr = hi - v
          lo = y - yr
          if (lo /= 0.0_dp) exit
       end do
       ! half-even rounding across several partials: round up when the rest pushes past the tie
       if (np > 0) then
          if ((lo < 0.0_dp .and. p(np) < 0.0_dp) .or. (lo > 0.0_dp .and. p(np) > 0.0_dp)) then
             y = lo * 2.0_dp
             v = hi + y
             yr = v - hi
             if (y == yr) hi = v
          end if
       end if
    end if
    s = hi
    ok = .true.
  end subroutine exact_sum

end module arpy_sums
