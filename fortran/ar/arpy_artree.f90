!> The AR tree (Awile et al., CPC 2012): particles in slot order and the
!> table of its cells, with the queries on that table that build, cell
!> operations and lists share, and the tables handed to Python.
!>
!> Slots order the particles by level (coarse to fine) and within a level by
!> cell.  A cell is entered in the table if it holds own-level particles (a
!> leaf) or if its region holds particles of a finer level (the finer flag).
!> Hashed levels keep their cells in the hash table (arpy_arhash); a level
!> whose occupied region is compact is "dense": its cells live in a plain
!> array over that region instead (a perfect hash for that level), with the
!> first slot of every cell, empty ones included, as in a uniform cell list.
module arpy_artree
  use arpy_kinds, only: dp, i8, RULE_MIN
  use arpy_arkeys, only: ar_first_index, ar_morton, axis_cell, pow2
  use arpy_arhash, only: ar_hash, NOKEY, NO_ENTRY, EMPTY_ENTRY, FINER_BIT
  implicit none
  private

  type, public :: ar_tree
     integer :: d = 0, n = 0
     integer :: maxlevel = -1                 !< deepest non-empty level
     logical :: holds(0:31) = .false.         !< whether level k holds particles
     integer :: kflag = 1                     !< dense cells flag their ancestors finer down to this level
     real(dp) :: lo(3) = 0.0_dp               !< lower corner of the cube
     real(dp) :: dm = 1.0_dp                  !< cube edge D_m
     integer, allocatable :: perm(:)          !< slot -> particle (1-based)
     real(dp), allocatable :: xs(:, :)        !< (3, n) positions by slot (z = 0 in 2D)
     real(dp), allocatable :: rcs(:)          !< cutoffs (+ skin: min and max rules) by slot
     integer :: rule = RULE_MIN               !< cutoff rule of its lists (RULE_* of arpy_kinds)
     real(dp) :: pskin = 0.0_dp               !< skin added to each pair's reach (sum rule)
     ! leaf cells (cells with own-level particles) of the hashed levels, in
     ! slot order (by level, then J): level k's are hleaf(k) .. hleaf(k+1)-1.
     ! The leaves of dense levels are their tables' non-empty cells (ndleaf).
     integer :: nleaf = 0, ndleaf = 0
     integer :: hleaf(0:32) = 1
     integer(i8), allocatable :: leaf_key(:)
     integer, allocatable :: leaf_first(:), leaf_last(:)
     ! the cells of the hashed levels: J -> entry (see arpy_arhash)
     type(ar_hash) :: hash
     ! dense levels: level k keeps its cells' entries in dval over the
     ! bounding box of its occupied region (cell coordinates dlo .. dlo +
     ! dext - 1, from index doff on; NO_ENTRY: an absent cell).  dstart(i):
     ! the first own-level slot of table cell i, empty cells included (as the
     ! start array of a uniform cell list), so cell i owns slots dstart(i) ..
     ! dstart(i+1) - 1; each level's table is followed by one sentinel entry
     ! (dval = NO_ENTRY, dstart = the level's last slot + 1).
     logical :: dense(0:31) = .false.
     integer(i8) :: dlo(3, 0:31) = 0, dext(3, 0:31) = 1, doff(0:31) = 0
     integer :: ndense = 0                    !< non-empty dense entries
     integer(i8), allocatable :: dval(:)
     integer, allocatable :: dstart(:)
  end type ar_tree

  public :: cell_coords, query_coords, dense_index, dense_slot, dense_range, dense_flag_finer
  public :: ar_ncells, ar_entries, ar_nleaves, ar_leaves

contains

  !> Integer cell coordinates on level k of a point (clamped to the cube).
  pure subroutine cell_coords(t, y, k, c)
    type(ar_tree), intent(in) :: t
    real(dp), intent(in) :: y(3)
    integer, intent(in) :: k
    integer(i8), intent(out) :: c(3)
    c = 0
    c(1:t%d) = axis_cell(y(1:t%d), t%lo(1:t%d), t%dm, pow2(k), ishft(1_i8, k) - 1_i8)
  end subroutine cell_coords

  !> Integer cell coordinates on level k of a point that may lie outside
  !> the cube (not clamped to it; the normalised coordinates are limited to
  !> [-2, 3], far enough for the stencils around the cube).
  pure subroutine query_coords(t, y, k, c)
    type(ar_tree), intent(in) :: t
    real(dp), intent(in) :: y(3)
    integer, intent(in) :: k
    integer(i8), intent(out) :: c(3)
    real(dp) :: u
    integer :: l
    c = 0
    do l = 1, t%d
       u = min(max((y(l) - t%lo(l)) / t%dm, -2.0_dp), 3.0_dp)
       c(l) = floor(u * pow2(k), i8)
    end do
  end subroutine query_coords

  !> Position in dval of the cell with coordinates c on dense level k, or -1
  !> if c lies outside that level's box.
  pure function dense_index(t, k, c) result(i)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k
    integer(i8), intent(in) :: c(3)
    integer(i8) :: i, r(3)
    r = c - t%dlo(:, k)
    i = -1
    if (any(r < 0) .or. any(r >= t%dext(:, k))) return
    i = dense_slot(t, k, c)
  end function dense_index

  !> dense_index without the box test, for cells known to lie in the box
  !> (every cell that holds or contains a particle of level >= k).
  pure function dense_slot(t, k, c) result(i)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k
    integer(i8), intent(in) :: c(3)
    integer(i8) :: i
    i = t%doff(k) + (c(1) - t%dlo(1, k)) + t%dext(1, k) * ((c(2) - t%dlo(2, k)) &
         + t%dext(2, k) * (c(3) - t%dlo(3, k)))
  end function dense_slot

  !> The range of dval indices of dense level k's cells (its sentinel excluded).
  pure subroutine dense_range(t, k, i0, i1)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k
    integer(i8), intent(out) :: i0, i1
    i0 = t%doff(k)
    i1 = t%doff(k) + product(t%dext(:, k)) - 1
  end subroutine dense_range

  !> Set the finer flag of the cell at dval index i of a dense level (an
  !> absent cell becomes present, without own slots).
  subroutine dense_flag_finer(t, i)
    type(ar_tree), intent(inout) :: t
    integer(i8), intent(in) :: i
    integer(i8) :: v
    v = t%dval(i)
    if (v == NO_ENTRY) then
       t%ndense = t%ndense + 1
       v = EMPTY_ENTRY
    end if
    t%dval(i) = ibset(v, FINER_BIT)
  end subroutine dense_flag_finer

  !> J of the cell at table index i of dense level k (for the tables handed
  !> to Python; the list loops know their cells' coordinates).
  pure function dense_key(t, k, i) result(key)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k
    integer(i8), intent(in) :: i
    integer(i8) :: key, c(3), r
    r = i - t%doff(k)
    c(1) = t%dlo(1, k) + mod(r, t%dext(1, k))
    r = r / t%dext(1, k)
    c(2) = t%dlo(2, k) + mod(r, t%dext(2, k))
    c(3) = t%dlo(3, k) + r / t%dext(2, k)
    key = ar_first_index(t%d, k) + ar_morton(t%d, c)
  end function dense_key

  !> Number of cells in the table (hash entries and non-empty dense entries).
  pure function ar_ncells(t) result(nc)
    type(ar_tree), intent(in) :: t
    integer :: nc
    nc = t%hash%nkey + t%ndense
  end function ar_ncells

  !> Every cell of the table: its J and entry, hash entries first, then the
  !> dense levels.
  subroutine ar_entries(t, keys, vals)
    type(ar_tree), intent(in) :: t
    integer(i8), intent(out) :: keys(:), vals(:)
    integer(i8) :: s, i, i0, i1
    integer :: e, j
    e = 0
    do s = 0, t%hash%mask
       if (t%hash%tab(1, s) == NOKEY) cycle
       e = e + 1
       keys(e) = t%hash%tab(1, s)
       vals(e) = t%hash%tab(2, s)
    end do
    do j = 1, 31
       if (.not. t%dense(j)) cycle
       call dense_range(t, j, i0, i1)
       do i = i0, i1
          if (t%dval(i) == NO_ENTRY) cycle
          e = e + 1
          keys(e) = dense_key(t, j, i)
          vals(e) = t%dval(i)
       end do
    end do
  end subroutine ar_entries

  !> Number of leaf cells (cells with own-level particles).
  pure function ar_nleaves(t) result(nl)
    type(ar_tree), intent(in) :: t
    integer :: nl
    nl = t%nleaf + t%ndleaf
  end function ar_nleaves

  !> Every leaf cell in slot order (by level, then J; on dense levels in
  !> table order): its J, slot range first .. last and level.
  subroutine ar_leaves(t, key, first, last, lev)
    type(ar_tree), intent(in) :: t
    integer(i8), intent(out) :: key(:)
    integer, intent(out) :: first(:), last(:), lev(:)
    integer(i8) :: i, i0, i1
    integer :: e, k, li
    e = 0
    do k = 0, t%maxlevel
       if (t%dense(k)) then
          call dense_range(t, k, i0, i1)
          do i = i0, i1
             if (t%dstart(i + 1) == t%dstart(i)) cycle
             e = e + 1
             key(e) = dense_key(t, k, i)
             first(e) = t%dstart(i)
             last(e) = t%dstart(i + 1) - 1
             lev(e) = k
          end do
       else
          do li = t%hleaf(k), t%hleaf(k + 1) - 1
             e = e + 1
             key(e) = t%leaf_key(li)
             first(e) = t%leaf_first(li)
             last(e) = t%leaf_last(li)
             lev(e) = k
          end do
       end if
    end do
  end subroutine ar_leaves

end module arpy_artree
