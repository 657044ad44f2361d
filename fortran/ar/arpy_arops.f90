!> The cell operations Op1-Op5 of the AR tree (Awile et al., CPC 2012,
!> §2.2): the cell of a point on a level, the particles of a cell, its
!> children, its parent and its neighbours, with their codes for the f2py
!> boundary (arpy_ar_ops; AR_OPS in arpy/_codes.py).
module arpy_arops
  use arpy_kinds, only: dp, i8
  use arpy_arkeys, only: ar_first_index, ar_morton, ar_decode
  use arpy_arhash, only: NO_ENTRY, entry_first, entry_last, entry_finer, hash_find
  use arpy_artree, only: ar_tree, cell_coords, dense_index
  implicit none
  private

  integer, parameter, public :: AR_OP_FIND_CELL = 1, AR_OP_LOOKUP = 2, AR_OP_CHILDREN = 3, &
       AR_OP_PARENT = 4, AR_OP_NEIGHBORS = 5

  public :: ar_find_cell, ar_lookup, ar_children, ar_parent, ar_neighbor_cells

contains

  !> Op1: J of the level-k cell containing point y(1:d); -1 if y lies
  !> outside the cube [lo, lo + D_m].
  function ar_find_cell(t, y, k) result(key)
    type(ar_tree), intent(in) :: t
    real(dp), intent(in) :: y(:)
    integer, intent(in) :: k
    integer(i8) :: key, c(3)
    real(dp) :: yy(3)
    key = -1
    if (any(y(1:t%d) < t%lo(1:t%d)) .or. any(y(1:t%d) > t%lo(1:t%d) + t%dm)) return
    yy = 0.0_dp
    yy(1:t%d) = y(1:t%d)
    call cell_coords(t, yy, k, c)
    key = ar_first_index(t%d, k) + ar_morton(t%d, c)
  end function ar_find_cell

  !> Op2 and the finer flag: look up cell J.  found = .false. if no particle
  !> lives in the cell's region on its level or below.
  pure subroutine ar_lookup(t, key, found, first, last, finer)
    type(ar_tree), intent(in) :: t
    integer(i8), intent(in) :: key
    logical, intent(out) :: found, finer
    integer, intent(out) :: first, last
    integer(i8) :: slot, c(3), v
    integer :: k
    found = .false.
    finer = .false.
    first = 1
    last = 0
    call ar_decode(t%d, key, k, c)
    if (t%dense(k)) then
       slot = dense_index(t, k, c)
       if (slot < 0) return
       v = t%dval(slot)
       if (v == NO_ENTRY) return
    else
       slot = hash_find(t%hash, key)
       if (slot < 0) return
       v = t%hash%tab(2, slot)
    end if
    found = .true.
    first = entry_first(v)
    last = entry_last(v)
    finer = entry_finer(v)
  end subroutine ar_lookup

  !> Op3: the 2**d children of cell J (level-order formula).
  pure subroutine ar_children(d, key, ch)
    integer, intent(in) :: d
    integer(i8), intent(in) :: key
    integer(i8), intent(out) :: ch(:)
    integer :: l
    do l = 0, ishft(1, d) - 1
       ch(l + 1) = key * ishft(1_i8, d) + l - ishft(1_i8, d) + 2
    end do
  end subroutine ar_children

  !> Op4: the parent of cell J > 1 (0 for the root).
  pure function ar_parent(d, key) result(par)
    integer, intent(in) :: d
    integer(i8), intent(in) :: key
    integer(i8) :: par
    par = 0
    if (key > 1) par = (key + ishft(1_i8, d) - 2) / ishft(1_i8, d)
  end function ar_parent

  !> Op5: the J of the (up to 3**d - 1) neighbours of cell J on its level
  !> that lie inside the domain, whether or not they hold particles.
  pure subroutine ar_neighbor_cells(d, key, nb, nnb)
    integer, intent(in) :: d
    integer(i8), intent(in) :: key
    integer(i8), intent(out) :: nb(:)
    integer, intent(out) :: nnb
    integer(i8) :: c(3), cc(3), m
    integer :: k, ox, oy, oz, oz_hi
    call ar_decode(d, key, k, c)
    m = ishft(1_i8, k)
    oz_hi = merge(1, 0, d == 3)
    nnb = 0
    do oz = -oz_hi, oz_hi
       do oy = -1, 1
          do ox = -1, 1
             if (ox == 0 .and. oy == 0 .and. oz == 0) cycle
             cc = c + [ox, oy, oz]
             if (any(cc(1:d) < 0) .or. any(cc(1:d) >= m)) cycle
             nnb = nnb + 1
             nb(nnb) = ar_first_index(d, k) + ar_morton(d, cc)
          end do
       end do
    end do
  end subroutine ar_neighbor_cells

end module arpy_arops
