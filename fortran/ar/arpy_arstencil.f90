!> The AR tree's stencils as slot ranges (Op5 with Op2; Awile et al., CPC 2012): the
!> 3**d stencil of a cell on a level, hashed or dense, as the slot ranges of its cells'
!> particles (joined where they continue each other), pruned to a point's reach; the
!> stencils on the finer levels around a point; and the distance scan of a row over the
!> ranges.  The building blocks of the lists of arpy_arlists and arpy_arquery.
module arpy_arstencil
  use arpy_kinds, only: dp, i8, ARPY_OK, RULE_MIN
  use arpy_csr, only: row_builder, rb_reserve
  use arpy_celllist, only: range_total
  use arpy_pairs, only: scan_ranges
  use arpy_arkeys, only: ar_first_index, stencil_morton, pow2
  use arpy_arhash, only: entry_first, entry_last, entry_finer, hash_find
  use arpy_artree, only: ar_tree, cell_coords, query_coords
  implicit none
  private

  !> the rows of lists in parallel: blocks of at least ROWS_PER_BLOCK rows, up to
  !> BLOCKS_PER_THREAD per thread, taken in turn by the threads (rows cost unevenly: a
  !> block per thread leaves one waiting)
  integer, parameter, public :: BLOCKS_PER_THREAD = 8, ROWS_PER_BLOCK = 256

  public :: stencil_ranges, finer_ranges, scan_row, add_range

contains

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
  !> r = 1..nr, within the reach of (xa, ra) under the tree's rule.  Room is made first,
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
  !> On the deepest level nothing is finer, and the lists of the max and sum
  !> rules never descend (they search from the fine side, arpy_arlists), so
  !> there only cells after `above` are looked up (finer: .false.).  Given a
  !> point xa and its cutoff ra, the cells (and their finer particles)
  !> farther than min(ra, e) from xa are left out, e the
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
    logical :: later
    real(dp) :: g(-1:1, 3), r2
    call stencil_gaps(t, k, c, g, r2, xa, ra)
    if (t%dense(k)) then
       call dense_stencil(t, k, c, above, nr, rs, re, finer, g, r2)
       return
    end if
    f = ar_first_index(t%d, k)
    later = k == t%maxlevel .or. t%rule /= RULE_MIN
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
             if (later .and. key <= above) cycle
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
    logical :: later
    real(dp) :: gyz
    later = k == t%maxlevel .or. t%rule /= RULE_MIN
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
          if (.not. later) then
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

end module arpy_arstencil
