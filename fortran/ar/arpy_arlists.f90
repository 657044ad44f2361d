!> Verlet lists on the AR tree (Awile et al., CPC 2012, Algorithm 3) and
!> cross-set lists of query points against a tree.
!>
!> For each leaf cell, its 3**d stencil on its own level is looked up once.
!> A particle on level k takes, on its own level, the later particles of its
!> cell and the particles of the stencil cells that come later (larger J; on
!> dense levels, later in the array): each pair once; then, level by level
!> while the stencil of the level above holds finer particles, the particles
!> of the full 3**d stencil around its cell on each finer level.  Each
!> unordered pair is found once, by its coarser particle.  On the deepest
!> level nothing is finer: when it is dense its pairs are those of a uniform
!> cell list over its array (the uniform list's own loop, grid_rows).  The
!> distance test is the brute-force one, |x_p - x_q|**2 <= min(rc_p, rc_q)**2
!> with rc including the skin.
!>
!> The max and sum rules (a tree built with t%rule, arpy_arbuild): a
!> particle's level is that of its level reach l = rc + skin (max rule) or
!> 2 rc + skin (sum rule), so the cell edge of its level exceeds l.  The reach
!> of a pair, max(rc_p, rc_q) + skin or (rc_p + rc_q) + skin, is at most the
!> larger of the two level reaches: that of the coarser particle, not of the
!> finer one as under the min rule.  A coarse particle would have to search
!> the finer levels far beyond their 3**d stencils, so the pairs are found
!> from the fine side instead: a particle on level k takes, on its own level,
!> the same half stencil as under the min rule, and on every coarser level j
!> that holds particles the full 3**d stencil around its ancestor cell there
!> (the level-j cell that contains it; level 0: the root), whose particles'
!> level reaches are below the cell edge of level j.  Nothing finer is
!> searched.  The ancestor cells are the same for all particles of a leaf
!> cell, so under the max rule each cell's ranges are looked up once and
!> shared by its particles.  Under the sum rule a particle q knows more: a
!> partner p on level j has 2 rc_p + skin < e_j, so the reach (rc_p + rc_q) +
!> skin is below e_j / 2 + rc_q + skin / 2, and in 3D each particle looks up
!> its own coarser stencils, leaving out the cells farther than that (measured
!> at N = 1e5, cutoffs log-uniform over a span of 10 and 100: 25 % less time
!> in 3D; in 2D, with 9 cells a stencil, the lookups per particle cost what
!> the pruning saves, so 2D shares each cell's ranges as under the max rule).
!> Each unordered pair is found once, by its finer particle (same level: by
!> the half stencil).
module arpy_arlists
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC, RULE_MIN, RULE_SUM
  use arpy_threads, only: team_size, MIN_PARALLEL_POINTS
  use arpy_csr, only: row_builder, rb_init, rb_reserve, rb_join, sort_run, list_capacity
  use arpy_celllist, only: grid_rows, range_total
  use arpy_pairs, only: scan_ranges
  use arpy_arkeys, only: ar_first_index, morton_coords, stencil_morton, pow2
  use arpy_arhash, only: entry_first, entry_last, entry_finer, hash_find
  use arpy_artree, only: ar_tree, cell_coords, query_coords, dense_range
  use arpy_arops, only: ar_lookup
  implicit none
  private

  !> slot ranges of a row: the own cell and stencil, then one stencil on
  !> each of up to 31 levels (adjacent ranges are joined)
  integer, parameter :: MAXR = 1 + 27 * 31
  !> ... and of a row of the direct full list: a stencil on every level, one split
  integer, parameter :: MAXF = 27 * 32 + 2
  !> the rows of queries (and of the direct full list) in parallel: blocks of at least
  !> ROWS_PER_BLOCK rows, up to BLOCKS_PER_THREAD per thread, taken in turn by the threads
  !> (rows cost unevenly: a block per thread leaves one waiting)
  integer, parameter :: BLOCKS_PER_THREAD = 8, ROWS_PER_BLOCK = 256

  public :: ar_half_list, ar_cross_list, ar_full_list

contains

  !> Algorithm 3, symmetric list: row a (slot order) lists the neighbours
  !> found by the particle in slot a (0-based particle indices).  Leaf cells
  !> in slot order: on dense levels the non-empty table cells, on hashed
  !> levels the recorded leaves; a deepest level kept dense is a uniform
  !> cell list over its table (grid_rows, after the others).  In parallel
  !> from MIN_PARALLEL_POINTS slots: the leaves in blocks of whole cells,
  !> balanced by slots, taken in turn by the threads (the first into rb
  !> itself, each other into its own builder), joined in slot order: the
  !> list one thread builds.
  subroutine ar_half_list(t, rb, info)
    type(ar_tree), intent(in) :: t
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    integer, allocatable :: ulev(:), us0(:), us1(:)
    integer(i8), allocatable :: uref(:)
    integer(i8) :: nnz
    integer :: nu, kgrid

    call rb_init(rb, t%n, list_capacity(t%d, t%n), info)
    if (info /= ARPY_OK) return
    nnz = 0
    kgrid = -1
    ! (under the max and sum rules the deepest level's particles search the coarser levels too:
    ! a uniform list over its table serves them only when no coarser level holds particles)
    if (t%dense(t%maxlevel) .and. (t%rule == RULE_MIN .or. count(t%holds(0:t%maxlevel)) == 1)) &
         kgrid = t%maxlevel
    call leaf_units(t, kgrid, nu, ulev, uref, us0, us1, info)
    if (info /= ARPY_OK) return
    call unit_rows(t, nu, ulev, uref, us0, us1, rb, nnz, info)
    if (info /= ARPY_OK) return
    if (kgrid >= 0) then
       ! the deepest level holds nothing finer: its pairs are those of a
       ! uniform cell list over its table
       call grid_rows(t%dstart(t%doff(kgrid):), t%dext(:, kgrid), t%xs, t%rcs, t%perm, rb, nnz, info, &
            rule=t%rule, pskin=t%pskin)
       if (info /= ARPY_OK) return
    end if
    rb%nnz = nnz
  end subroutine ar_half_list

  !> The leaf cells of every level but kgrid, in slot order: level ulev(u),
  !> table index (dense) or leaf index (hashed) uref(u), slots us0(u) .. us1(u).
  subroutine leaf_units(t, kgrid, nu, ulev, uref, us0, us1, info)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: kgrid
    integer, intent(out) :: nu, info
    integer, allocatable, intent(out) :: ulev(:), us0(:), us1(:)
    integer(i8), allocatable, intent(out) :: uref(:)
    integer(i8) :: i, i0, i1
    integer :: k, li, stat
    info = ARPY_OK
    nu = 0
    do k = 0, t%maxlevel                    ! (count, then record; a level without particles has no leaves)
       if (k == kgrid .or. .not. t%holds(k)) cycle
       if (t%dense(k)) then
          call dense_range(t, k, i0, i1)
          nu = nu + count(t%dstart(i0 + 1:i1 + 1) > t%dstart(i0:i1))
       else
          nu = nu + (t%hleaf(k + 1) - t%hleaf(k))
       end if
    end do
    allocate(ulev(max(nu, 1)), uref(max(nu, 1)), us0(max(nu, 1)), us1(max(nu, 1)), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    nu = 0
    do k = 0, t%maxlevel
       if (k == kgrid .or. .not. t%holds(k)) cycle
       if (t%dense(k)) then
          call dense_range(t, k, i0, i1)
          do i = i0, i1
             if (t%dstart(i + 1) == t%dstart(i)) cycle
             nu = nu + 1
             ulev(nu) = k
             uref(nu) = i
             us0(nu) = t%dstart(i)
             us1(nu) = t%dstart(i + 1) - 1
          end do
       else
          do li = t%hleaf(k), t%hleaf(k + 1) - 1
             nu = nu + 1
             ulev(nu) = k
             uref(nu) = li
             us0(nu) = t%leaf_first(li)
             us1(nu) = t%leaf_last(li)
          end do
       end if
    end do
  end subroutine leaf_units

  !> The rows of the leaf units 1 .. nu (slots us0(1) = 1 on) into rb from entry nnz on.
  subroutine unit_rows(t, nu, ulev, uref, us0, us1, rb, nnz, info)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: nu, ulev(:), us0(:), us1(:)
    integer(i8), intent(in) :: uref(:)
    type(row_builder), intent(inout) :: rb
    integer(i8), intent(inout) :: nnz
    integer, intent(out) :: info
    type(row_builder), allocatable :: part(:)
    integer, allocatable :: pinfo(:), ufirst(:), rfirst(:)
    integer :: nb, b, u, nslot, stat
    info = ARPY_OK
    if (nu == 0) return
    nslot = us1(nu) - us0(1) + 1
    nb = min(BLOCKS_PER_THREAD * team_size(), nslot / ROWS_PER_BLOCK, nu)
    if (nslot < MIN_PARALLEL_POINTS .or. team_size() <= 1 .or. nb <= 1) then
       do u = 1, nu
          call unit_pairs(u, rb, 0, nnz, info)
          if (info /= ARPY_OK) return
       end do
       return
    end if
    allocate(part(nb), pinfo(nb), ufirst(nb + 1), rfirst(nb), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    ! block b: the units from the first that starts at or after its share of the slots
    ufirst(nb + 1) = nu + 1
    u = 1
    do b = 1, nb
       do while (u <= nu)
          if (us0(u) - us0(1) >= int((int(nslot, i8) * (b - 1)) / nb)) exit
          u = u + 1
       end do
       ufirst(b) = u
       rfirst(b) = us0(1) - 1
       if (u <= nu) rfirst(b) = us0(u) - 1        ! its rows follow row rfirst(b) of rb
    end do
    pinfo = ARPY_OK
    !$omp parallel do num_threads(min(team_size(), nb)) schedule(dynamic, 1)
    do b = 1, nb
       call block(b)
    end do
    !$omp end parallel do
    info = maxval(pinfo)
    if (info /= ARPY_OK) return
    nnz = rb%nnz
    call rb_join(rb, nnz, nb - 1, part(2:), rfirst(2:), info)

  contains

    !> Block b's units: block 1 into rb itself, the others into their own builders.
    subroutine block(b)
      integer, intent(in) :: b
      integer(i8) :: pn
      integer :: v, rows
      if (b == 1) then
         pn = nnz
         do v = ufirst(1), ufirst(2) - 1
            call unit_pairs(v, rb, 0, pn, pinfo(1))
            if (pinfo(1) /= ARPY_OK) return
         end do
         rb%nnz = pn
         return
      end if
      rows = 0
      if (ufirst(b) < ufirst(b + 1)) rows = us1(ufirst(b + 1) - 1) - us0(ufirst(b)) + 1
      call rb_init(part(b), rows, list_capacity(t%d, rows), pinfo(b))
      if (pinfo(b) /= ARPY_OK) return
      pn = 0
      do v = ufirst(b), ufirst(b + 1) - 1
         call unit_pairs(v, part(b), rfirst(b), pn, pinfo(b))
         if (pinfo(b) /= ARPY_OK) return
      end do
      part(b)%nnz = pn
    end subroutine block

    !> The rows of unit v into builder r (row a - base for slot a).
    subroutine unit_pairs(v, r, base, pn, pinf)
      integer, intent(in) :: v, base
      type(row_builder), intent(inout) :: r
      integer(i8), intent(inout) :: pn
      integer, intent(out) :: pinf
      integer(i8) :: c(3), rest
      integer :: k
      k = ulev(v)
      c = 0
      if (t%dense(k)) then
         rest = uref(v) - t%doff(k)               ! table index -> cell coordinates
         c(1) = t%dlo(1, k) + modulo(rest, t%dext(1, k))
         rest = rest / t%dext(1, k)
         c(2) = t%dlo(2, k) + modulo(rest, t%dext(2, k))
         c(3) = t%dlo(3, k) + rest / t%dext(2, k)
         call leaf_pairs(t, k, c, uref(v), us0(v), us1(v), r, base, pn, pinf)
      else
         ! the cell's coordinates from its J (Morton code), no division
         if (k > 0) call morton_coords(t%d, t%leaf_key(uref(v)) - ar_first_index(t%d, k), c)
         call leaf_pairs(t, k, c, t%leaf_key(uref(v)), us0(v), us1(v), r, base, pn, pinf)
      end if
    end subroutine unit_pairs

  end subroutine unit_rows

  !> The rows of leaf cell c on level k (slots s0 .. s1; `above` = its J, or
  !> on a dense level its table index): on its own level the later particles
  !> of the cell and of the stencil cells that come after it (Op5, looked up
  !> once per cell), then on finer levels the full stencils.
  subroutine leaf_pairs(t, k, c, above, s0, s1, rb, base, nnz, info)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k, s0, s1, base
    integer(i8), intent(in) :: c(3), above
    type(row_builder), intent(inout) :: rb
    integer(i8), intent(inout) :: nnz
    integer, intent(out) :: info
    integer :: a, nr_own, nr, re_own
    integer :: rs(MAXR), re(MAXR)
    logical :: finer_own

    info = ARPY_OK
    ! own level: range 1 = the rest of the cell (set per particle), then
    ! the stencil cells that come later
    nr_own = 1
    rs(1) = s0
    re(1) = s1
    if (t%rule /= RULE_MIN) then
       ! max and sum rules: the own level's half stencil, then the coarser levels' full stencils
       if (k > 0) call stencil_ranges(t, k, c, above, nr_own, rs, re, finer_own)
       if (t%rule /= RULE_SUM .or. k == 0 .or. t%d == 2) then
          call coarser_ranges(t, k, c, nr_own, rs, re)
          call coarse_rows(t, s0, s1, nr_own, rs, re, rb, base, nnz, info)
          return
       end if
       re_own = re(nr_own)
       do a = s0, s1              ! (sum rule in 3D: each particle's own coarser stencils, pruned)
          rs(1) = a + 1
          nr = nr_own
          re(nr) = re_own
          call coarser_ranges(t, k, c, nr, rs, re, t%xs(:, a), t%rcs(a))
          call scan_row(t, t%xs(:, a), t%rcs(a), nr, rs, re, rb, nnz, info)
          if (info /= ARPY_OK) return
          rb%off(a - base + 1) = nnz
       end do
       return
    end if
    if (k == 0) then
       finer_own = t%maxlevel > 0
    else
       call stencil_ranges(t, k, c, above, nr_own, rs, re, finer_own)
    end if
    if (.not. finer_own) then
       call coarse_rows(t, s0, s1, nr_own, rs, re, rb, base, nnz, info)
       return
    end if
    re_own = re(nr_own)
    do a = s0, s1
       rs(1) = a + 1            ! range 1: the rest of the cell (and what follows it)
       nr = nr_own
       re(nr) = re_own          ! a finer range may have been joined to it
       call finer_ranges(t, t%xs(:, a), k, .true., .true., nr, rs, re, t%rcs(a))
       call scan_row(t, t%xs(:, a), t%rcs(a), nr, rs, re, rb, nnz, info)
       if (info /= ARPY_OK) return
       rb%off(a - base + 1) = nnz
    end do
  end subroutine leaf_pairs

  !> Append to rs/re, for a cell c on level k, the full 3**d stencil around the cell that contains
  !> it on every coarser level that holds particles (the cell's coordinates there: c shifted right
  !> by the difference of levels; level 0: the root's particles).  The max and sum rules' search
  !> towards the coarse side (see the module's notes).  Given a particle of the cell, at xa with
  !> cutoff rq, under the sum rule: only the cells within e_j / 2 + rq + skin / 2 of it on level j
  !> (widened by 1e-12 of itself against rounding).
  subroutine coarser_ranges(t, k, c, nr, rs, re, xa, rq)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k
    integer(i8), intent(in) :: c(3)
    integer, intent(inout) :: nr, rs(:), re(:)
    real(dp), intent(in), optional :: xa(3), rq
    integer(i8) :: cj(3)
    integer :: j, first, last
    logical :: found, finer
    real(dp) :: bound
    do j = 0, k - 1
       if (.not. t%holds(j)) cycle
       if (j == 0) then
          call ar_lookup(t, 1_i8, found, first, last, finer)
          if (found) call add_range(first, last, nr, rs, re)
          cycle
       end if
       cj = ishft(c, -(k - j))
       if (present(xa)) then
          bound = (0.5_dp * (t%dm / pow2(j)) + rq + 0.5_dp * t%pskin) * (1.0_dp + 1.0e-12_dp)
          call stencil_ranges(t, j, cj, -1_i8, nr, rs, re, finer, xa, bound)
       else
          call stencil_ranges(t, j, cj, -1_i8, nr, rs, re, finer)
       end if
    end do
  end subroutine coarser_ranges

  !> The rows of slots s0 .. s1 when no finer level lies in their stencil:
  !> every row searches the ranges rs/re (range 1 from the slot after its
  !> own), so room is checked against one bound.
  subroutine coarse_rows(t, s0, s1, nr, rs, re, rb, base, nnz, info)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: s0, s1, nr, base
    integer, intent(inout) :: rs(:)
    integer, intent(in) :: re(:)
    type(row_builder), intent(inout) :: rb
    integer(i8), intent(inout) :: nnz
    integer, intent(out) :: info
    integer(i8) :: need
    integer :: a
    info = ARPY_OK
    need = range_total(nr, rs, re)
    do a = s0, s1
       if (nnz + need > size(rb%idx, kind=i8)) then
          call rb_reserve(rb, nnz, need, info)
          if (info /= ARPY_OK) return
       end if
       rs(1) = a + 1
       call scan_ranges(t%xs, t%rcs, t%perm, t%xs(:, a), t%rcs(a), nr, rs, re, rb%idx, nnz, t%rule, t%pskin)
       rb%off(a - base + 1) = nnz
    end do
  end subroutine coarse_rows

  !> Cross-set list: row i lists the particles q of the tree (0-based particle
  !> indices) with |xq_i - x_q| <= min(rcq_i, rc_q).  Queries may lie outside
  !> the tree's domain.  A tree of the min rule (the queries descend
  !> towards the finer levels).
  subroutine ar_cross_list(t, m, xq, rcq, rb, info)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: m
    real(dp), intent(in) :: xq(t%d, m), rcq(m)
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    call rows_in_blocks(t, m, rb, info, xq, rcq)
  end subroutine ar_cross_list

  !> Algorithm 3, asymmetric branch: row a (slot order) lists every neighbour of the
  !> particle in slot a (level k): on each coarser level that holds particles, those of
  !> the 3**d stencil around the cell holding it there (Op4's ancestors; level 0: the
  !> root); on level k the full stencil around its cell, without itself; then the full
  !> stencils of the finer levels while the level above holds finer particles (as in the
  !> symmetric list).  A coarser partner q lies in that stencil: |x_p - x_q| <=
  !> min(rc_p, rc_q) <= rc_q, at most the cell edge of q's level.  Each pair is tested
  !> from both of its sides, and no second pass expands a half list.  A tree of the min rule.
  subroutine ar_full_list(t, rb, info)
    type(ar_tree), intent(in) :: t
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    call rows_in_blocks(t, t%n, rb, info)
  end subroutine ar_full_list

  !> The rows of m queries (xq, rcq; absent: the tree's own particles in slot order,
  !> each without itself).  In parallel for MIN_PARALLEL_POINTS rows or more: one
  !> contiguous block of rows per thread, the first into rb itself, each other into
  !> its own builder, appended in row order (the serial list).
  subroutine rows_in_blocks(t, m, rb, info, xq, rcq)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: m
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    real(dp), intent(in), optional :: xq(:, :), rcq(:)
    type(row_builder), allocatable :: part(:)
    integer, allocatable :: pinfo(:), first(:)
    integer(i8) :: nnz
    integer :: nb, k, stat

    nb = min(BLOCKS_PER_THREAD * team_size(), m / ROWS_PER_BLOCK)
    if (m < MIN_PARALLEL_POINTS .or. team_size() <= 1 .or. nb <= 1) then
       call rb_init(rb, m, 8_i8 * m, info)
       if (info /= ARPY_OK) return
       call query_rows(t, 1, m, rb, info, xq, rcq)
       return
    end if
    allocate(part(nb), pinfo(nb), first(nb), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    first = [((int(m, i8) * (k - 1)) / nb, k = 1, nb)]       ! block k: rows first(k)+1 ..
    call rb_init(rb, m, 8_i8 * m, info)
    if (info /= ARPY_OK) return
    !$omp parallel do num_threads(min(team_size(), nb)) schedule(dynamic, 1)
    do k = 1, nb
       call block(k)
    end do
    !$omp end parallel do
    info = maxval(pinfo)
    if (info /= ARPY_OK) return
    nnz = rb%nnz
    call rb_join(rb, nnz, nb - 1, part(2:), first(2:), info)

  contains

    !> Block 1 writes its rows straight into rb, the others into their own builders.
    subroutine block(k)
      integer, intent(in) :: k
      integer :: i0, i1
      i0 = first(k) + 1
      i1 = m
      if (k < nb) i1 = first(k + 1)
      if (k == 1) then
         call query_rows(t, i0, i1, rb, pinfo(1), xq, rcq)
         return
      end if
      call rb_init(part(k), i1 - i0 + 1, 8_i8 * (i1 - i0 + 1), pinfo(k))
      if (pinfo(k) == ARPY_OK) call query_rows(t, i0, i1, part(k), pinfo(k), xq, rcq)
    end subroutine block

  end subroutine rows_in_blocks

  !> The rows of queries i0 .. i1 into rb (its rows 1 .. i1 - i0 + 1); without xq the
  !> queries are the tree's particles in slots i0 .. i1, each without itself.
  subroutine query_rows(t, i0, i1, rb, info, xq, rcq)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: i0, i1
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    real(dp), intent(in), optional :: xq(:, :), rcq(:)
    integer :: i, k, nr, rs(MAXF), re(MAXF), root_first, root_last, last(0:31)
    integer(i8) :: nnz
    logical :: found, finer_root, own
    real(dp) :: xa(3), ra

    info = ARPY_OK
    nnz = 0
    own = .not. present(xq)
    ! level 0: every level-0 particle (their cutoffs may exceed the domain)
    call ar_lookup(t, 1_i8, found, root_first, root_last, finer_root)
    if (own) call level_ends(t, last)
    k = 0
    do i = i0, i1
       if (own) then
          do while (i > last(k))              ! slots are in level order
             k = k + 1
          end do
          call own_ranges(t, i, k, root_first, root_last, nr, rs, re)
          call scan_row(t, t%xs(:, i), t%rcs(i), nr, rs, re, rb, nnz, info)
       else
          xa = 0.0_dp
          xa(1:t%d) = xq(:, i)
          ra = rcq(i)
          nr = 1
          rs(1) = root_first        ! (set per query: later ranges may be joined to it)
          re(1) = root_last
          call finer_ranges(t, xa, 0, finer_root, .false., nr, rs, re, ra)
          call scan_row(t, xa, ra, nr, rs, re, rb, nnz, info)
          if (info == ARPY_OK) call sort_run(rb%idx, rb%off(i - i0 + 1) + 1, nnz)    ! (ascending)
       end if
       if (info /= ARPY_OK) return
       rb%off(i - i0 + 2) = nnz
    end do
    rb%nnz = nnz
  end subroutine query_rows

  !> The last slot of each level (levels are contiguous in slot order; an empty level
  !> ends where the one before it does).
  subroutine level_ends(t, last)
    type(ar_tree), intent(in) :: t
    integer, intent(out) :: last(0:31)
    integer :: k
    integer(i8) :: cells
    last = 0
    do k = 0, t%maxlevel
       if (k > 0) last(k) = last(k - 1)
       if (t%dense(k)) then
          cells = product(t%dext(1:t%d, k))
          last(k) = t%dstart(t%doff(k) + cells) - 1
       else if (t%hleaf(k + 1) > t%hleaf(k)) then
          last(k) = t%leaf_last(t%hleaf(k + 1) - 1)
       end if
    end do
    last(t%maxlevel + 1:) = t%n
  end subroutine level_ends

  !> The slot ranges the particle in slot a, on level k, searches in the direct full list.
  subroutine own_ranges(t, a, k, root_first, root_last, nr, rs, re)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: a, k, root_first, root_last
    integer, intent(out) :: nr
    integer, intent(inout) :: rs(:), re(:)
    integer(i8) :: c(3)
    integer :: j
    logical :: more
    nr = 0
    more = t%maxlevel > 0
    call add_range(root_first, root_last, nr, rs, re)            ! level 0: the root
    do j = 1, k
       if (.not. t%holds(j)) cycle                              ! no particles on level j
       call cell_coords(t, t%xs(:, a), j, c)
       call stencil_ranges(t, j, c, -1_i8, nr, rs, re, more, t%xs(:, a), t%rcs(a))
    end do
    call drop_slot(a, nr, rs, re)
    call finer_ranges(t, t%xs(:, a), k, more, .true., nr, rs, re, t%rcs(a))
  end subroutine own_ranges

  !> Split the range holding slot a (the ranges are disjoint) so that a is in none.
  pure subroutine drop_slot(a, nr, rs, re)
    integer, intent(in) :: a
    integer, intent(inout) :: nr, rs(:), re(:)
    integer :: r
    do r = 1, nr
       if (rs(r) <= a .and. a <= re(r)) then
          rs(r + 2:nr + 1) = rs(r + 1:nr)
          re(r + 2:nr + 1) = re(r + 1:nr)
          rs(r + 1) = a + 1
          re(r + 1) = re(r)
          re(r) = a - 1
          nr = nr + 1
          return
       end if
    end do
  end subroutine drop_slot

  !> Append to rs/re the stencils around point xa on the levels below k,
  !> level by level while the stencil of the level above holds finer
  !> particles (finer: whether level k's does).  inside: xa lies in the
  !> cube (a particle of the tree); else it may lie outside (a query).  ra:
  !> its cutoff (stencil cells farther away are left out).  A level without
  !> particles is passed over: its stencil adds no slots, and the finer
  !> levels' stencils lie within its own, so only the pruning it would have
  !> allowed is lost (the levels above the coarsest cutoff are all such).
  subroutine finer_ranges(t, xa, k, finer, inside, nr, rs, re, ra)
    type(ar_tree), intent(in) :: t
    real(dp), intent(in) :: xa(3), ra
    integer, intent(in) :: k
    logical, intent(in) :: finer, inside
    integer, intent(inout) :: nr, rs(:), re(:)
    integer(i8) :: c(3)
    integer :: j
    logical :: more
    more = finer
    j = k
    do while (more .and. j < t%maxlevel)
       j = j + 1
       if (.not. t%holds(j)) cycle
       if (inside) then
          call cell_coords(t, xa, j, c)
       else
          call query_coords(t, xa, j, c)
       end if
       call stencil_ranges(t, j, c, -1_i8, nr, rs, re, more, xa, ra)
    end do
  end subroutine finer_ranges

  !> Append to the current row every slot b of the ranges rs(r)..re(r),
  !> r = 1..nr, within the min-rule cutoff of (xa, ra).  Room is made first,
  !> so the acceptance is branch-free.
  subroutine scan_row(t, xa, ra, nr, rs, re, rb, nnz, info)
    type(ar_tree), intent(in) :: t
    real(dp), intent(in) :: xa(3), ra
    integer, intent(in) :: nr, rs(:), re(:)
    type(row_builder), intent(inout) :: rb
    integer(i8), intent(inout) :: nnz
    integer, intent(out) :: info
    integer(i8) :: need
    info = ARPY_OK
    need = range_total(nr, rs, re)
    if (nnz + need > size(rb%idx, kind=i8)) then
       call rb_reserve(rb, nnz, need, info)
       if (info /= ARPY_OK) return
    end if
    call scan_ranges(t%xs, t%rcs, t%perm, xa, ra, nr, rs, re, rb%idx, nnz, t%rule, t%pskin)
  end subroutine scan_row

  !> Op5 with Op2: the 3**d stencil around cell c on level k (cells outside
  !> [0, 2**k) dropped).  Appends the own-level slot range of every existing
  !> stencil cell that comes after the cell `above` (all of them for above <
  !> 0) to rs/re, joining ranges that continue the one before, and tells
  !> whether any stencil cell holds finer particles.  Cells are ordered by J,
  !> or on a dense level by their table index (the order of their slots).
  !> On the deepest level nothing is finer, so only cells after `above` are
  !> looked up.  Given a point xa and its cutoff ra, the cells (and their
  !> finer particles) farther than min(ra, e) from xa are left out, e the
  !> cell edge (every cutoff on level k >= 1 is below it): they hold no
  !> neighbour of it (the rows are the same, with fewer distance checks).
  subroutine stencil_ranges(t, k, c, above, nr, rs, re, finer, xa, ra)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k
    integer(i8), intent(in) :: c(3), above
    integer, intent(inout) :: nr, rs(:), re(:)
    logical, intent(out) :: finer
    real(dp), intent(in), optional :: xa(3), ra
    integer(i8) :: f, key, slot, v, sx(-1:1), sy(-1:1), sz(-1:1)
    integer :: oz_hi, ox, oy, oz
    logical :: deepest
    real(dp) :: g(-1:1, 3), r2
    call stencil_gaps(t, k, c, g, r2, xa, ra)
    if (t%dense(k)) then
       call dense_stencil(t, k, c, above, nr, rs, re, finer, g, r2)
       return
    end if
    f = ar_first_index(t%d, k)
    deepest = k == t%maxlevel
    call stencil_morton(t%d, c, ishft(1_i8, k), sx, sy, sz)
    oz_hi = merge(1, 0, t%d == 3)
    finer = .false.
    do oz = -oz_hi, oz_hi
       if (sz(oz) < 0 .or. g(oz, 3) > r2) cycle
       do oy = -1, 1
          if (sy(oy) < 0 .or. g(oy, 2) + g(oz, 3) > r2) cycle
          do ox = -1, 1
             if (sx(ox) < 0 .or. g(ox, 1) + g(oy, 2) + g(oz, 3) > r2) cycle
             key = f + ior(ior(sx(ox), sy(oy)), sz(oz))
             if (deepest .and. key <= above) cycle
             slot = hash_find(t%hash, key)   ! Op2
             if (slot < 0) cycle
             v = t%hash%tab(2, slot)
             finer = finer .or. entry_finer(v)
             if (key > above) call add_range(entry_first(v), entry_last(v), nr, rs, re)
          end do
       end do
    end do
  end subroutine stencil_ranges

  !> The squared gaps g(o, l) between xa and the stencil cells c(l) + o along
  !> each axis l (0 beyond d) and r2, the squared cutoff they are held to
  !> (without xa: all zero and r2 = huge).  The cell faces are widened by a
  !> hair so that no rounding of the cell a particle was put in can drop a
  !> neighbour.
  pure subroutine stencil_gaps(t, k, c, g, r2, xa, ra)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k
    integer(i8), intent(in) :: c(3)
    real(dp), intent(out) :: g(-1:1, 3), r2
    real(dp), intent(in), optional :: xa(3), ra
    real(dp) :: e, hair, lower, gap
    integer :: l, o
    g = 0.0_dp
    r2 = huge(1.0_dp)
    if (.not. present(xa)) return
    e = t%dm / pow2(k)
    hair = 1.0e-9_dp * (t%dm + maxval(abs(t%lo(1:t%d))))
    do l = 1, t%d
       do o = -1, 1
          lower = t%lo(l) + real(c(l) + o, dp) * e
          gap = max(lower - hair - xa(l), xa(l) - (lower + e) - hair, 0.0_dp)
          g(o, l) = gap * gap
       end do
    end do
    r2 = min(ra, e)**2          ! (a particle of level k >= 1, or finer, reaches less than e)
  end subroutine stencil_gaps

  !> stencil_ranges on a dense level: the table index orders the cells, so
  !> each row of the stencil (axis 1) is three consecutive entries, and their
  !> own-level particles one slot range read from dstart (g, r2: the gaps
  !> of stencil_gaps; farther cells are left out).
  subroutine dense_stencil(t, k, c, above, nr, rs, re, finer, g, r2)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k
    integer(i8), intent(in) :: c(3), above
    integer, intent(inout) :: nr, rs(:), re(:)
    logical, intent(out) :: finer
    real(dp), intent(in) :: g(-1:1, 3), r2
    integer(i8) :: cl(3), row, slot, xlo, xhi, first, lo_, hi_
    integer :: oz_hi, oy, oz
    logical :: deepest
    real(dp) :: gyz
    deepest = k == t%maxlevel
    cl = c - t%dlo(:, k)
    xlo = max(cl(1) - 1, 0_i8)
    xhi = min(cl(1) + 1, t%dext(1, k) - 1)
    oz_hi = merge(1, 0, t%d == 3)
    finer = .false.
    if (xlo > xhi) return
    do oz = -oz_hi, oz_hi
       if (cl(3) + oz < 0 .or. cl(3) + oz >= t%dext(3, k)) cycle
       do oy = -1, 1
          if (cl(2) + oy < 0 .or. cl(2) + oy >= t%dext(2, k)) cycle
          gyz = g(oy, 2) + g(oz, 3)
          lo_ = xlo
          hi_ = xhi
          do while (lo_ <= hi_)
             if (g(int(lo_ - cl(1)), 1) + gyz <= r2) exit
             lo_ = lo_ + 1
          end do
          do while (hi_ >= lo_)
             if (g(int(hi_ - cl(1)), 1) + gyz <= r2) exit
             hi_ = hi_ - 1
          end do
          if (lo_ > hi_) cycle
          row = t%doff(k) + t%dext(1, k) * ((cl(2) + oy) + t%dext(2, k) * (cl(3) + oz))
          if (.not. deepest) then
             do slot = row + lo_, row + hi_
                finer = finer .or. entry_finer(t%dval(slot))
             end do
          end if
          first = max(row + lo_, above + 1)
          if (first <= row + hi_) call add_range(t%dstart(first), t%dstart(row + hi_ + 1) - 1, nr, rs, re)
       end do
    end do
  end subroutine dense_stencil

  !> Append the slot range first .. last to rs/re (nothing if empty),
  !> extending the last range when it continues it.
  pure subroutine add_range(first, last, nr, rs, re)
    integer, intent(in) :: first, last
    integer, intent(inout) :: nr, rs(:), re(:)
    if (last < first) return
    if (nr > 0) then
       if (re(nr) + 1 == first) then
          re(nr) = last
          return
       end if
    end if
    nr = nr + 1
    rs(nr) = first
    re(nr) = last
  end subroutine add_range

end module arpy_arlists
