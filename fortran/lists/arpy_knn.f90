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
!> result does not depend on the number of threads.  min_distance, the least
!> distance between two of the points, scans each pair of neighbouring cells
!> once instead (exact when that pair is closer than a cell edge, else it
!> asks every point for its nearest).
module arpy_knn
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_SIZE
  use arpy_threads, only: team_size, MIN_PARALLEL_POINTS
  use arpy_celllist, only: cell_grid, bin_particles, bounding_box_of
  implicit none
  private

  !> points per cell the grid aims at (on average over the points, in the cell of each)
  real(dp), parameter :: PER_CELL = 2.0_dp
  !> rounds of refinement for graded sets, and the most cells per point they may make
  integer, parameter :: MAX_REFINE = 3
  real(dp), parameter :: MAX_CELLS = 16.0_dp

  !> The points counted into a uniform grid (the uniform cell list's counting sort, bin_particles):
  !> cell b (0-based, axis 1 fastest) holds slots start(b + 1) .. start(b + 2) - 1, slot a the point
  !> perm(a) (1-based) at xs(:, a), in cell cellof(a).
  type :: point_grid
     integer :: d = 0, nc(3) = 1
     real(dp) :: lo(3) = 0.0_dp, hi(3) = 0.0_dp, h(3) = 1.0_dp, hair = 0.0_dp, period(3) = 0.0_dp
     integer, allocatable :: start(:), perm(:), cellof(:)
     real(dp), allocatable :: xs(:, :)
  end type point_grid

  public :: knn_query, min_distance

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
    type(point_grid) :: g
    integer :: j, nt
    dist = 0.0_dp
    idx = -1
    if (k < 1 .or. k > n) then
       info = ARPY_ERR_SIZE
       return
    end if
    call grid_build(g, d, n, x, period, info)
    if (info /= ARPY_OK) return
    nt = 1
    if (m >= MIN_PARALLEL_POINTS) nt = team_size()
    ! (dynamic: a query where the points are sparse searches many more cells than one where they
    ! are dense, and graded sets have both)
    !$omp parallel do num_threads(nt) schedule(dynamic, 32)
    do j = 1, m
       call query(g, y(:, j), k, dist(:, j), idx(:, j))
    end do
    !$omp end parallel do
  end subroutine knn_query

  !> dmin: the least distance between two of the points x (d, n), n >= 2 (periods as knn_query),
  !> the same value as the least second-nearest distance of knn_query with y = x, k = 2.
  subroutine min_distance(d, n, x, period, dmin, info)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), period(d)
    real(dp), intent(out) :: dmin
    integer, intent(out) :: info
    type(point_grid) :: g
    real(dp) :: s2, edge, dq(2)
    integer :: b, l, nt, iq(2), j
    logical :: tight
    dmin = 0.0_dp
    if (n < 2) then
       info = ARPY_ERR_SIZE
       return
    end if
    call grid_build(g, d, n, x, period, info)
    if (info /= ARPY_OK) return
    nt = 1
    if (n >= MIN_PARALLEL_POINTS) nt = team_size()
    ! each pair of points in one cell or in neighbouring cells once (a periodic axis of fewer than
    ! three cells would meet a cell twice: the queries below instead); min is exact in any order
    tight = .false.
    do l = 1, d
       tight = tight .or. (period(l) > 0.0_dp .and. g%nc(l) < 3)
    end do
    s2 = huge(1.0_dp)
    if (.not. tight) then
       ! (the non-empty cells only, each by its first slot: graded sets have far more cells)
       !$omp parallel do num_threads(nt) schedule(static) private(b) reduction(min: s2)
       do j = 1, n
          b = g%cellof(j)
          if (g%start(b + 1) /= j) cycle
          s2 = min(s2, cell_pairs(g, b))
       end do
       !$omp end parallel do
       ! every pair closer than the narrowest edge of an axis with more than one cell was seen
       edge = huge(1.0_dp)
       do l = 1, d
          if (g%nc(l) > 1) edge = min(edge, g%h(l))
       end do
       edge = edge - g%hair
       if (edge <= 0.0_dp .or. s2 >= edge * edge) s2 = -1.0_dp
    end if
    if (tight .or. s2 < 0.0_dp) then
       s2 = huge(1.0_dp)
       !$omp parallel do num_threads(nt) schedule(static) private(dq, iq) reduction(min: s2)
       do j = 1, n
          call query(g, x(:, j), 2, dq, iq)
          s2 = min(s2, dq(2))
       end do
       !$omp end parallel do
       dmin = s2                              ! (query's distances are square roots already)
       return
    end if
    dmin = sqrt(s2)
  end subroutine min_distance

  !> The least squared distance between a point of cell b and a later point of it or a point of
  !> a neighbouring cell after it (the forward half of the 3**d stencil), huge if none.
  function cell_pairs(g, b) result(s2)
    type(point_grid), intent(in) :: g
    integer, intent(in) :: b
    real(dp) :: s2
    integer :: c(3), o(3), o1, o2, o3, cell(3), nb, a, q, ll
    s2 = huge(1.0_dp)
    if (g%start(b + 2) == g%start(b + 1)) return
    c(1) = modulo(b, g%nc(1))
    c(2) = modulo(b / g%nc(1), g%nc(2))
    c(3) = b / (g%nc(1) * g%nc(2))
    do o3 = 0, merge(1, 0, g%d == 3)
       do o2 = merge(-1, 0, o3 > 0), 1
          do o1 = merge(-1, 0, o2 > 0 .or. o3 > 0), 1
             o = [o1, o2, o3]
             cell = c + o
             nb = -1
             do ll = 1, 3
                if (ll <= g%d .and. g%period(ll) > 0.0_dp) cell(ll) = modulo(cell(ll), g%nc(ll))
                if (cell(ll) < 0 .or. cell(ll) >= g%nc(ll)) nb = -2
             end do
             if (nb == -2) cycle
             nb = cell(1) + g%nc(1) * (cell(2) + g%nc(2) * cell(3))
             do a = g%start(b + 1), g%start(b + 2) - 1
                do q = merge(a + 1, g%start(nb + 1), nb == b), g%start(nb + 2) - 1
                   s2 = min(s2, dist2(g, g%xs(:, a), g%xs(:, q)))
                end do
             end do
          end do
       end do
    end do
  end function cell_pairs

  !> The grid of the points x (d, n): over [0, period) along periodic axes, else over the points'
  !> extent; cells of about PER_CELL points (an axis without extent gets one cell), finer for
  !> graded sets; the points counted into it.
  subroutine grid_build(g, d, n, x, period, info)
    type(point_grid), intent(out) :: g
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), period(d)
    integer, intent(out) :: info
    real(dp) :: vol, ext(3), edge, crowd, grow
    integer :: l, stat, dd, round, a
    type(cell_grid) :: cg
    integer(i8), allocatable :: cell(:)
    info = ARPY_OK
    g%d = d
    g%period = 0.0_dp
    g%period(1:d) = period
    call bounding_box_of(d, n, x, g%lo, g%hi)
    do l = 1, d
       if (period(l) > 0.0_dp) then
          g%lo(l) = 0.0_dp
          g%hi(l) = period(l)
       end if
    end do
    ext = g%hi - g%lo
    dd = count(ext(1:d) > 0.0_dp)
    vol = product(ext(1:d), mask=ext(1:d) > 0.0_dp)
    edge = (vol * PER_CELL / n)**(1.0_dp / max(dd, 1))
    do l = 1, d
       if (ext(l) > 0.0_dp) g%nc(l) = int(max(1.0_dp, min(ext(l) / edge, real(n, dp))))
    end do
    do while (product(real(g%nc, dp)) > 4.0_dp * n + 8.0_dp)     ! (axes of very different extents)
       l = maxloc(g%nc, dim=1)
       g%nc(l) = max(1, g%nc(l) / 2)
    end do
    do l = 1, d
       if (ext(l) > 0.0_dp) g%h(l) = ext(l) / g%nc(l)
    end do
    ! graded sets (most points where they are densest): finer cells, until a point's cell holds
    ! about PER_CELL points on average over the points (at most MAX_REFINE rounds, MAX_CELLS n cells)
    do round = 1, MAX_REFINE
       crowd = crowding(d, n, x, g%lo, g%h, g%nc)
       if (crowd <= 2.0_dp * PER_CELL) exit
       grow = min((crowd / PER_CELL)**(1.0_dp / max(dd, 1)), &
            (MAX_CELLS * n / product(real(g%nc, dp)))**(1.0_dp / max(dd, 1)))
       if (grow < 1.5_dp) exit
       do l = 1, d
          if (ext(l) > 0.0_dp) then
             g%nc(l) = int(g%nc(l) * grow)
             g%h(l) = ext(l) / g%nc(l)
          end if
       end do
    end do
    g%hair = 1.0e-9_dp * (maxval(ext(1:d)) + maxval(abs(g%lo(1:d))) + maxval(abs(g%hi(1:d))))
    cg%d = d
    cg%n = n
    cg%nc = g%nc
    cg%lo = g%lo
    cg%inv_h = 0.0_dp
    do l = 1, d
       if (ext(l) > 0.0_dp) cg%inv_h(l) = g%nc(l) / ext(l)
    end do
    allocate(cg%start(product(g%nc) + 1), cg%perm(n), cell(n), g%xs(d, n), g%cellof(n), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    call bin_particles(d, n, x, cg, cell, info)
    if (info /= ARPY_OK) return
    call move_alloc(cg%start, g%start)
    call move_alloc(cg%perm, g%perm)
    do a = 1, n
       g%xs(:, a) = x(:, g%perm(a))
       g%cellof(a) = int(cell(g%perm(a)))
    end do
  end subroutine grid_build

  !> The k points of grid g nearest to yq: squared distances searched shell by shell of cells
  !> around the cell of yq, square roots in dq, 0-based indices in iq.
  subroutine query(g, yq, k, dq, iq)
    type(point_grid), intent(in) :: g
    real(dp), intent(in) :: yq(:)
    integer, intent(in) :: k
    real(dp), intent(out) :: dq(k)
    integer, intent(out) :: iq(k)
    integer :: c(3), r, found, o2, o3, olo(3), ohi(3), ll, row, d
    real(dp) :: g2(3), out2, bound2, gap
    logical :: whole
    d = g%d
    c = 0
    g2 = 0.0_dp
    do ll = 1, d
       c(ll) = cell_of(yq(ll), g%lo(ll), g%h(ll), g%nc(ll))
       if (g%period(ll) <= 0.0_dp) g2(ll) = max(g%lo(ll) - yq(ll), yq(ll) - g%hi(ll), 0.0_dp)**2
    end do
    out2 = sum(g2)                       ! squared distance from yq to the grid's box
    found = 0
    dq = huge(1.0_dp)
    iq = -1
    r = 0
    do
       ! the shell of Chebyshev radius r around c: the offsets of the block, each cell once (a
       ! periodic axis wraps), those with some offset of size r
       olo = 0
       ohi = 0
       do ll = 1, d
          if (g%period(ll) > 0.0_dp) then
             olo(ll) = -min(r, (g%nc(ll) - 1) / 2)
             ohi(ll) = min(r, g%nc(ll) / 2)
          else
             olo(ll) = max(-r, -c(ll))
             ohi(ll) = min(r, g%nc(ll) - 1 - c(ll))
          end if
       end do
       do o3 = olo(3), ohi(3)
          do o2 = olo(2), ohi(2)
             row = g%nc(1) * (wrapped(g, 2, c(2) + o2) + g%nc(2) * wrapped(g, 3, c(3) + o3))
             if (r == 0 .or. abs(o2) == r .or. abs(o3) == r) then
                call scan_run(g, yq, row, c(1) + olo(1), c(1) + ohi(1), k, found, dq, iq)    ! a row of the shell
             else                                     ! inside: only its ends lie on the shell
                if (-r >= olo(1)) call scan_run(g, yq, row, c(1) - r, c(1) - r, k, found, dq, iq)
                if (r <= ohi(1)) call scan_run(g, yq, row, c(1) + r, c(1) + r, k, found, dq, iq)
             end if
          end do
       end do
       ! a cell not searched lies beyond a face of the block that is neither the grid's boundary
       ! nor (along a periodic axis) one of a block that wraps all the way round; bound2: the
       ! least squared distance from yq to the points beyond such a face
       whole = .true.
       bound2 = huge(1.0_dp)
       do ll = 1, d
          if (g%period(ll) > 0.0_dp) then
             if (2 * r + 1 >= g%nc(ll)) cycle
             gap = min(yq(ll) - (g%lo(ll) + (c(ll) - r) * g%h(ll)), g%lo(ll) + (c(ll) + r + 1) * g%h(ll) - yq(ll))
          else
             if (c(ll) - r <= 0 .and. c(ll) + r >= g%nc(ll) - 1) cycle
             gap = huge(1.0_dp)
             if (c(ll) - r > 0) gap = yq(ll) - (g%lo(ll) + (c(ll) - r) * g%h(ll))
             if (c(ll) + r < g%nc(ll) - 1) gap = min(gap, g%lo(ll) + (c(ll) + r + 1) * g%h(ll) - yq(ll))
          end if
          whole = .false.
          gap = max(gap - g%hair, 0.0_dp)
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

  !> The squared distance between points u and v: the squares of u - v along the axes, in order,
  !> summed, each periodic difference first brought into [-L/2, L/2] by one period L.
  pure real(dp) function dist2(g, u, v) result(s)
    type(point_grid), intent(in) :: g
    real(dp), intent(in) :: u(:), v(:)
    real(dp) :: t
    integer :: ll
    s = 0.0_dp
    do ll = 1, g%d
       t = u(ll) - v(ll)
       if (g%period(ll) > 0.0_dp) then
          if (t < -0.5_dp * g%period(ll)) then
             t = g%period(ll) + t
          else if (t > 0.5_dp * g%period(ll)) then
             t = t - g%period(ll)
          end if
       end if
       s = s + t * t
    end do
  end function dist2

  !> The cell coordinate v along axis ll wrapped into 0 .. nc(ll) - 1 along a periodic axis (v is
  !> at most one period off); as it is along the others.
  pure integer function wrapped(g, ll, v)
    type(point_grid), intent(in) :: g
    integer, intent(in) :: ll, v
    wrapped = v
    if (ll > g%d) return
    if (g%period(ll) > 0.0_dp) then
       if (v < 0) wrapped = v + g%nc(ll)
       if (v >= g%nc(ll)) wrapped = v - g%nc(ll)
    end if
  end function wrapped

  !> The points of the cells v1 .. v2 along axis 1 (wrapped along a periodic axis 1) of the grid
  !> row starting at cell index row, offered to the k best of query yq: one or two runs of slots.
  subroutine scan_run(g, yq, row, v1, v2, k, found, dq, iq)
    type(point_grid), intent(in) :: g
    real(dp), intent(in) :: yq(:)
    integer, intent(in) :: row, v1, v2, k
    integer, intent(inout) :: found, iq(k)
    real(dp), intent(inout) :: dq(k)
    integer :: w1, w2
    w1 = wrapped(g, 1, v1)
    w2 = wrapped(g, 1, v2)
    if (w1 <= w2) then
       call scan_slots(g, yq, g%start(row + w1 + 1), g%start(row + w2 + 2) - 1, k, found, dq, iq)
    else                                   ! (the run wraps round a periodic axis 1)
       call scan_slots(g, yq, g%start(row + w1 + 1), g%start(row + g%nc(1) + 1) - 1, k, found, dq, iq)
       call scan_slots(g, yq, g%start(row + 1), g%start(row + w2 + 2) - 1, k, found, dq, iq)
    end if
  end subroutine scan_run

  !> The points in slots a0 .. a1 offered to the k best of query yq.
  subroutine scan_slots(g, yq, a0, a1, k, found, dq, iq)
    type(point_grid), intent(in) :: g
    real(dp), intent(in) :: yq(:)
    integer, intent(in) :: a0, a1, k
    integer, intent(inout) :: found, iq(k)
    real(dp), intent(inout) :: dq(k)
    integer :: a
    real(dp) :: s
    do a = a0, a1
       s = dist2(g, yq, g%xs(:, a))
       if (found == k) then
          if (s > dq(k)) cycle
       end if
       call keep(s, g%perm(a) - 1, found, dq, iq)
    end do
  end subroutine scan_slots

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

end module arpy_knn
