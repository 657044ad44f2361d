!> Algorithm 2 of Awile et al. (CPC 2012) on the hashed levels of the AR
!> tree: the particles of one level block are partitioned recursively and
!> in place, cell by cell, keyed by their Morton code on that level.  At each
!> step the particles of a cell are split into its descendants (an in-place
!> multi-way partition on the next digits of the Morton code), down to the
!> block's level; small ranges finish with an insertion sort.  Every leaf
!> cell (own-level particles) and every cell crossed on the way down (its
!> region holds particles of a finer level: the finer flag that lets
!> Algorithm 3 stop descending early) is entered in the cell table.
module arpy_arpartition
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC
  use arpy_arkeys, only: ar_first_index, ar_morton, morton_coords, axis_cell, pow2
  use arpy_arhash, only: FINER_BIT, entry_pack, hash_insert, hash_flag_finer
  use arpy_artree, only: ar_tree, dense_index, dense_flag_finer
  implicit none
  private

  integer, parameter :: SMALL = 24          !< ranges this short are insertion-sorted

  public :: partition_level, insertion_sort

contains

  !> Algorithm 2 on hashed level k, whose particles are in slots s0 .. s1
  !> (positions x(d, n)): their Morton keys on level k (into key(s0:s1)),
  !> then the recursive partition from the root.
  subroutine partition_level(t, x, k, s0, s1, key, info)
    type(ar_tree), intent(inout) :: t
    real(dp), intent(in) :: x(:, :)
    integer, intent(in) :: k, s0, s1
    integer(i8), intent(inout) :: key(:)
    integer, intent(out) :: info
    integer(i8) :: c(3), top
    real(dp) :: p2
    integer :: s, p
    p2 = pow2(k)
    top = ishft(1_i8, k) - 1_i8
    c = 0
    do s = s0, s1
       p = t%perm(s)
       c(1:t%d) = axis_cell(x(:, p), t%lo(1:t%d), t%dm, p2, top)
       key(s) = ar_morton(t%d, c)
    end do
    call partition(t, key, t%perm, s0, s1, 0, k, 0_i8, info)
  end subroutine partition_level

  !> Record the cell with Morton prefix `prefix` at depth `depth` of a level-k
  !> block: a leaf (depth == k: own-level slots s0..s1) or a cell crossed on
  !> the way down (0 < depth < k: it holds finer particles).
  subroutine record_cell(t, depth, k, prefix, s0, s1, info)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: depth, k, s0, s1
    integer(i8), intent(in) :: prefix
    integer, intent(out) :: info
    integer(i8) :: slot, key, c(3)
    info = ARPY_OK
    if (depth == 0 .and. k > 0) return  ! the root's finer flag is set by ar_build
    if (t%dense(depth)) then            ! a crossed cell: dense levels are not partitioned
       call morton_coords(t%d, prefix, c)
       call dense_flag_finer(t, dense_index(t, depth, c))
       return
    end if
    key = ar_first_index(t%d, depth) + prefix
    call hash_insert(t%hash, key, slot, info)
    if (info /= ARPY_OK) return
    if (depth < k) then
       call hash_flag_finer(t%hash, slot)
       return
    end if
    t%hash%tab(2, slot) = ior(iand(t%hash%tab(2, slot), ibset(0_i8, FINER_BIT)), &
         entry_pack(int(s0, i8), int(s1, i8)))
    t%nleaf = t%nleaf + 1
    t%leaf_key(t%nleaf) = key
    t%leaf_first(t%nleaf) = s0
    t%leaf_last(t%nleaf) = s1
  end subroutine record_cell

  !> Partition slots s0..s1 (all on level k, inside the cell with Morton
  !> prefix `prefix` at depth `depth`) recursively and in place into the
  !> cells below, recording every cell it creates.  Each step splits a cell
  !> into its descendants up to L levels down (2**(d L) buckets on the next
  !> d L bits of the Morton key): the paper's nested binary splits, L levels
  !> at a time, with L as large as keeps about 8 particles per bucket (at
  !> most 8 levels in 2D, 5 in 3D).
  recursive subroutine partition(t, key, perm, s0, s1, depth, k, prefix, info)
    type(ar_tree), intent(inout) :: t
    integer(i8), intent(inout) :: key(:)
    integer, intent(inout) :: perm(:)
    integer, intent(in) :: s0, s1, depth, k
    integer(i8), intent(in) :: prefix
    integer, intent(out) :: info
    integer, parameter :: LMAX(2:3) = [8, 5]
    integer :: nch, nl, l, s, e, dd, stat
    integer, allocatable :: cstart(:), nxt(:)
    integer(i8) :: last_anc(8), anc

    info = ARPY_OK
    call record_cell(t, depth, k, prefix, s0, s1, info)
    if (info /= ARPY_OK .or. depth == k) return
    if (s1 - s0 + 1 <= SMALL) then
       call sorted_cells(t, key, perm, s0, s1, depth, k, info)
       return
    end if
    ! levels split in this step: as many as keep the buckets well filled
    nl = 1
    do while (nl < min(LMAX(t%d), k - depth) .and. ishft(1, t%d * (nl + 1)) * 8 <= s1 - s0 + 1)
       nl = nl + 1
    end do
    nch = ishft(1, t%d * nl)
    allocate(cstart(0:nch), nxt(0:nch - 1), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    call bucket_partition(key, perm, s0, s1, t%d * (k - depth - nl), nch, cstart, nxt)
    ! the cells between this one and the buckets (each recorded once), then
    ! the buckets themselves, recursively
    last_anc = -1
    do l = 0, nch - 1
       s = cstart(l)
       e = cstart(l + 1) - 1
       if (e < s) cycle
       do dd = 1, nl - 1
          anc = ishft(int(l, i8), -t%d * (nl - dd))
          if (anc == last_anc(dd)) cycle
          last_anc(dd) = anc
          call record_cell(t, depth + dd, k, ishft(prefix, t%d * dd) + anc, s, e, info)
          if (info /= ARPY_OK) return
       end do
       call partition(t, key, perm, s, e, depth + nl, k, ishft(prefix, t%d * nl) + l, info)
       if (info /= ARPY_OK) return
    end do
  end subroutine partition

  !> In-place "American flag" partition of slots s0..s1 into nch buckets by
  !> the digit iand(ishft(key, -shift), nch - 1): bucket l ends up in slots
  !> cstart(l) .. cstart(l + 1) - 1.  nxt(0:nch-1): work space.
  pure subroutine bucket_partition(key, perm, s0, s1, shift, nch, cstart, nxt)
    integer(i8), intent(inout) :: key(:)
    integer, intent(inout) :: perm(:)
    integer, intent(in) :: s0, s1, shift, nch
    integer, intent(out) :: cstart(0:), nxt(0:)
    integer(i8) :: kt, kc, mask
    integer :: l, b, s, pt, pc
    mask = int(nch - 1, i8)
    cstart(0:nch) = 0
    do s = s0, s1
       b = int(iand(ishft(key(s), -shift), mask))
       cstart(b + 1) = cstart(b + 1) + 1
    end do
    cstart(0) = s0
    do b = 1, nch
       cstart(b) = cstart(b) + cstart(b - 1)
    end do
    nxt(0:nch - 1) = cstart(0:nch - 1)
    do l = 0, nch - 1
       do while (nxt(l) < cstart(l + 1))
          kc = key(nxt(l))
          pc = perm(nxt(l))
          b = int(iand(ishft(kc, -shift), mask))
          ! follow the cycle: drop the element into its bucket and pick up
          ! the one it displaces, until one belongs to bucket l
          do while (b /= l)
             kt = key(nxt(b))
             pt = perm(nxt(b))
             key(nxt(b)) = kc
             perm(nxt(b)) = pc
             nxt(b) = nxt(b) + 1
             kc = kt
             pc = pt
             b = int(iand(ishft(kc, -shift), mask))
          end do
          key(nxt(l)) = kc
          perm(nxt(l)) = pc
          nxt(l) = nxt(l) + 1
       end do
    end do
  end subroutine bucket_partition

  !> Finish a short range: insertion sort by key (this is the same partition
  !> for a handful of particles), then record the cells below depth from the
  !> runs of equal key prefixes.
  subroutine sorted_cells(t, key, perm, s0, s1, depth, k, info)
    type(ar_tree), intent(inout) :: t
    integer(i8), intent(inout) :: key(:)
    integer, intent(inout) :: perm(:)
    integer, intent(in) :: s0, s1, depth, k
    integer, intent(out) :: info
    integer :: s, dd, e, dnew
    info = ARPY_OK
    call insertion_sort(key, perm, s0, s1)
    ! each run of equal keys is a leaf; its ancestors below `depth` are new
    ! from the first depth at which its key differs from the previous run's
    s = s0
    do while (s <= s1)
       e = s
       do while (e < s1)
          if (key(e + 1) /= key(s)) exit
          e = e + 1
       end do
       dnew = depth + 1
       if (s > s0) dnew = k - (63 - leadz(ieor(key(s), key(s - 1)))) / t%d
       do dd = dnew, k
          call record_cell(t, dd, k, ishft(key(s), -t%d * (k - dd)), s, e, info)
          if (info /= ARPY_OK) return
       end do
       s = e + 1
    end do
  end subroutine sorted_cells

  !> Sort slots s0..s1 by key (stable), carrying perm along.
  pure subroutine insertion_sort(key, perm, s0, s1)
    integer(i8), intent(inout) :: key(:)
    integer, intent(inout) :: perm(:)
    integer, intent(in) :: s0, s1
    integer(i8) :: kt
    integer :: s, l, pt
    do s = s0 + 1, s1
       kt = key(s)
       pt = perm(s)
       l = s - 1
       do while (l >= s0)
          if (key(l) <= kt) exit
          key(l + 1) = key(l)
          perm(l + 1) = perm(l)
          l = l - 1
       end do
       key(l + 1) = kt
       perm(l + 1) = pt
    end do
  end subroutine insertion_sort

end module arpy_arpartition
