!> How crowded particles are on the uniform cell list's grid: the statistic with which
!> `method="auto"` (arpy.lists.search.auto_work) sees clustered particles.
module arpy_crowding
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_SIZE
  implicit none
  private

  public :: crowding_counts

contains

  !> The grid cell of x(:) (0-based per axis), positions outside the grid (and NaN) in its border
  !> cells: cells of edge g from lo, nc(a) along axis a.
  pure subroutine grid_cell(d, x, lo, g, nc, c)
    integer, intent(in) :: d, nc(d)
    real(dp), intent(in) :: x(d), lo(d), g
    integer, intent(out) :: c(3)
    integer :: a
    real(dp) :: t
    c = 0
    do a = 1, d
       t = (x(a) - lo(a)) / g
       if (.not. (t >= 1.0_dp)) then               ! (below the grid's second cell, or NaN)
          c(a) = 0
       else if (t >= real(nc(a) - 1, dp)) then
          c(a) = nc(a) - 1
       else
          c(a) = int(t)
       end if
    end do
  end subroutine grid_cell

  !> block(j): of the sampled particle 1 + (j - 1) * step, the number of the other sampled particles
  !> (1, 1 + step, 1 + 2 step, ...) in the 3**d grid cells around its own (cells of edge g from lo,
  !> nc(a) along axis a; particles outside the grid counted in its border cells).
  !> ns = (n - 1) / step + 1.  info: ARPY_ERR_SIZE on a bad grid or sample, ARPY_ERR_ALLOC.
  subroutine crowding_counts(d, n, x, step, lo, g, nc, ns, block, info)
    integer, intent(in) :: d, n, step, nc(d), ns
    real(dp), intent(in) :: x(d, n), lo(d), g
    integer(i8), intent(out) :: block(ns)
    integer, intent(out) :: info
    integer(i8), allocatable :: hist(:)
    integer(i8) :: ncell, s(3), b
    integer :: p, j, a, c(3), lo3(3), hi3(3), stat, i1, i2, i3
    block = 0
    info = ARPY_OK
    if (d < 2 .or. d > 3 .or. n < 1 .or. step < 1 .or. any(nc < 1) &
        .or. ns /= (n - 1) / step + 1 .or. .not. (g > 0.0_dp)) then
       info = ARPY_ERR_SIZE
       return
    end if
    ncell = product(int(nc, i8))
    allocate(hist(0:ncell - 1), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    hist = 0
    s = 0                                    ! (row-major strides; axis 3 of a 2D grid unused)
    s(d) = 1
    do a = d - 1, 1, -1
       s(a) = s(a + 1) * nc(a + 1)
    end do
    do p = 1, n, step
       call grid_cell(d, x(:, p), lo, g, nc, c)
       b = c(1) * s(1) + c(2) * s(2) + c(3) * s(3)
       hist(b) = hist(b) + 1
    end do
    lo3 = 0
    hi3 = 0
    do j = 1, ns
       p = 1 + (j - 1) * step
       call grid_cell(d, x(:, p), lo, g, nc, c)
       lo3(1:d) = max(c(1:d) - 1, 0)
       hi3(1:d) = min(c(1:d) + 1, nc - 1)
       do i1 = lo3(1), hi3(1)
          do i2 = lo3(2), hi3(2)
             b = i1 * s(1) + i2 * s(2)
             do i3 = lo3(3), hi3(3)
                block(j) = block(j) + hist(b + i3 * s(3))
             end do
          end do
       end do
       block(j) = block(j) - 1                                    ! (not itself)
    end do
  end subroutine crowding_counts

end module arpy_crowding
