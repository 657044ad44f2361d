!> Build of the AR tree (Awile et al., CPC 2012, Algorithms 1 and 2).
!>
!> Algorithm 1: levels are found by exact power-of-two comparisons and
!> particles are grouped by level with a counting sort (O(N), the same blocks
!> as the paper's sort by descending cutoff).  Algorithm 2 then finds the
!> cells of every level block: on hashed levels by the recursive partition
!> of arpy_arpartition; on dense levels (those whose occupied region is
!> compact, see plan_dense) all particles are put into their cells by one
!> counting sort in the tables' row-major order, so that a stencil row is
!> one contiguous slot range, and the cells above are flagged finer
!> bottom-up.
module arpy_arbuild
  use arpy_memory, only: advise_large
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_DEPTH, ARPY_ERR_OUTSIDE, RULE_MIN
  use arpy_threads, only: team_size, block_range, MIN_PARALLEL_ROWS
  use arpy_celllist, only: bounding_box, bounding_box_of, gather_slots, cell_prefix
  use arpy_pairs, only: rule_skins
  use arpy_arkeys, only: AR_MAXLEVEL, ar_first_index, ar_morton, ar_level_of, axis_cell, pow2
  use arpy_arhash, only: NO_ENTRY, entry_finer, entry_pack, hash_init, hash_insert, hash_flag_finer
  use arpy_artree, only: ar_tree, dense_slot, dense_range, dense_flag_finer
  use arpy_arpartition, only: partition_level
  use arpy_checks, only: particle_extremes
  implicit none
  private

  public :: ar_build

  !> at most this many blocks of particles in the counting sort of place_slots
  integer, parameter :: MAX_PLACE_BLOCKS = 256

contains

  !> Algorithms 1 and 2: build the AR tree of n particles.
  !> lo_in, hi_in: the domain if has_domain (particles outside it are an
  !> error, ARPY_ERR_OUTSIDE, bad = particle); else the bounding box.
  !> for_lists: a tree for Algorithm 3 alone, whose particles search their own
  !> and finer levels only: the cells of dense levels flag their ancestors
  !> finer down to the coarsest level that holds particles, not to the root
  !> (at lambda = 1, one level, that spares the walk up the levels from every
  !> other cell, about 1 ms at 1e6 particles).  Cell lookups from the root (queries, Op1-Op5) need the
  !> whole tree.
  !> ext: the particles' extremes, if the caller has them (check_particles), for the bounding box
  !> and the cutoffs' range without another pass.
  !> rule: the cutoff rule of the tree's lists (RULE_MIN if absent).  A particle's level is that of
  !> the largest reach it can have with a partner no larger than itself: rc + skin (min and max
  !> rules), 2 rc + skin (sum rule); see arpy_arlists for how the lists use it.
  subroutine ar_build(d, n, x, rc, skin, has_domain, lo_in, hi_in, t, info, bad, for_lists, ext, rule)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), rc(n), skin, lo_in(d), hi_in(d)
    logical, intent(in) :: has_domain
    type(ar_tree), intent(inout) :: t
    integer, intent(out) :: info, bad
    logical, intent(in), optional :: for_lists
    type(particle_extremes), intent(in), optional :: ext
    integer, intent(in), optional :: rule
    integer, allocatable :: cnt(:), slot_of_level(:)
    ! plev: each particle's level, then its table index.  8 bytes, as the
    ! uniform list's cell array: freed before the list is built, it leaves
    ! room for the list's row offsets (8 bytes per particle), so the heap
    ! need not grow for them.
    integer(i8), allocatable :: plev(:)
    integer(i8) :: slot
    real(dp), allocatable :: bmin(:, :), bmax(:, :)
    real(dp) :: hi(3), rlo, rhi, sskin, mult
    integer :: k, stat, nhashed

    info = ARPY_OK
    bad = 0
    t%rule = RULE_MIN
    if (present(rule)) t%rule = rule
    call rule_skins(t%rule, skin, sskin, t%pskin, mult)
    ! ---- the cube: anchored at the domain box's lo, its edge D_m fitted to
    !      the smallest cutoff (root_edge); 1 without particles
    t%d = d
    t%n = n
    call domain_box(d, n, x, has_domain, lo_in, hi_in, t%lo, hi, info, bad, ext)
    if (info /= ARPY_OK) return
    t%dm = 1.0_dp
    if (n > 0) then
       if (present(ext)) then
          rlo = ext%rlo
          rhi = ext%rhi
       else
          call cutoff_range(n, rc, rlo, rhi)
       end if
       t%dm = root_edge(maxval(hi(1:d) - t%lo(1:d)), mult * rlo + skin, mult * rhi + skin, AR_MAXLEVEL(d))
    end if

    ! ---- Algorithm 1: levels, grouped by a counting sort
    allocate(plev(n), stat=stat)
    if (stat /= 0) goto 90
    call advise_large(plev)
    t%maxlevel = 0
    allocate(cnt(0:64), bmin(3, 0:63), bmax(3, 0:63), stat=stat)
    if (stat /= 0) goto 90
    call find_levels(t, d, n, x, rc, skin, mult, plev, cnt, bmin, bmax, info)
    if (info /= ARPY_OK) return
    if (t%maxlevel > AR_MAXLEVEL(d)) then
       info = ARPY_ERR_DEPTH
       bad = maxloc(plev, dim=1)
       return
    end if
    allocate(slot_of_level(0:t%maxlevel + 1), stat=stat)
    if (stat /= 0) goto 90
    cnt(0) = 1
    do k = 1, t%maxlevel + 1
       cnt(k) = cnt(k) + cnt(k - 1)
    end do
    slot_of_level(:) = cnt(0:t%maxlevel + 1)   ! first slot of each level; the last = n + 1
    t%holds = .false.
    t%holds(0:t%maxlevel) = slot_of_level(1:t%maxlevel + 1) > slot_of_level(0:t%maxlevel)
    t%kflag = 1
    if (present(for_lists)) then
       if (for_lists) t%kflag = max(1, findloc(t%holds, .true., dim=1) - 1)
    end if

    if (allocated(t%perm)) deallocate(t%perm)     ! (each on its own: a caller may
    if (allocated(t%xs)) deallocate(t%xs)         !  have moved perm out of the tree)
    if (allocated(t%rcs)) deallocate(t%rcs)
    allocate(t%perm(n), t%xs(3, n), t%rcs(n), stat=stat)
    if (stat /= 0) goto 90
    call advise_large(t%perm)
    call advise_large(t%xs)
    call advise_large(t%rcs)

    ! ---- the cell table: dense arrays for compact levels, the hash for the rest
    call plan_dense(t, d, n, bmin, bmax, slot_of_level, info)
    if (info /= ARPY_OK) return
    ! slots: by level, and on dense levels by cell (one counting sort)
    call place_slots(t, d, n, x, plev, slot_of_level, nhashed, info)
    if (info /= ARPY_OK) return
    call hash_init(t%hash, d, 16_i8 + nhashed, info)
    if (info /= ARPY_OK) return

    ! ---- Algorithm 2 on each level block
    if (allocated(t%leaf_key)) deallocate(t%leaf_key, t%leaf_first, t%leaf_last)
    allocate(t%leaf_key(max(nhashed, 1)), t%leaf_first(max(nhashed, 1)), &
         t%leaf_last(max(nhashed, 1)), stat=stat)
    if (stat /= 0) goto 90
    call level_cells(t, n, x, slot_of_level, info)
    if (info /= ARPY_OK) return
    ! the root: level-0 particles are its own; finer if anything else exists
    if (t%maxlevel > 0) then
       call hash_insert(t%hash, 1_i8, slot, info)
       if (info /= ARPY_OK) return
       call hash_flag_finer(t%hash, slot)
    end if

    ! ---- gather positions and cutoffs into slot order
    call gather_slots(d, n, x, rc, sskin, t%perm, t%xs, t%rcs)
    return
90  info = ARPY_ERR_ALLOC
  end subroutine ar_build

  !> The root's edge D_m for a box of largest extent ext and cutoffs rmin ..
  !> rmax (skin included): D_m = r * 2**K with r the double just above rmin
  !> and K >= 0 the fewest doublings that reach ext.  The particles of the
  !> smallest cutoff then sit on level K, whose cells are r wide: as narrow as
  !> the rule "cell edge > cutoff" allows, for every N (an edge of ext / 2**k
  !> would lie anywhere in (rmin, 2 rmin]).  If that puts them below level
  !> kmax, the edge is ext as in the paper (footnote 1; rmax if ext is 0), so
  !> the fitted root never costs depth.
  pure function root_edge(ext, rmin, rmax, kmax) result(dm)
    real(dp), intent(in) :: ext, rmin, rmax
    integer, intent(in) :: kmax
    real(dp) :: dm
    integer :: k
    dm = nearest(rmin, 1.0_dp)
    k = 0
    do while (dm < ext .and. k <= kmax)
       dm = dm * 2.0_dp
       k = k + 1
    end do
    if (k > kmax) then
       dm = ext
       if (.not. (dm > 0.0_dp)) dm = rmax
    end if
  end function root_edge

  !> The smallest and largest of the n >= 1 cutoffs rc (exact; threads from MIN_PARALLEL_ROWS).
  subroutine cutoff_range(n, rc, rlo, rhi)
    integer, intent(in) :: n
    real(dp), intent(in) :: rc(n)
    real(dp), intent(out) :: rlo, rhi
    integer :: p
    rlo = rc(1)
    rhi = rc(1)
    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_ROWS) schedule(static) &
    !$omp& reduction(min: rlo) reduction(max: rhi)
    do p = 2, n
       rlo = min(rlo, rc(p))
       rhi = max(rhi, rc(p))
    end do
    !$omp end parallel do
  end subroutine cutoff_range

  !> The domain box lo .. hi (zero beyond d): [lo_in, hi_in] if has_domain
  !> (a particle outside it: ARPY_ERR_OUTSIDE, bad = the particle), else the
  !> particles' bounding box (from ext if present).
  subroutine domain_box(d, n, x, has_domain, lo_in, hi_in, lo, hi, info, bad, ext)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), lo_in(d), hi_in(d)
    logical, intent(in) :: has_domain
    real(dp), intent(out) :: lo(3), hi(3)
    integer, intent(inout) :: info, bad
    type(particle_extremes), intent(in), optional :: ext
    integer :: p
    lo = 0.0_dp
    hi = 0.0_dp
    if (has_domain) then
       lo(1:d) = lo_in
       hi(1:d) = hi_in
       do p = 1, n
          if (any(x(:, p) < lo_in) .or. any(x(:, p) > hi_in)) then
             info = ARPY_ERR_OUTSIDE
             bad = p
             return
          end if
       end do
    else if (present(ext)) then
       lo = ext%lo
       hi = ext%hi
    else if (n > 0) then
       call bounding_box_of(d, n, x, lo, hi)
    end if
  end subroutine domain_box

  !> Algorithm 1: each particle's level plev(p) (that of mult rc + skin), and per level k the
  !> number of its particles cnt(k + 1) and their bounding box bmin(:, k) ..
  !> bmax(:, k) (for plan_dense); t%maxlevel the deepest non-empty level.
  subroutine find_levels(t, d, n, x, rc, skin, mult, plev, cnt, bmin, bmax, info)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), rc(n), skin, mult
    integer(i8), intent(out) :: plev(n)
    integer, intent(out) :: cnt(0:), info
    real(dp), intent(out) :: bmin(:, 0:), bmax(:, 0:)
    integer, allocatable :: bcnt(:, :)
    real(dp), allocatable :: blo(:, :, :), bhi(:, :, :)
    integer :: b, nb, k, stat, p0, p1
    ! blocks of particles in parallel from MIN_PARALLEL_ROWS, each with its own counts and boxes,
    ! joined after (integer sums, exact minima and maxima: the same for any number of blocks)
    nb = team_size()
    if (n < MIN_PARALLEL_ROWS) nb = 1
    info = ARPY_OK
    allocate(bcnt(0:64, nb), blo(3, 0:63, nb), bhi(3, 0:63, nb), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    !$omp parallel do num_threads(nb) schedule(static, 1) private(p0, p1)
    do b = 1, nb
       call block_range(n, nb, b, p0, p1)
       call block_levels(p0, p1, bcnt(:, b), blo(:, :, b), bhi(:, :, b))
    end do
    !$omp end parallel do
    cnt = 0
    bmin = huge(1.0_dp)
    bmax = -huge(1.0_dp)
    do b = 1, nb
       cnt(0:64) = cnt(0:64) + bcnt(:, b)
       bmin(1:d, :) = min(bmin(1:d, :), blo(1:d, :, b))
       bmax(1:d, :) = max(bmax(1:d, :), bhi(1:d, :, b))
    end do
    do k = 63, 0, -1
       if (cnt(k + 1) > 0) exit
    end do
    t%maxlevel = max(k, 0)

  contains

    !> Particles p0 .. p1: their levels into plev, counts per level (level k at c(k + 1)) and
    !> bounding boxes per level, by runs of one level (equal cutoffs are common).
    subroutine block_levels(p0_in, p1, c, lo, hi)
      integer, intent(in) :: p0_in, p1
      integer, intent(out) :: c(0:64)
      real(dp), intent(out) :: lo(3, 0:63), hi(3, 0:63)
      real(dp) :: rmin(3), rmax(3)
      integer :: p, p0, kb
      c = 0
      lo = huge(1.0_dp)
      hi = -huge(1.0_dp)
      p0 = p0_in
      do while (p0 <= p1)
         kb = ar_level_of(mult * rc(p0) + skin, t%dm)
         p = p0
         do while (p < p1)
            if (rc(p + 1) /= rc(p)) then
               if (ar_level_of(mult * rc(p + 1) + skin, t%dm) /= kb) exit
            end if
            p = p + 1
         end do
         plev(p0:p) = kb
         c(kb + 1) = c(kb + 1) + (p - p0 + 1)
         call bounding_box(d, p - p0 + 1, x(:, p0:p), rmin, rmax)
         lo(1:d, kb) = min(lo(1:d, kb), rmin(1:d))
         hi(1:d, kb) = max(hi(1:d, kb), rmax(1:d))
         p0 = p + 1
      end do
    end subroutine block_levels

  end subroutine find_levels

  !> Algorithm 2 on every level block (first_slot(k): the first slot of
  !> level k): the cells of dense levels from place_slots' counting sort,
  !> those of hashed levels by the recursive partition; t%hleaf indexes the
  !> leaves recorded per level.
  subroutine level_cells(t, n, x, first_slot, info)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: n
    real(dp), intent(in) :: x(:, :)
    integer, intent(in) :: first_slot(0:)
    integer, intent(out) :: info
    integer(i8), allocatable :: key(:)
    integer :: k, s0, stat
    info = ARPY_OK
    t%nleaf = 0
    t%ndleaf = 0
    t%hleaf = 1
    do k = 0, t%maxlevel
       t%hleaf(k) = t%nleaf + 1
       s0 = first_slot(k)
       if (first_slot(k + 1) == s0) cycle
       if (t%dense(k)) then
          call dense_cells(t, k, s0, info)
          if (info /= ARPY_OK) return
          cycle
       end if
       if (.not. allocated(key)) then     ! Morton keys, for the hashed levels only
          allocate(key(n), stat=stat)
          if (stat /= 0) then
             info = ARPY_ERR_ALLOC
             return
          end if
       end if
       call partition_level(t, x, k, s0, first_slot(k + 1) - 1, key, info)
       if (info /= ARPY_OK) return
    end do
    t%hleaf(t%maxlevel + 1:) = t%nleaf + 1
  end subroutine level_cells

  !> Put the particles into slots: level by level (Algorithm 1's blocks,
  !> first_slot(k) the first slot of level k), and within a dense level by
  !> cell in the table's row-major order (axis 1 fastest), all in one
  !> counting sort over the particles.  This is Algorithm 2 on the dense
  !> levels: the same cells as the recursive partition, found directly, and
  !> a cell's forward neighbours become a few contiguous slot ranges, as in
  !> a uniform cell list.  On exit dstart(i) holds the slot after the last
  !> of dense cell i (dense_cells turns it into the first), and plev is
  !> overwritten (dense: table index; other levels: -(level + 1)).
  !> nhashed: the number of particles on the other (hashed) levels.
  !> In parallel from MIN_PARALLEL_ROWS particles: each thread counts and
  !> places one block of particles, and within a cell (or a hashed level)
  !> the blocks follow one another in order, so the slots are those of the
  !> serial sort.
  subroutine place_slots(t, d, n, x, plev, first_slot, nhashed, info)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n)
    integer(i8), intent(inout) :: plev(n)
    integer, intent(in) :: first_slot(0:)
    integer, intent(out) :: nhashed, info
    integer, allocatable :: bc(:, :), hc(:, :)
    integer(i8) :: i, i0, i1, ndc
    integer(i8) :: bfirst(MAX_PLACE_BLOCKS), blast(MAX_PLACE_BLOCKS)
    logical :: bsorted(MAX_PLACE_BLOCKS), in_order
    integer :: b, nb, k, pos, c, stat
    info = ARPY_OK
    ndc = size(t%dstart, kind=i8)
    nb = team_size()
    ! (one count per dense cell and thread: at most about 4e8 counts in all)
    if (n < MIN_PARALLEL_ROWS .or. real(nb, dp) * real(ndc, dp) > 4.0e8_dp) nb = 1
    nb = min(nb, MAX_PLACE_BLOCKS)
    allocate(bc(0:ndc - 1, nb), hc(0:t%maxlevel, nb), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    call advise_large(bc)
    !$omp parallel do num_threads(nb) schedule(static, 1)
    do b = 1, nb
       call count_block(b)
    end do
    !$omp end parallel do
    ! counts -> each block's first slot in each cell (hashed level), level by level
    nhashed = 0
    do k = 0, t%maxlevel
       pos = first_slot(k)
       if (.not. t%dense(k)) then
          nhashed = nhashed + (first_slot(k + 1) - first_slot(k))
          do b = 1, nb
             c = hc(k, b)
             hc(k, b) = pos
             pos = pos + c
          end do
          cycle
       end if
       call dense_range(t, k, i0, i1)
       call cell_prefix(i0, i1, nb, bc, 0_i8, ndc - 1, first_slot(k), pos)
       t%dstart(i1 + 1) = pos                 ! = first_slot(k + 1)
    end do
    ! particles already in slot order (all on dense levels, table indices never decreasing: a
    ! caller who keeps them in the order of neighbor_list_in_cell_order) keep their places
    in_order = all(bsorted(1:nb))
    do b = 2, nb
       in_order = in_order .and. bfirst(b) >= blast(b - 1)
    end do
    if (in_order) then
       !$omp parallel do num_threads(nb) schedule(static)
       do c = 1, n
          t%perm(c) = c
       end do
       !$omp end parallel do
       do k = 0, t%maxlevel                    ! a cell ends where the next begins
          if (.not. t%dense(k)) cycle
          call dense_range(t, k, i0, i1)
          t%dstart(i0:i1 - 1) = bc(i0 + 1:i1, 1)
          t%dstart(i1) = t%dstart(i1 + 1)
       end do
       return
    end if
    !$omp parallel do num_threads(nb) schedule(static, 1)
    do b = 1, nb
       call place_block(b)
    end do
    !$omp end parallel do
    do k = 0, t%maxlevel                       ! the last block's next slot ends the cell
       if (.not. t%dense(k)) cycle
       call dense_range(t, k, i0, i1)
       t%dstart(i0:i1) = bc(i0:i1, nb)
    end do

  contains

    !> The particles p0 .. p1 of block b: their table index (dense) or -(level + 1) into plev,
    !> their counts per cell into bc(:, b) and per hashed level into hc(:, b); whether the block
    !> is in slot order (bsorted(b): on dense levels, table indices bfirst(b) .. blast(b) never
    !> decreasing).
    subroutine count_block(b)
      integer, intent(in) :: b
      integer(i8) :: j, top, off, s2, s3, c0(3), jfirst, jlast
      real(dp) :: p2, lo(3), dm
      integer :: p, p0, p1, kb, kp
      logical :: ordered
      call block_range(n, nb, b, p0, p1)
      bc(:, b) = 0
      hc(:, b) = 0
      ordered = .true.                     ! (table indices in order, none hashed; an empty block is)
      jfirst = huge(1_i8)
      jlast = -huge(1_i8)
      kp = -1
      p2 = 1.0_dp
      top = 0
      off = 0
      s2 = 0
      s3 = 0
      lo = t%lo
      dm = t%dm
      do p = p0, p1
         kb = int(plev(p))
         if (.not. t%dense(kb)) then
            plev(p) = -(kb + 1)
            hc(kb, b) = hc(kb, b) + 1
            ordered = .false.
            cycle
         end if
         if (kb /= kp) then          ! the level's table, in scalars (runs of one level are common)
            kp = kb
            p2 = pow2(kb)
            top = ishft(1_i8, kb) - 1_i8
            s2 = t%dext(1, kb)
            s3 = t%dext(1, kb) * t%dext(2, kb)
            c0 = t%dlo(:, kb)
            off = t%doff(kb) - c0(1) - s2 * c0(2) - s3 * c0(3)
         end if
         ! dense_slot of the particle's cell
         j = off + axis_cell(x(1, p), lo(1), dm, p2, top) + s2 * axis_cell(x(2, p), lo(2), dm, p2, top)
         if (d == 3) j = j + s3 * axis_cell(x(d, p), lo(3), dm, p2, top)
         plev(p) = j
         bc(j, b) = bc(j, b) + 1
         ordered = ordered .and. j >= jlast
         jfirst = min(jfirst, j)
         jlast = j
      end do
      bsorted(b) = ordered
      bfirst(b) = jfirst
      blast(b) = jlast
    end subroutine count_block

    !> Block b's particles into their slots, in particle order within each cell.
    subroutine place_block(b)
      integer, intent(in) :: b
      integer(i8) :: j
      integer :: p, p0, p1, kb
      call block_range(n, nb, b, p0, p1)
      do p = p0, p1
         j = plev(p)
         if (j >= 0) then
            t%perm(bc(j, b)) = p
            bc(j, b) = bc(j, b) + 1
         else
            kb = int(-j) - 1
            t%perm(hc(kb, b)) = p
            hc(kb, b) = hc(kb, b) + 1
         end if
      end do
    end subroutine place_block

  end subroutine place_slots

  !> Finish dense level k (first slot s0) after place_slots: dstart back to
  !> each cell's first slot, every non-empty cell's slot range into the
  !> table (these cells are the level's leaves), and every such cell's
  !> ancestors (down to level t%kflag) flagged finer, bottom-up until one
  !> already is.
  subroutine dense_cells(t, k, s0, info)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: k, s0
    integer, intent(out) :: info
    integer(i8) :: c(3), i, pos, last, cx, cy, cz, parent(3), i0, i1, bpos(MAX_PLACE_BLOCKS)
    integer :: nb, b, lo, hi, nleaf
    info = ARPY_OK
    if (k <= t%kflag) then
       ! no ancestor to flag: the cells in parallel blocks, each starting where the cell before it
       ! ends (read before any block moves it)
       call dense_range(t, k, i0, i1)
       nb = min(team_size(), MAX_PLACE_BLOCKS)
       if (i1 - i0 + 1 < MIN_PARALLEL_ROWS) nb = 1
       do b = 1, nb
          call block_range(int(i1 - i0 + 1), nb, b, lo, hi)
          bpos(b) = s0
          if (lo > 1) bpos(b) = t%dstart(i0 + lo - 2)
       end do
       nleaf = 0
       !$omp parallel do num_threads(nb) schedule(static, 1) private(lo, hi, pos, i, last) reduction(+: nleaf)
       do b = 1, nb
          call block_range(int(i1 - i0 + 1), nb, b, lo, hi)
          pos = bpos(b)
          do i = i0 + lo - 1, i0 + hi - 1
             last = t%dstart(i) - 1
             t%dstart(i) = int(pos)
             if (last < pos) cycle
             t%dval(i) = entry_pack(pos, last)
             nleaf = nleaf + 1
             pos = last + 1
          end do
       end do
       !$omp end parallel do
       t%ndense = t%ndense + nleaf
       t%ndleaf = t%ndleaf + nleaf
       return
    end if
    c = 0
    parent = -1
    pos = s0
    i = t%doff(k) - 1
    do cz = t%dlo(3, k), t%dlo(3, k) + t%dext(3, k) - 1
       do cy = t%dlo(2, k), t%dlo(2, k) + t%dext(2, k) - 1
          do cx = t%dlo(1, k), t%dlo(1, k) + t%dext(1, k) - 1
             i = i + 1
             last = t%dstart(i) - 1
             t%dstart(i) = int(pos)
             if (last < pos) cycle
             t%dval(i) = entry_pack(pos, last)
             t%ndense = t%ndense + 1
             t%ndleaf = t%ndleaf + 1
             pos = last + 1
             c = [cx, cy, cz]
             if (all(ishft(c, -1) == parent)) cycle   ! the parent of the cell before: flagged
             parent = ishft(c, -1)
             call mark_ancestors(t, k, c, info)
             if (info /= ARPY_OK) return
          end do
       end do
    end do
  end subroutine dense_cells

  !> Flag the ancestors (levels k-1 .. t%kflag) of cell c on level k as
  !> holding finer particles, stopping at the first that already is (its own
  !> ancestors are then flagged too).
  subroutine mark_ancestors(t, k, c, info)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: k
    integer(i8), intent(in) :: c(3)
    integer, intent(out) :: info
    integer(i8) :: cc(3), slot
    integer :: j
    info = ARPY_OK
    cc = c
    do j = k - 1, t%kflag, -1
       cc = ishft(cc, -1)
       if (t%dense(j)) then
          slot = dense_slot(t, j, cc)     ! an ancestor lies in its level's box
          if (entry_finer(t%dval(slot))) return
          call dense_flag_finer(t, slot)
       else
          call hash_insert(t%hash, ar_first_index(t%d, j) + ar_morton(t%d, cc), slot, info)
          if (info /= ARPY_OK) return
          if (entry_finer(t%hash%tab(2, slot))) return
          call hash_flag_finer(t%hash, slot)
       end if
    end do
  end subroutine mark_ancestors

  !> Choose the dense levels.  Every cell of level j that exists holds a
  !> particle of level >= j, so it lies inside the level-j cells spanned by
  !> the bounding box of those particles.  Level j is kept dense when that
  !> box has at most 4 cells per such particle (+1024), within a total budget
  !> of 4 n + 4096 cells (12 bytes each).  bmin/bmax: on entry the bounding
  !> box of each level's own particles; first_slot: each level's first slot
  !> (as in ar_build).
  subroutine plan_dense(t, d, n, bmin, bmax, first_slot, info)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: d, n, first_slot(0:)
    real(dp), intent(inout) :: bmin(:, 0:), bmax(:, 0:)
    integer, intent(out) :: info
    real(dp) :: cells
    integer(i8) :: cum(0:t%maxlevel + 1), total, budget, clo(3), chi(3)
    integer :: j, stat
    info = ARPY_OK
    t%dense = .false.
    t%ndense = 0
    cum = 0
    do j = 0, t%maxlevel
       cum(j) = first_slot(j + 1) - first_slot(j)
    end do
    do j = t%maxlevel - 1, 0, -1
       bmin(:, j) = min(bmin(:, j), bmin(:, j + 1))
       bmax(:, j) = max(bmax(:, j), bmax(:, j + 1))
       cum(j) = cum(j) + cum(j + 1)
    end do
    budget = 4_i8 * n + 4096_i8
    total = 0
    do j = 1, t%maxlevel
       if (cum(j) == 0) cycle
       clo = 0
       chi = 0
       clo(1:d) = axis_cell(bmin(1:d, j), t%lo(1:d), t%dm, pow2(j), ishft(1_i8, j) - 1_i8)
       chi(1:d) = axis_cell(bmax(1:d, j), t%lo(1:d), t%dm, pow2(j), ishft(1_i8, j) - 1_i8)
       cells = product(real(chi - clo + 1, dp))
       if (cells > real(4_i8 * cum(j) + 1024_i8, dp) .or. real(total, dp) + cells > real(budget, dp)) cycle
       t%dense(j) = .true.
       t%dlo(:, j) = clo
       t%dext(:, j) = chi - clo + 1
       t%doff(j) = total
       total = total + int(cells, i8) + 1_i8     ! + the sentinel
    end do
    if (allocated(t%dval)) deallocate(t%dval)
    if (allocated(t%dstart)) deallocate(t%dstart)
    allocate(t%dval(0:max(total, 1_i8) - 1), t%dstart(0:max(total, 1_i8) - 1), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    call advise_large(t%dval)
    call advise_large(t%dstart)
    t%dval = NO_ENTRY
    t%dstart = 0
  end subroutine plan_dense

end module arpy_arbuild
