!> Symmetric (half) Verlet lists on the AR tree (Awile et al., CPC 2012,
!> Algorithm 3), under every cutoff rule (the direct full list and cross-set
!> lists: arpy_arquery; the stencils as slot ranges: arpy_arstencil).
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
  use arpy_csr, only: row_builder, rb_init, rb_reserve, rb_join, list_capacity
  use arpy_celllist, only: grid_rows, range_total
  use arpy_pairs, only: scan_ranges
  use arpy_arkeys, only: ar_first_index, morton_coords, pow2
  use arpy_artree, only: ar_tree, dense_range
  use arpy_arops, only: ar_lookup
  use arpy_arstencil, only: BLOCKS_PER_THREAD, ROWS_PER_BLOCK, stencil_ranges, finer_ranges, scan_row, &
       add_range
  implicit none
  private

  !> slot ranges of a row: the own cell and stencil, then one stencil on
  !> each of up to 31 levels (adjacent ranges are joined)
  integer, parameter :: MAXR = 1 + 27 * 31

  public :: ar_half_list

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

end module arpy_arlists
