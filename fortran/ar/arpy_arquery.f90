!> The AR tree's direct full list (Algorithm 3, asymmetric branch) and cross-set lists of
!> query points against a tree (Awile et al., CPC 2012): each row searched on its own, from
!> the root down, in blocks of rows in parallel.  Trees of the min rule (the symmetric list
!> and the max and sum rules: arpy_arlists).
module arpy_arquery
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC
  use arpy_threads, only: team_size, MIN_PARALLEL_POINTS
  use arpy_csr, only: row_builder, rb_init, rb_join, sort_run
  use arpy_artree, only: ar_tree, cell_coords
  use arpy_arops, only: ar_lookup
  use arpy_arstencil, only: BLOCKS_PER_THREAD, ROWS_PER_BLOCK, stencil_ranges, finer_ranges, scan_row, &
       add_range
  implicit none
  private

  !> slot ranges of a row of the direct full list: a stencil on every level, one split
  integer, parameter :: MAXF = 27 * 32 + 2

  public :: ar_cross_list, ar_full_list

contains

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

end module arpy_arquery
