!> Conventional uniform cell list (the baseline of the AR cell-list paper).
!>
!> Build: every particle gets the linear index of its cell, a counting sort
!> (count, prefix sum, scatter) groups particle indices by cell so that cell c
!> owns the contiguous range start(c+1) .. start(c+2)-1 of `perm`; positions
!> and cutoffs are copied into that order for cache-coherent pair loops.
!> No linked lists.
!>
!> Pairs: half-shell iteration.  Each cell is paired with itself (a < b) and
!> with its "forward" neighbour cells, the offsets (dx, dy, dz) that are
!> lexicographically positive with z most significant (13 in 3D, 4 in 2D), so
!> every unordered pair of neighbouring cells is visited exactly once.  Cells
!> are numbered x-fastest, so forward cells that differ only in dx are
!> adjacent in the sorted order and are searched as one contiguous range:
!> the rest of the own cell together with the cell at dx = +1, plus one range
!> per forward row (dy, dz) = (1, 0) [2D and 3D] and (-1..1, 1) [3D]: 2
!> ranges per particle in 2D, 5 in 3D.
!>
!> Positions are padded to three components (z = 0 in 2D) so one loop serves
!> d = 2 and d = 3.  The cell edge is at least the largest reach of a pair
!> under the list's cutoff rule: the largest cutoff plus skin (min and max
!> rules), twice the largest cutoff plus skin (sum rule);
!> the number of cells is capped near 2n so sparse sets with tiny cutoffs
!> cannot exhaust memory (larger cells stay correct, only slower).
module arpy_celllist
  use arpy_memory, only: advise_large
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC, RULE_MIN, RULE_MAX, RULE_SUM
  use arpy_pairs, only: rule_skins, scan_ranges
  use arpy_csr, only: row_builder, rb_init, rb_reserve, rb_join, list_capacity
  use arpy_threads, only: team_size, block_range, MIN_PARALLEL_POINTS, MIN_PARALLEL_ROWS
  use arpy_checks, only: particle_extremes
  implicit none
  private

  type, public :: cell_grid
     integer :: d = 0, n = 0
     integer(i8) :: nc(3) = 1               !< cells per axis
     real(dp) :: lo(3) = 0.0_dp              !< lower corner
     real(dp) :: inv_h(3) = 0.0_dp           !< cells per unit length
     real(dp) :: period(3) = 0.0_dp          !< box edge along periodic axes (the grid wraps), else 0
     integer, allocatable :: start(:)        !< (ncell+1): first sorted slot of each cell (1-based)
     integer, allocatable :: perm(:)         !< sorted slot -> original particle (1-based)
     real(dp), allocatable :: xs(:, :)       !< (3, n) positions in sorted order
     real(dp), allocatable :: rcs(:)         !< cutoffs (+ skin: min and max rules) in sorted order
     integer :: rule = RULE_MIN              !< cutoff rule (arpy_kinds)
     real(dp) :: pskin = 0.0_dp              !< skin added to each pair's reach (sum rule; else in rcs)
  end type cell_grid

  public :: grid_build, grid_half_list, grid_rows, bounding_box, bounding_box_of, gather_slots, &
       range_total, cell_prefix, bin_particles

  !> at most this many parallel chunks of cells in cell_prefix
  integer, parameter :: MAX_CHUNKS = 256
  !> forward rows (dy, dz) searched over dx = -1..1
  integer, parameter :: nrow = 4
  integer, parameter :: fwd_row(2, nrow) = reshape([1, 0,  -1, 1,  0, 1,  1, 1], [2, nrow])

contains

  !> Bin n particles into a uniform grid whose cell edge is >= h, the largest reach of a pair under
  !> `rule` (RULE_MIN if absent).  known: the particles' extremes, if the caller has them
  !> (check_particles), for the box and h without another pass.
  subroutine grid_build(d, n, x, rc, skin, g, info, box_lo, box_hi, periodic, known, rule)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), rc(n), skin
    type(cell_grid), intent(inout) :: g
    integer, intent(out) :: info
    real(dp), intent(in), optional :: box_lo(d), box_hi(d)
    logical, intent(in), optional :: periodic(d)
    type(particle_extremes), intent(in), optional :: known
    integer, intent(in), optional :: rule
    real(dp) :: hi(3), ext(3), h, maxabs, ncr(3), sskin, mult
    integer(i8), allocatable :: cell(:)
    integer(i8) :: ncell, maxcells
    integer :: k, stat

    info = ARPY_OK
    g%rule = RULE_MIN
    if (present(rule)) g%rule = rule
    call rule_skins(g%rule, skin, sskin, g%pskin, mult)
    g%d = d
    g%n = n
    g%lo = 0.0_dp
    hi = 0.0_dp
    if (present(known)) then
       g%lo = known%lo
       hi = known%hi
    else if (n > 0) then
       call bounding_box_of(d, n, x, g%lo, hi)
    end if
    g%period = 0.0_dp
    if (present(periodic)) then             ! periodic axes: cells tile the box [box_lo, box_hi]
       do k = 1, d
          if (.not. periodic(k)) cycle
          g%lo(k) = box_lo(k)
          hi(k) = box_hi(k)
          g%period(k) = box_hi(k) - box_lo(k)
       end do
    end if
    ext = hi - g%lo
    maxabs = max(maxval(abs(g%lo)), maxval(abs(hi)))
    h = 0.0_dp
    if (present(known)) then
       h = mult * known%rhi + skin
    else if (n > 0) then
       h = mult * maxval(rc) + skin
    end if
    ! a relative margin keeps the cell edge strictly above h after rounding
    h = h * (1.0_dp + 1.0e-12_dp) + 16.0_dp * epsilon(1.0_dp) * maxabs
    maxcells = max(2_i8 * n, 64_i8)
    do
       ncr = 1.0_dp
       do k = 1, d
          ncr(k) = max(1.0_dp, min(aint(ext(k) / h), 4.0e9_dp))
       end do
       if (product(ncr) <= real(maxcells, dp)) exit
       h = h * (product(ncr) / real(maxcells, dp))**(1.0_dp / d) * 1.01_dp
    end do
    g%nc = int(ncr, i8)
    ncell = product(g%nc)
    do k = 1, 3
       g%inv_h(k) = 0.0_dp
       if (ext(k) > 0.0_dp) g%inv_h(k) = real(g%nc(k), dp) / ext(k)
    end do

    if (allocated(g%start)) deallocate(g%start)
    if (allocated(g%perm)) deallocate(g%perm)
    if (allocated(g%xs)) deallocate(g%xs)
    if (allocated(g%rcs)) deallocate(g%rcs)
    allocate(g%start(ncell + 1), g%perm(n), g%xs(3, n), g%rcs(n), cell(n), stat=stat)
    if (stat == 0) then
       call advise_large(g%start)
       call advise_large(g%perm)
       call advise_large(g%xs)
       call advise_large(g%rcs)
       call advise_large(cell)
    end if
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if

    call bin_particles(d, n, x, g, cell, info)
    if (info /= ARPY_OK) return
    call gather_slots(d, n, x, rc, sskin, g%perm, g%xs, g%rcs)
  end subroutine grid_build

  !> The prefix sums of a counting sort whose nb blocks of particles counted their cells apart:
  !> over cells i0 .. i1 (in order) and within a cell over blocks (in order), bc(i, t) becomes the
  !> first slot of block t's particles in cell i, from slot first on; start(i) (if present) the
  !> first slot of cell i; last: the slot after them all.  The cells in parallel chunks from
  !> MIN_PARALLEL_ROWS cells (each chunk's total first, then each chunk from its own start): the
  !> slots of the serial sum.
  subroutine cell_prefix(i0, i1, nb, bc, blo, bhi, first, last, start)
    integer(i8), intent(in) :: i0, i1, blo, bhi
    integer, intent(in) :: nb, first
    integer, intent(inout) :: bc(blo:bhi, nb)
    integer, intent(out) :: last
    integer, intent(inout), optional :: start(blo:)
    integer(i8) :: i, c0, c1
    integer :: t, k, nch, h, run
    integer :: base(MAX_CHUNKS + 1)
    nch = 1
    if (i1 - i0 + 1 >= MIN_PARALLEL_ROWS) nch = min(team_size(), MAX_CHUNKS)
    base = 0
    ! (each chunk sums into a private count: threads adding into neighbouring entries of base
    ! would share its cache line at every step)
    !$omp parallel do num_threads(nch) schedule(static, 1) private(c0, c1, i, t, run)
    do h = 1, nch
       call chunk(h, c0, c1)
       run = 0
       do i = c0, c1
          do t = 1, nb
             run = run + bc(i, t)
          end do
       end do
       base(h + 1) = run
    end do
    !$omp end parallel do
    base(1) = first
    do h = 1, nch
       base(h + 1) = base(h + 1) + base(h)
    end do
    !$omp parallel do num_threads(nch) schedule(static, 1) private(c0, c1, i, t, k, run)
    do h = 1, nch
       call chunk(h, c0, c1)
       run = base(h)
       do i = c0, c1
          if (present(start)) start(i) = run
          do t = 1, nb
             k = bc(i, t)
             bc(i, t) = run
             run = run + k
          end do
       end do
    end do
    !$omp end parallel do
    last = base(nch + 1)

  contains

    !> Cells of chunk h.
    subroutine chunk(h, c0, c1)
      integer, intent(in) :: h
      integer(i8), intent(out) :: c0, c1
      c0 = i0 + ((i1 - i0 + 1) * (h - 1)) / nch
      c1 = i0 + ((i1 - i0 + 1) * h) / nch - 1
    end subroutine chunk

  end subroutine cell_prefix

  !> A stable counting sort of the particles by cell: g%start (first slot of each cell, 1-based, with
  !> a sentinel) and g%perm (slot -> particle).  In parallel from MIN_PARALLEL_ROWS particles: each
  !> thread bins one block of particles, and within a cell the blocks follow one another in order,
  !> so the slots are those of a serial sort.  cell(n): workspace.
  subroutine bin_particles(d, n, x, g, cell, info)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n)
    type(cell_grid), intent(inout) :: g
    integer(i8), intent(inout) :: cell(n)
    integer, intent(out) :: info
    integer, allocatable :: bc(:, :)
    integer(i8) :: ncell, c, ci(3)
    integer :: nb, t, p, k, p0, p1, stat, run
    info = ARPY_OK
    ncell = product(g%nc)
    nb = team_size()
    ! (one count per cell and thread: at most about 4e8 counts in all)
    if (n < MIN_PARALLEL_ROWS .or. real(nb, dp) * real(ncell, dp) > 4.0e8_dp) nb = 1
    allocate(bc(ncell, nb), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    call advise_large(bc)
    !$omp parallel do num_threads(nb) schedule(static, 1) private(p0, p1, p, k, ci, c)
    do t = 1, nb
       call block_range(n, nb, t, p0, p1)
       bc(:, t) = 0
       do p = p0, p1
          ci = 0
          do k = 1, d
             ci(k) = min(max(int((x(k, p) - g%lo(k)) * g%inv_h(k), i8), 0_i8), g%nc(k) - 1)
          end do
          c = ci(1) + g%nc(1) * (ci(2) + g%nc(2) * ci(3))
          cell(p) = c
          bc(c + 1, t) = bc(c + 1, t) + 1
       end do
    end do
    !$omp end parallel do
    ! cell c's slots start after all earlier cells; block t's after the blocks before it in the cell
    call cell_prefix(1_i8, ncell, nb, bc, 1_i8, ncell, 1, run, g%start)
    g%start(ncell + 1) = run
    !$omp parallel do num_threads(nb) schedule(static, 1) private(p0, p1, p, c)
    do t = 1, nb
       call block_range(n, nb, t, p0, p1)
       do p = p0, p1
          c = cell(p) + 1
          g%perm(bc(c, t)) = p
          bc(c, t) = bc(c, t) + 1
       end do
    end do
    !$omp end parallel do
  end subroutine bin_particles

  !> bounding_box of many points, one block per thread (minima and maxima are exact in any order).
  subroutine bounding_box_of(d, n, x, lo, hi)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n)
    real(dp), intent(inout) :: lo(3), hi(3)
    real(dp) :: l(3), h(3)
    integer :: nb, k, p0, p1
    nb = team_size()
    if (n < MIN_PARALLEL_ROWS .or. nb <= 1) then
       call bounding_box(d, n, x, lo, hi)
       return
    end if
    l = huge(1.0_dp)
    h = -huge(1.0_dp)
    !$omp parallel do num_threads(nb) schedule(static, 1) private(p0, p1) firstprivate(lo, hi) &
    !$omp reduction(min: l) reduction(max: h)
    do k = 1, nb
       call block_range(n, nb, k, p0, p1)
       call bounding_box(d, p1 - p0 + 1, x(:, p0:p1), lo, hi)
       l(1:d) = min(l(1:d), lo(1:d))
       h(1:d) = max(h(1:d), hi(1:d))
    end do
    !$omp end parallel do
    lo(1:d) = l(1:d)
    hi(1:d) = h(1:d)
  end subroutine bounding_box_of

  !> Bounding box lo(1:d), hi(1:d) of n >= 1 points x(d, n), in one pass.
  pure subroutine bounding_box(d, n, x, lo, hi)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n)
    real(dp), intent(inout) :: lo(3), hi(3)
    real(dp) :: l(3), h(3)
    integer :: p
    l = 0.0_dp
    l(1:d) = x(:, 1)
    h = l
    do p = 2, n
       l(1) = min(l(1), x(1, p))
       h(1) = max(h(1), x(1, p))
       l(2) = min(l(2), x(2, p))
       h(2) = max(h(2), x(2, p))
       if (d == 3) then
          l(3) = min(l(3), x(d, p))
          h(3) = max(h(3), x(d, p))
       end if
    end do
    lo(1:d) = l(1:d)
    hi(1:d) = h(1:d)
  end subroutine bounding_box

  !> Positions (z = 0 in 2D) and cutoffs (+ skin) in slot order: slot s holds
  !> particle perm(s).
  subroutine gather_slots(d, n, x, rc, skin, perm, xs, rcs)
    integer, intent(in) :: d, n, perm(n)
    real(dp), intent(in) :: x(d, n), rc(n), skin
    real(dp), intent(out) :: xs(3, n), rcs(n)
    integer :: s, p
    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_ROWS) schedule(static) private(p)
    do s = 1, n
       p = perm(s)
       xs(1, s) = x(1, p)
       xs(2, s) = x(2, p)
       xs(3, s) = x(d, p) * (d - 2)   ! the z row, or 0 in 2D
       rcs(s) = rc(p) + skin
    end do
    !$omp end parallel do
  end subroutine gather_slots

  !> Number of slots in the ranges rs(r) .. re(r), r = 1 .. nr (empty ones count 0).
  pure function range_total(nr, rs, re) result(total)
    integer, intent(in) :: nr, rs(*), re(*)
    integer(i8) :: total
    integer :: r
    total = 0
    do r = 1, nr
       total = total + max(0, re(r) - rs(r) + 1)
    end do
  end function range_total

  !> Symmetric neighbour list by half-shell iteration over the grid.  Row a
  !> of rb belongs to the particle in sorted slot a, i.e. particle g%perm(a);
  !> entries are 0-based particle indices.
  subroutine grid_half_list(g, rb, info)
    type(cell_grid), intent(in) :: g
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    integer(i8) :: nnz

    call rb_init(rb, g%n, list_capacity(g%d, g%n), info)
    if (info /= ARPY_OK) return
    nnz = 0
    call grid_rows(g%start, g%nc, g%xs, g%rcs, g%perm, rb, nnz, info, g%period, g%rule, g%pskin)
  end subroutine grid_half_list

  !> Half-shell rows over a uniform grid of nc(1) x nc(2) x nc(3) cells
  !> numbered axis 1 fastest, cell c (0-based) owning slots start(c) ..
  !> start(c+1) - 1 (the last entry of start is a sentinel).  The row of the
  !> particle in slot a gets the later particles of its cell and those of the
  !> forward cells; rows are appended to rb in slot order from entry nnz on.
  !> Used by the uniform cell list and by the deepest level of an AR tree
  !> kept as a dense table.
  !>
  !> In parallel (from MIN_PARALLEL_POINTS slots: a row scans the particles of several cells, like
  !> the AR list's rows, which run in parallel from two blocks of ROWS_PER_BLOCK): the cells, in
  !> that order, are split into one contiguous run per thread, balanced by particles (not whole pencils: a long thin domain
  !> has few of them); the first run is built in rb itself, each other run into
  !> its own buffer, and the buffers are appended in slot order, so the list is
  !> the serial one whatever the number of threads.  (More runs, taken in turn,
  !> balance the threads better but copy more of the list into fresh memory in
  !> the append: slower in all.)  rule, pskin: the pair test (scan_ranges;
  !> RULE_MIN if absent).
  subroutine grid_rows(start, nc, xs, rcs, perm, rb, nnz, info, period, rule, pskin)
    integer, intent(in) :: start(0:)
    integer(i8), intent(in) :: nc(3)
    real(dp), intent(in) :: xs(3, *), rcs(*)
    integer, intent(in) :: perm(*)
    type(row_builder), intent(inout) :: rb
    integer(i8), intent(inout) :: nnz
    integer, intent(out) :: info
    real(dp), intent(in), optional :: period(3)
    integer, intent(in), optional :: rule
    real(dp), intent(in), optional :: pskin
    real(dp) :: per(3), ps
    integer :: rl
    type(row_builder), allocatable :: part(:)
    integer(i8), allocatable :: cb(:)
    integer, allocatable :: pinfo(:)
    integer(i8) :: ncell, pnnz, lo, hi, mid
    integer :: nrun, k, s0, s1, stat, nslot

    per = 0.0_dp
    if (present(period)) per = period
    rl = RULE_MIN
    if (present(rule)) rl = rule
    ps = 0.0_dp
    if (present(pskin)) ps = pskin
    ncell = nc(1) * nc(2) * nc(3)
    nslot = start(ncell) - start(0)
    nrun = int(min(int(team_size(), i8), ncell))
    if (nrun <= 1 .or. nslot < MIN_PARALLEL_POINTS) then
       call cell_rows(start, nc, xs, rcs, perm, 0_i8, ncell, 0, rb, nnz, info, per, rl, ps)
       rb%nnz = nnz
       return
    end if
    allocate(part(nrun), cb(0:nrun), pinfo(nrun), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    ! run k: cells cb(k-1) .. cb(k)-1, about nslot / nrun particles each (the first cell whose
    ! particles begin at or after the k-th share, by bisection of start).  (Runs of equal checks
    ! instead, counted in a pass over the cells, balance the threads better, but the pass costs
    ! what they gain.)
    cb(0) = 0
    do k = 1, nrun - 1
       lo = cb(k - 1)
       hi = ncell
       do while (lo < hi)
          mid = (lo + hi) / 2
          if (start(mid) - start(0) < (int(nslot, i8) * k) / nrun) then
             lo = mid + 1
          else
             hi = mid
          end if
       end do
       cb(k) = lo
    end do
    cb(nrun) = ncell
    ! the first run writes its rows straight into rb (as the serial loop does), the others into
    ! their own builders, appended after it in order
    !$omp parallel do num_threads(nrun) schedule(static, 1) private(k, s0, s1, pnnz)
    do k = 1, nrun
       if (k == 1) then
          call cell_rows(start, nc, xs, rcs, perm, 0_i8, cb(1), 0, rb, nnz, pinfo(1), per, rl, ps)
          cycle
       end if
       s0 = start(cb(k - 1))
       s1 = start(cb(k))
       call rb_init(part(k), s1 - s0, list_capacity(merge(3, 2, nc(3) > 1), s1 - s0), pinfo(k))
       if (pinfo(k) /= ARPY_OK) cycle
       pnnz = 0
       call cell_rows(start, nc, xs, rcs, perm, cb(k - 1), cb(k), s0 - 1, part(k), pnnz, pinfo(k), per, rl, ps)
       part(k)%nnz = pnnz
    end do
    !$omp end parallel do
    rb%nnz = nnz
    info = maxval(pinfo)
    if (info /= ARPY_OK) return
    call rb_join(rb, nnz, nrun - 1, part(2:), [(int(start(cb(k - 1))) - 1, k = 2, nrun)], info)
  end subroutine grid_rows

  !> The rows of the particles in cells c0 .. c1-1 (numbered axis 1 fastest, see grid_rows),
  !> appended to rb from entry nnz on; the row end of slot a goes to rb%off(a - shift + 1).
  !> period(k) > 0: the grid wraps along axis k (cells tile a periodic box of that edge, at least 3
  !> of them): the cells on its faces take their forward neighbours across it (wrapped_rows).
  !> rule, pskin: the pair test (scan_ranges).
  subroutine cell_rows(start, nc, xs, rcs, perm, c0, c1, shift, rb, nnz, info, period, rule, pskin)
    integer, intent(in) :: start(0:)
    integer(i8), intent(in) :: nc(3), c0, c1
    real(dp), intent(in) :: xs(3, *), rcs(*), period(3), pskin
    integer, intent(in) :: perm(*), shift, rule
    type(row_builder), intent(inout) :: rb
    integer(i8), intent(inout) :: nnz
    integer, intent(out) :: info
    integer(i8) :: c, cand, cc(3)
    integer :: nr, a, rs(1 + nrow), re(1 + nrow)
    logical :: wraps(3)

    info = ARPY_OK
    wraps = period > 0.0_dp
    call cell_coords(nc, c0, cc)
    cc(1) = cc(1) - 1
    do c = c0, c1 - 1
       call next_cell(nc, cc)
       if (start(c) == start(c + 1)) cycle
       if (on_face(cc(1), 1) .or. on_face(cc(2), 2) .or. on_face(cc(3), 3)) then
          call wrapped_rows(start, nc, xs, rcs, perm, cc, period, shift, rb, nnz, info, rule, pskin)
          if (info /= ARPY_OK) return
          cycle
       end if
       call forward_ranges(start, nc, c, cc, nr, rs, re)
       cand = range_total(nr, rs, re)
       do a = start(c), start(c + 1) - 1
          ! room for every candidate of this row (branch-free acceptance)
          if (nnz + cand > size(rb%idx, kind=i8)) then
             call rb_reserve(rb, nnz, cand, info)
             if (info /= ARPY_OK) return
          end if
          rs(1) = a + 1
          call scan_ranges(xs, rcs, perm, xs(:, a), rcs(a), nr, rs, re, rb%idx, nnz, rule, pskin)
          rb%off(a - shift + 1) = nnz
       end do
    end do

  contains

    !> Whether cell coordinate ck lies on a face of a wrapping axis k.
    logical function on_face(ck, k)
      integer(i8), intent(in) :: ck
      integer, intent(in) :: k
      on_face = wraps(k) .and. (ck == 0 .or. ck == nc(k) - 1)
    end function on_face

  end subroutine cell_rows

  !> Coordinates cc (0-based, axis 1 fastest) of cell c of a grid of nc cells.
  pure subroutine cell_coords(nc, c, cc)
    integer(i8), intent(in) :: nc(3), c
    integer(i8), intent(out) :: cc(3)
    cc(1) = mod(c, nc(1))
    cc(2) = mod(c / nc(1), nc(2))
    cc(3) = c / (nc(1) * nc(2))
  end subroutine cell_coords

  !> The coordinates of the next cell (the loops over cells count them along: two integer
  !> divisions per cell cost 0.7 of 10.8 ms in the rows of 1e6 particles).
  pure subroutine next_cell(nc, cc)
    integer(i8), intent(in) :: nc(3)
    integer(i8), intent(inout) :: cc(3)
    cc(1) = cc(1) + 1
    if (cc(1) < nc(1)) return
    cc(1) = 0
    cc(2) = cc(2) + 1
    if (cc(2) < nc(2)) return
    cc(2) = 0
    cc(3) = cc(3) + 1
  end subroutine next_cell

  !> The slot ranges of the half shell of cell c (coordinates cc) in a grid that does not wrap:
  !> range 1 is the cell itself and the cell at dx = +1 (adjacent in memory), ranges 2 .. nr the
  !> forward rows, dx = -1 .. 1 clipped to the grid.
  pure subroutine forward_ranges(start, nc, c, cc, nr, rs, re)
    integer, intent(in) :: start(0:)
    integer(i8), intent(in) :: nc(3), c, cc(3)
    integer, intent(out) :: nr, rs(1 + nrow), re(1 + nrow)
    integer(i8) :: oy, oz, xlo, xhi
    integer :: k
    rs(1) = start(c)
    re(1) = start(c + 1) - 1
    if (cc(1) + 1 < nc(1)) re(1) = start(c + 2) - 1
    xlo = max(cc(1) - 1, 0_i8)
    xhi = min(cc(1) + 1, nc(1) - 1)
    nr = 1
    do k = 1, nrow
       oy = cc(2) + fwd_row(1, k)
       oz = cc(3) + fwd_row(2, k)
       if (oy < 0 .or. oy >= nc(2) .or. oz >= nc(3)) cycle
       nr = nr + 1
       rs(nr) = start(xlo + nc(1) * (oy + nc(2) * oz))
       re(nr) = start(xhi + nc(1) * (oy + nc(2) * oz) + 1) - 1
    end do
  end subroutine forward_ranges


  !> The rows of the particles of cell c (coordinates, 0-based) on a face of a wrapping axis: its
  !> own later particles, then each forward neighbour cell (the offsets of the half shell), taken
  !> across the periodic faces.  Across a face the neighbour is an image: the pair's distance is
  !> that of the image of the larger particle index at the smaller one (x + s period, as the
  !> periodic images of arpy_search make it), so the lists equal those built from images.
  !> rule, pskin: the pair test (scan_ranges).
  subroutine wrapped_rows(start, nc, xs, rcs, perm, c, period, shift, rb, nnz, info, rule, pskin)
    integer, intent(in) :: start(0:), perm(*), shift, rule
    integer(i8), intent(in) :: nc(3), c(3)
    real(dp), intent(in) :: xs(3, *), rcs(*), period(3), pskin
    type(row_builder), intent(inout) :: rb
    integer(i8), intent(inout) :: nnz
    integer, intent(out) :: info
    integer, parameter :: noff = 13
    integer :: nb, a, b, k, o, first(noff), last(noff), s(3, noff)
    integer(i8) :: oc(3), cand, own
    integer :: off3(3)
    real(dp) :: ya(3), yb(3), dx(3), rm

    info = ARPY_OK
    ! the forward neighbour cells: (1, 0, 0), then the rows (dy, dz) of fwd_row over dx = -1..1
    nb = 0
    cand = 0
    do o = 0, 3 * nrow
       if (o == 0) then
          off3 = [1, 0, 0]
       else
          off3 = [mod(o - 1, 3) - 1, fwd_row(1, (o - 1) / 3 + 1), fwd_row(2, (o - 1) / 3 + 1)]
       end if
       oc = c + off3
       s(:, nb + 1) = 0
       do k = 1, 3
          if (oc(k) >= 0 .and. oc(k) < nc(k)) cycle
          if (period(k) <= 0.0_dp) exit            ! beyond a free face: no neighbour
          s(k, nb + 1) = merge(1, -1, oc(k) >= nc(k))
          oc(k) = modulo(oc(k), nc(k))
       end do
       if (k <= 3) cycle
       own = oc(1) + nc(1) * (oc(2) + nc(2) * oc(3))
       if (start(own) == start(own + 1)) cycle
       nb = nb + 1
       first(nb) = start(own)
       last(nb) = start(own + 1) - 1
       cand = cand + (last(nb) - first(nb) + 1)
    end do
    own = c(1) + nc(1) * (c(2) + nc(2) * c(3))
    cand = cand + (start(own + 1) - start(own))
    do a = start(own), start(own + 1) - 1
       if (nnz + cand > size(rb%idx, kind=i8)) then
          call rb_reserve(rb, nnz, cand, info)
          if (info /= ARPY_OK) return
       end if
       ! the rest of the own cell, then the neighbour cells
       call scan_ranges(xs, rcs, perm, xs(:, a), rcs(a), 1, [a + 1], [start(own + 1) - 1], rb%idx, nnz, rule, pskin)
       do o = 1, nb
          if (all(s(:, o) == 0)) then
             call scan_ranges(xs, rcs, perm, xs(:, a), rcs(a), 1, first(o:o), last(o:o), rb%idx, nnz, rule, pskin)
             cycle
          end if
          do b = first(o), last(o)
             ! the image of the larger index, shifted towards the other particle
             if (perm(b) > perm(a)) then
                yb = xs(:, b) + real(s(:, o), dp) * period
                ya = xs(:, a)
             else
                yb = xs(:, b)
                ya = xs(:, a) - real(s(:, o), dp) * period
             end if
             dx = yb - ya
             select case (rule)
             case (RULE_MAX)
                rm = max(rcs(a), rcs(b))
             case (RULE_SUM)
                rm = (rcs(a) + rcs(b)) + pskin
             case default
                rm = min(rcs(a), rcs(b))
             end select
             rb%idx(nnz + 1) = perm(b) - 1
             nnz = nnz + merge(1_i8, 0_i8, dx(1) * dx(1) + dx(2) * dx(2) + dx(3) * dx(3) <= rm * rm)
          end do
       end do
       rb%off(a - shift + 1) = nnz
    end do
  end subroutine wrapped_rows

end module arpy_celllist
