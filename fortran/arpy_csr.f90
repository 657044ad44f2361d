!> Compressed sparse row (CSR) neighbour lists: a growable row builder, row
!> permutation, symmetric -> full expansion, and the hand-off store through
!> which a list of a priori unknown size reaches Python.
!>
!> Conventions: offsets are 0-based (off(1) = 0, off(n+1) = nnz) and the
!> stored neighbour indices are 0-based particle indices (default integer,
!> int32: at most 2**31-1 particles), so the arrays can be handed to NumPy
!> unchanged.  Row p (1-based here) occupies
!> idx(off(p)+1 : off(p+1)).
module arpy_csr
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_NO_RESULT, &
       ARPY_ERR_SIZE
  implicit none
  private

  !> Rows are appended in order; entries of the current row with push.
  type, public :: row_builder
     integer :: n = 0                        !< number of rows
     integer(i8) :: nnz = 0                  !< entries stored so far
     integer(i8), allocatable :: off(:)      !< (n+1) row offsets
     integer, allocatable :: idx(:)          !< growable entry storage
  end type row_builder

  public :: rb_init, rb_push, rb_grow, csr_permute_rows, csr_expand_full
  public :: handoff_publish, handoff_size, handoff_take, handoff_clear

  integer(i8), allocatable, save :: h_off(:)
  integer, allocatable, save :: h_idx(:)
  integer, save :: h_n = -1

contains

  !> Prepare a builder for n rows with an initial capacity (>= 1).
  subroutine rb_init(rb, n, capacity, info)
    type(row_builder), intent(inout) :: rb
    integer, intent(in) :: n
    integer(i8), intent(in) :: capacity
    integer, intent(out) :: info
    integer :: stat
    info = ARPY_OK
    if (allocated(rb%off)) deallocate(rb%off)
    if (allocated(rb%idx)) deallocate(rb%idx)
    rb%n = n
    rb%nnz = 0
    allocate(rb%off(n + 1), rb%idx(max(capacity, 16_i8)), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    rb%off(1) = 0
  end subroutine rb_init

  !> Double the entry storage of a builder.
  subroutine rb_grow(rb, info)
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    integer, allocatable :: tmp(:)
    integer :: stat
    info = ARPY_OK
    allocate(tmp(2 * size(rb%idx, kind=i8)), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    tmp(1:rb%nnz) = rb%idx(1:rb%nnz)
    call move_alloc(tmp, rb%idx)
  end subroutine rb_grow

  !> Append entry j (0-based particle index) to the current row.
  subroutine rb_push(rb, j, info)
    type(row_builder), intent(inout) :: rb
    integer, intent(in) :: j
    integer, intent(inout) :: info
    if (rb%nnz == size(rb%idx, kind=i8)) then
       call rb_grow(rb, info)
       if (info /= ARPY_OK) return
    end if
    rb%nnz = rb%nnz + 1
    rb%idx(rb%nnz) = j
  end subroutine rb_push

  !> Reorder the rows of a CSR list: row a of (off_s, idx_s) becomes row
  !> perm(a) of (off, idx).  off and idx are allocated here (exact size).
  subroutine csr_permute_rows(n, perm, off_s, idx_s, off, idx, info)
    integer, intent(in) :: n
    integer, intent(in) :: perm(n)
    integer(i8), intent(in) :: off_s(n + 1)
    integer, intent(in) :: idx_s(:)
    integer(i8), allocatable, intent(out) :: off(:)
    integer, allocatable, intent(out) :: idx(:)
    integer, intent(out) :: info
    integer(i8), allocatable :: dest(:)
    integer :: a, p, stat
    integer(i8) :: k, shift
    info = ARPY_OK
    allocate(off(n + 1), idx(off_s(n + 1)), dest(n), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    off(1) = 0
    do a = 1, n
       off(perm(a) + 1) = off_s(a + 1) - off_s(a)
    end do
    do p = 1, n
       off(p + 1) = off(p + 1) + off(p)
    end do
    ! gather the destinations first (independent loads), then copy rows with
    ! sequential reads and scattered writes
    do a = 1, n
       dest(a) = off(perm(a))
    end do
    do a = 1, n
       shift = dest(a) - off_s(a)
       do k = off_s(a) + 1, off_s(a + 1)
          idx(k + shift) = idx_s(k)
       end do
    end do
  end subroutine csr_permute_rows

  !> Expand a symmetric list (each unordered pair once) into the full list
  !> (each pair in both rows).  offf and idxf are allocated here.
  subroutine csr_expand_full(n, offh, idxh, offf, idxf, info)
    integer, intent(in) :: n
    integer(i8), intent(in) :: offh(n + 1)
    integer, intent(in) :: idxh(:)
    integer(i8), allocatable, intent(out) :: offf(:)
    integer, allocatable, intent(out) :: idxf(:)
    integer, intent(out) :: info
    integer(i8), allocatable :: fill(:)
    integer(i8) :: k
    integer :: p, q, stat
    info = ARPY_OK
    allocate(offf(n + 1), fill(n), idxf(2 * offh(n + 1)), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    ! degree of p = own entries + appearances as a neighbour of others
    offf(1) = 0
    do p = 1, n
       offf(p + 1) = offh(p + 1) - offh(p)
    end do
    do k = 1, offh(n + 1)
       q = idxh(k) + 2
       offf(q) = offf(q) + 1
    end do
    do p = 1, n
       offf(p + 1) = offf(p + 1) + offf(p)
    end do
    fill = offf(1:n)
    do p = 1, n
       do k = offh(p) + 1, offh(p + 1)
          q = idxh(k) + 1
          fill(p) = fill(p) + 1
          idxf(fill(p)) = idxh(k)
          fill(q) = fill(q) + 1
          idxf(fill(q)) = p - 1
       end do
    end do
  end subroutine csr_expand_full

  !> Keep a finished list until Python collects it (arrays are moved, not copied).
  subroutine handoff_publish(n, off, idx)
    integer, intent(in) :: n
    integer(i8), allocatable, intent(inout) :: off(:)
    integer, allocatable, intent(inout) :: idx(:)
    call handoff_clear()
    call move_alloc(off, h_off)
    call move_alloc(idx, h_idx)
    h_n = n
  end subroutine handoff_publish

  !> Number of rows and entries of the published list (-1, -1 if none).
  subroutine handoff_size(n, nnz)
    integer, intent(out) :: n
    integer(i8), intent(out) :: nnz
    n = h_n
    nnz = -1
    if (allocated(h_off)) nnz = h_off(h_n + 1)
  end subroutine handoff_size

  !> Copy the published list into caller arrays of exactly its size and free it.
  subroutine handoff_take(n, nnz, off, idx, info)
    integer, intent(in) :: n
    integer(i8), intent(in) :: nnz
    integer(i8), intent(out) :: off(n + 1)
    integer, intent(out) :: idx(nnz)
    integer, intent(out) :: info
    info = ARPY_OK
    if (.not. allocated(h_off)) then
       info = ARPY_ERR_NO_RESULT
       return
    end if
    if (n /= h_n .or. nnz /= h_off(h_n + 1)) then
       info = ARPY_ERR_SIZE
       return
    end if
    off = h_off
    idx = h_idx(1:nnz)
    call handoff_clear()
  end subroutine handoff_take

  !> Free the published list, if any.
  subroutine handoff_clear()
    if (allocated(h_off)) deallocate(h_off)
    if (allocated(h_idx)) deallocate(h_idx)
    h_n = -1
  end subroutine handoff_clear

end module arpy_csr
