!> Sums rounded once: the partials of Shewchuk (Discrete Comput. Geom. 18, 1997) that hold a
!> running sum exactly, rounded to the nearest double (ties to even) as Python's math.fsum rounds
!> them, so the result is math.fsum's whatever the order of the terms.
module arpy_sums
  use arpy_kinds, only: dp
  implicit none
  private

  !> nonoverlapping partials of doubles: at most about 40 (2098 bits of exponent range / 53)
  integer, parameter :: MAXP = 64

  public :: MAXP, exact_partials, exact_sum

contains

  !> p(1:np): nonoverlapping partials, in increasing magnitude, whose exact sum is that of x(1:n)
  !> (np = 0 for a zero sum); ok = .false. (np = 0) if a term is not finite, a partial sum overflows
  !> or the partials would outgrow MAXP.
  pure subroutine exact_partials(n, x, p, np, ok)
    integer, intent(in) :: n
    real(dp), intent(in) :: x(n)
    real(dp), intent(out) :: p(MAXP)
    integer, intent(out) :: np
    logical, intent(out) :: ok
    real(dp) :: v, y, t, hi, lo, yr
    integer :: i, j, k
    p = 0.0_dp
    ok = .false.
    np = 0
    do k = 1, n
       v = x(k)
       if (.not. abs(v) <= huge(v)) then                  ! NaN or an infinity
          np = 0
          return
       end if
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
       np = i
       if (.not. abs(v) <= huge(v)) then                  ! an intermediate overflow
          np = 0
          return
       end if
       if (v /= 0.0_dp) then
          if (np == MAXP) then
             np = 0
             return
          end if
          np = np + 1
          p(np) = v
       end if
    end do
    ok = .true.
  end subroutine exact_partials

  !> s = the sum of x(1:n) rounded once; ok = .false. (s = 0) if a term is not finite or a partial
  !> sum overflows (the caller's math.fsum then answers as it does for those).
  pure subroutine exact_sum(n, x, s, ok)
    integer, intent(in) :: n
    real(dp), intent(in) :: x(n)
    real(dp), intent(out) :: s
    logical, intent(out) :: ok
    real(dp) :: p(MAXP), v, y, hi, lo, yr
    integer :: np
    s = 0.0_dp
    call exact_partials(n, x, p, np, ok)
    if (.not. ok) return
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
