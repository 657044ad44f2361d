!> The k nearest points: for every query point, the k points of a set nearest
!> to it, by the minimum image along periodic axes, nearest first (by squared
!> distance) and equal squared distances by index.
!>
!> The points are counted into a uniform grid of about two per cell; a query
!> searches the shells of cells around its own (Chebyshev radius 0, 1, 2,
!> ...) and stops once its k-th distance lies below the distance to every
!> cell not yet searched.  A distance is sqrt of the sum over the axes, in
!> axis order, of the squared differences, each difference along a periodic
!> axis of period L brought into [-L/2, L/2] by one period (the formula of
!> scipy's cKDTree with boxsize, whose results these are).
!>
!> The queries run in parallel, each writing its own output columns: the
!> result does not depend on the number of threads.
module arpy_knn
  use arpy_kinds, only: dp, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_SIZE
  use arpy_threads, only: team_size, MIN_PARALLEL_POINTS
  implicit none
  private

  !> points per cell the grid aims at (on average over the points, in the cell of each)
  real(dp), parameter :: PER_CELL = 2.0_dp
  !> rounds of refinement for graded sets, and the most cells per point they may make
  integer, parameter :: MAX_REFINE = 3
  real(dp), parameter :: MAX_CELLS = 16.0_dp

  public :: knn_query

contains

  !> dist(1:k, j), idx(1:k, j): the k points of x (d, n) nearest to y(:, j), j = 1 .. m, and their
  !> 0-based indices.  period(l) > 0: axis l is periodic with that period, and x and y lie in
  !> [0, period(l)) along it; period(l) = 0: a plain axis.  Positions finite; info = ARPY_ERR_SIZE
  !> unless 1 <= k <= n, ARPY_ERR_ALLOC without memory.
  subroutine knn_query(d, n, x, m, y, k, period, dist, idx, info)
    integer, intent(in) :: d, n, m, k
    real(dp), intent(in) :: x(d, n), y(d, m), period(d)
    real(dp), intent(out) :: dist(k, m)
    integer, intent(out) :: idx(k, m), info
    real(dp) :: lo(3), hi(3), h(3), hair, vol, ext(3), edge, crowd, grow
    integer :: nc(3), l, j, stat, nt, dd, round
    integer, allocatable :: start(:), slot(:)
    real(dp), allocatable :: xs(:, :)

    info = ARPY_OK
    dist = 0.0_dp
    idx = -1
    if (k < 1 .or. k > n) then
       info = ARPY_ERR_SIZE
       return
    end if
    ! the grid: over [0, period) along periodic axes, else over the points' extent; cells of
    ! about PER_CELL points (an axis without extent gets one cell)
    lo = 0.0_dp
    hi = 0.0_dp
    do l = 1, d
       if (period(l) > 0.0_dp) then
          hi(l) = period(l)
       else
          lo(l) = minval(x(l, :))
          hi(l) = maxval(x(l, :))
       end if
    end do
    ext = hi - lo
    dd = count(ext(1:d) > 0.0_dp)
    vol = product(ext(1:d), mask=ext(1:d) > 0.0_dp)
    edge = (vol * PER_CELL / n)**(1.0_dp / max(dd, 1))
    nc = 1
    h = 1.0_dp
    do l = 1, d
       if (ext(l) > 0.0_dp) nc(l) = int(max(1.0_dp, min(ext(l) / edge, real(n, dp))))
    end do
    do while (product(real(nc, dp)) > 4.0_dp * n + 8.0_dp)     ! (axes of very different extents)
       l = maxloc(nc, dim=1)
       nc(l) = max(1, nc(l) / 2)
    end do
    do l = 1, d
       if (ext(l) > 0.0_dp) h(l) = ext(l) / nc(l)
    end do
    ! graded sets (most points where they are densest): finer cells, until a point's cell holds
    ! about PER_CELL points on average over the points (at most MAX_REFINE rounds, MAX_CELLS n cells)
    do round = 1, MAX_REFINE
       crowd = crowding(d, n, x, lo, h, nc)
       if (crowd <= 2.0_dp * PER_CELL) exit
       grow = min((crowd / PER_CELL)**(1.0_dp / max(dd, 1)), &
            (MAX_CELLS * n / product(real(nc, dp)))**(1.0_dp / max(dd, 1)))
       if (grow < 1.5_dp) exit
       do l = 1, d
          if (ext(l) > 0.0_dp) then
             nc(l) = int(nc(l) * grow)
             h(l) = ext(l) / nc(l)
          end if
       end do
    end do
    hair = 1.0e-9_dp * (maxval(ext(1:d)) + maxval(abs(lo(1:d))) + maxval(abs(hi(1:d))))
    allocate(start(0:product(nc)), slot(n), xs(d, n), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    call bin_points(d, n, x, lo, h, nc, start, slot, xs, info)
    if (info /= ARPY_OK) return
    nt = 1
    if (m >= MIN_PARALLEL_POINTS) nt = team_size()
    !$omp parallel do num_threads(nt) schedule(static)
    do j = 1, m
       call query(y(:, j), dist(:, j), idx(:, j))
    end do
    !$omp end parallel do

  contains

    subroutine query(yq, dq, iq)
      real(dp), intent(in) :: yq(d)
      real(dp), intent(out) :: dq(k)
      integer, intent(out) :: iq(k)
      integer :: c(3), r, found, o2, o3, olo(3), ohi(3), ll, row
      real(dp) :: g2(3), out2, bound2, gap
      logical :: whole
      c = 0
      g2 = 0.0_dp
      do ll = 1, d
         c(ll) = cell_of(yq(ll), lo(ll), h(ll), nc(ll))
         if (period(ll) <= 0.0_dp) g2(ll) = max(lo(ll) - yq(ll), yq(ll) - hi(ll), 0.0_dp)**2
      end do
      out2 = sum(g2)                       ! squared distance from yq to the grid's box
      found = 0
      dq = huge(1.0_dp)
      iq = -1
      r = 0
      do
         ! the shell of Chebyshev radius r around c: the offsets o of the block, each cell once
         ! (a periodic axis wraps), those with some |o(l)| = r
         olo = 0
         ohi = 0
         do ll = 1, d
            if (period(ll) > 0.0_dp) then
               olo(ll) = -min(r, (nc(ll) - 1) / 2)
               ohi(ll) = min(r, nc(ll) / 2)
            else
               olo(ll) = max(-r, -c(ll))
               ohi(ll) = min(r, nc(ll) - 1 - c(ll))
            end if
         end do
         do o3 = olo(3), ohi(3)
            do o2 = olo(2), ohi(2)
               row = nc(1) * (wrapped(2, c(2) + o2) + nc(2) * wrapped(3, c(3) + o3))
               if (r == 0 .or. abs(o2) == r .or. abs(o3) == r) then
                  call scan_run(yq, row, c(1) + olo(1), c(1) + ohi(1), found, dq, iq)    ! a row of the shell
               else                                     ! inside: only its ends lie on the shell
                  if (-r >= olo(1)) call scan_run(yq, row, c(1) - r, c(1) - r, found, dq, iq)
                  if (r <= ohi(1)) call scan_run(yq, row, c(1) + r, c(1) + r, found, dq, iq)
               end if
            end do
         end do
         ! a cell not searched lies beyond a face of the block that is neither the grid's boundary
         ! nor (along a periodic axis) one of a block that wraps all the way round; bound2: the
         ! least squared distance from yq to the points beyond such a face
         whole = .true.
         bound2 = huge(1.0_dp)
         do ll = 1, d
            if (period(ll) > 0.0_dp) then
               if (2 * r + 1 >= nc(ll)) cycle
               gap = min(yq(ll) - (lo(ll) + (c(ll) - r) * h(ll)), lo(ll) + (c(ll) + r + 1) * h(ll) - yq(ll))
            else
               if (c(ll) - r <= 0 .and. c(ll) + r >= nc(ll) - 1) cycle
               gap = huge(1.0_dp)
               if (c(ll) - r > 0) gap = yq(ll) - (lo(ll) + (c(ll) - r) * h(ll))
               if (c(ll) + r < nc(ll) - 1) gap = min(gap, lo(ll) + (c(ll) + r + 1) * h(ll) - yq(ll))
            end if
            whole = .false.
            gap = max(gap - hair, 0.0_dp)
            bound2 = min(bound2, out2 - g2(ll) + gap * gap)
         end do
         if (whole) exit
         if (found == k) then
            if (dq(k) < bound2) exit
         end if
         r = r + 1
      end do
      dq = sqrt(dq)
    end subroutine query

    !> The cell coordinate v along axis ll wrapped into 0 .. nc(ll) - 1 along a periodic axis (v is
    !> at most one period off); as it is along the others.
    pure integer function wrapped(ll, v)
      integer, intent(in) :: ll, v
      wrapped = v
      if (ll > d) return
      if (period(ll) > 0.0_dp) then
         if (v < 0) wrapped = v + nc(ll)
         if (v >= nc(ll)) wrapped = v - nc(ll)
      end if
    end function wrapped

    !> The points of the cells v1 .. v2 along axis 1 (wrapped along a periodic axis 1) of the grid
    !> row starting at cell index row, offered to the k best of query yq: one or two runs of slots.
    subroutine scan_run(yq, row, v1, v2, found, dq, iq)
      real(dp), intent(in) :: yq(d)
      integer, intent(in) :: row, v1, v2
      integer, intent(inout) :: found, iq(k)
      real(dp), intent(inout) :: dq(k)
      integer :: w1, w2
      w1 = wrapped(1, v1)
      w2 = wrapped(1, v2)
      if (w1 <= w2) then
         call scan_slots(yq, start(row + w1), start(row + w2 + 1) - 1, found, dq, iq)
      else                                   ! (the run wraps round a periodic axis 1)
         call scan_slots(yq, start(row + w1), start(row + nc(1)) - 1, found, dq, iq)
         call scan_slots(yq, start(row), start(row + w2 + 1) - 1, found, dq, iq)
      end if
    end subroutine scan_run

    !> The points in slots a0 .. a1 offered to the k best of query yq.
    subroutine scan_slots(yq, a0, a1, found, dq, iq)
      real(dp), intent(in) :: yq(d)
      integer, intent(in) :: a0, a1
      integer, intent(inout) :: found, iq(k)
      real(dp), intent(inout) :: dq(k)
      integer :: a, ll
      real(dp) :: s, t
      do a = a0, a1
         s = 0.0_dp
         do ll = 1, d
            t = yq(ll) - xs(ll, a)
            if (period(ll) > 0.0_dp) then
               if (t < -0.5_dp * period(ll)) then
                  t = period(ll) + t
               else if (t > 0.5_dp * period(ll)) then
                  t = t - period(ll)
               end if
            end if
            s = s + t * t
         end do
         if (found == k) then
            if (s > dq(k)) cycle
         end if
         call keep(s, slot(a), found, dq, iq)
      end do
    end subroutine scan_slots

  end subroutine knn_query

  !> The cell (0 .. nc - 1) of coordinate v on a grid from lo with cells of width h.
  pure integer function cell_of(v, lo, h, nc)
    real(dp), intent(in) :: v, lo, h
    integer, intent(in) :: nc
    cell_of = int(min(max(aint((v - lo) / h), 0.0_dp), real(nc - 1, dp)))   ! (aint: floor where >= 0)
  end function cell_of

  !> Insert (s, p) into the k best so far (ascending by squared distance, then index).
  pure subroutine keep(s, p, found, dq, iq)
    real(dp), intent(in) :: s
    integer, intent(in) :: p
    integer, intent(inout) :: found
    real(dp), intent(inout) :: dq(:)
    integer, intent(inout) :: iq(:)
    integer :: i, k
    k = size(dq)
    if (found == k) then
       if (s > dq(k) .or. (s == dq(k) .and. p > iq(k))) return
    else
       found = found + 1
    end if
    i = found
    do while (i > 1)
       if (dq(i - 1) < s .or. (dq(i - 1) == s .and. iq(i - 1) < p)) exit
       dq(i) = dq(i - 1)
       iq(i) = iq(i - 1)
       i = i - 1
    end do
    dq(i) = s
    iq(i) = p
  end subroutine keep

  !> The index of the cell holding point xp: axis 1 fastest.
  pure integer function point_cell(d, xp, lo, h, nc) result(b)
    integer, intent(in) :: d, nc(3)
    real(dp), intent(in) :: xp(d), lo(3), h(3)
    integer :: l
    b = 0
    do l = d, 1, -1
       b = b * nc(l) + cell_of(xp(l), lo(l), h(l), nc(l))
    end do
  end function point_cell

  !> The mean over the points of how many points share their cell: sum of squared counts / n
  !> (0 without memory for the counts: no refinement then).
  function crowding(d, n, x, lo, h, nc) result(crowd)
    integer, intent(in) :: d, n, nc(3)
    real(dp), intent(in) :: x(d, n), lo(3), h(3)
    real(dp) :: crowd
    integer, allocatable :: cnt(:)
    integer :: p, b, stat
    crowd = 0.0_dp
    allocate(cnt(0:product(nc) - 1), stat=stat)
    if (stat /= 0) return
    cnt = 0
    do p = 1, n
       b = point_cell(d, x(:, p), lo, h, nc)
       cnt(b) = cnt(b) + 1
    end do
    crowd = sum(real(cnt, dp)**2) / n
  end function crowding

  !> Counting sort of the points into the cells: cell b holds slots start(b) .. start(b+1) - 1,
  !> slot a the point slot(a) (0-based) at xs(:, a); within a cell by index.
  subroutine bin_points(d, n, x, lo, h, nc, start, slot, xs, info)
    integer, intent(in) :: d, n, nc(3)
    integer, intent(out) :: info
    real(dp), intent(in) :: x(d, n), lo(3), h(3)
    integer, intent(out) :: start(0:), slot(n)
    real(dp), intent(out) :: xs(d, n)
    integer :: p, b, ncell
    integer, allocatable :: cellof(:)
    integer :: stat
    ncell = product(nc)
    info = ARPY_OK
    allocate(cellof(n), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    start = 0
    do p = 1, n
       b = point_cell(d, x(:, p), lo, h, nc)
       cellof(p) = b
       start(b + 1) = start(b + 1) + 1
    end do
    start(0) = 1
    do b = 1, ncell
       start(b) = start(b) + start(b - 1)
    end do
    do p = 1, n
       b = cellof(p)
       slot(start(b)) = p - 1
       xs(:, start(b)) = x(:, p)
       start(b) = start(b) + 1
    end do
    do b = ncell, 1, -1
       start(b) = start(b - 1)
    end do
    start(0) = 1
  end subroutine bin_points

end module arpy_knn
