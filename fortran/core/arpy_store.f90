!> The hand-off store through which a CSR list (arpy_csr) of a priori unknown size reaches Python.
!>
!> A search publishes its symmetric list with rows in its own order (e.g. the
!> cell order of a cell list) plus the map from that order to particle
!> indices, and gets a handle for it.  Python then allocates arrays of the
!> final size and collects the list by its handle; only then are rows put
!> into particle order (and, for full lists, every pair written into both
!> rows), straight into Python's arrays.  Each published list has its own
!> handle, so builds never overwrite each other's results (a call made from a
!> signal handler between another call's build and collection is safe).
!> Offsets and indices follow arpy_csr's conventions.
module arpy_store
  use arpy_kinds, only: i8, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_NO_RESULT, ARPY_ERR_SIZE
  use arpy_threads, only: team_size, block_range, MIN_PARALLEL_ROWS
  use arpy_csr, only: row_builder
  implicit none
  private

  !> A published list: symmetric rows in search order, row a is particle perm(a) (perm unallocated:
  !> rows in particle order, a symmetric list in one piece), its entries idx(off(a) + 1 : off(a + 1)).
  !> Extra rows (xpart allocated): row j belongs to particle xpart(j) (1-based, ascending) after its
  !> row above; its entries are xidx(xoff(j) + 1 : xoff(j + 1)) (a list that adds a few pairs to
  !> another without moving it: the pairs across the faces of a periodic box).
  type :: published
     logical :: full = .false.
     integer :: n = -1
     integer(i8), allocatable :: off(:), xoff(:)
     integer, allocatable :: idx(:), perm(:), xpart(:), xidx(:)
  end type published

  !> A slot of the store: the list of one handle (null: free).  Lists live behind pointers, so
  !> growing the store never moves a list another call is reading or writing.
  type :: slot
     type(published), pointer :: list => null()
  end type slot

  public :: handoff_publish, handoff_size, handoff_take, handoff_free

  !> published lists by handle (1-based); freed slots are reused.  Calls may come from several
  !> threads at once (the GIL is released): the slot table is touched only inside the critical
  !> section arpy_handoff, and each list by the one call that holds its handle.
  type(slot), allocatable, save :: store(:)

contains

  !> Keep a finished symmetric list until Python collects it by `handle`.
  !> Row a of rb is particle perm(a) (1-based; rows in particle order if perm
  !> is absent or unallocated); full = .true. asks for both directions.  The
  !> builder's arrays and perm are moved, not copied.
  subroutine handoff_publish(rb, full, handle, info, perm, xpart, xoff, xidx)
    type(row_builder), intent(inout) :: rb
    logical, intent(in) :: full
    integer, intent(out) :: handle, info
    integer, allocatable, intent(inout), optional :: perm(:)
    integer, allocatable, intent(inout), optional :: xpart(:), xidx(:)   !< with xoff: extra rows (type published)
    integer(i8), allocatable, intent(inout), optional :: xoff(:)
    type(published), pointer :: e
    integer :: a, stat
    info = ARPY_OK
    handle = 0
    allocate(e, stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    if (present(perm)) call move_alloc(perm, e%perm)
    if (.not. allocated(e%perm) .and. (full .or. present(xpart))) then   ! (else rows in particle order: unallocated)
       allocate(e%perm(rb%n), stat=stat)
       if (stat /= 0) then
          deallocate(e)
          info = ARPY_ERR_ALLOC
          return
       end if
       e%perm = [(a, a = 1, rb%n)]
    end if
    call move_alloc(rb%off, e%off)
    call move_alloc(rb%idx, e%idx)
    if (present(xpart)) then
       call move_alloc(xpart, e%xpart)
       call move_alloc(xoff, e%xoff)
       call move_alloc(xidx, e%xidx)
    end if
    e%n = rb%n
    e%full = full
    !$omp critical (arpy_handoff)
    call claim_slot(e, handle, info)
    !$omp end critical (arpy_handoff)
    if (info /= ARPY_OK) deallocate(e)
  end subroutine handoff_publish

  !> Put list e into a free slot of the store (grown if full); called inside arpy_handoff.
  subroutine claim_slot(e, handle, info)
    type(published), pointer, intent(in) :: e
    integer, intent(out) :: handle, info
    type(slot), allocatable :: tmp(:)
    integer :: h, stat
    info = ARPY_OK
    handle = 0
    if (.not. allocated(store)) then
       allocate(store(4), stat=stat)
       if (stat /= 0) then
          info = ARPY_ERR_ALLOC
          return
       end if
    end if
    do h = 1, size(store)
       if (.not. associated(store(h)%list)) exit
    end do
    if (h > size(store)) then
       allocate(tmp(2 * size(store)), stat=stat)
       if (stat /= 0) then
          info = ARPY_ERR_ALLOC
          return
       end if
       tmp(1:size(store)) = store
       call move_alloc(tmp, store)
    end if
    store(h)%list => e
    handle = h
  end subroutine claim_slot

  !> The list of a handle (null if there is none); with detach, the slot is freed too.
  function list_of(handle, detach) result(e)
    integer, intent(in) :: handle
    logical, intent(in) :: detach
    type(published), pointer :: e
    e => null()
    !$omp critical (arpy_handoff)
    if (allocated(store)) then
       if (handle >= 1 .and. handle <= size(store)) then
          e => store(handle)%list
          if (detach) store(handle)%list => null()
       end if
    end if
    !$omp end critical (arpy_handoff)
  end function list_of

  !> Number of entries the list of `handle` will have (-1 if there is none).
  subroutine handoff_size(handle, nnz)
    integer, intent(in) :: handle
    integer(i8), intent(out) :: nnz
    type(published), pointer :: e
    nnz = -1
    e => list_of(handle, .false.)
    if (.not. associated(e)) return
    nnz = entries(e)
  end subroutine handoff_size

  !> Entries of the final list of e (both directions of a full list).
  integer(i8) function entries(e) result(nnz)
    type(published), intent(in) :: e
    nnz = e%off(e%n + 1)
    if (allocated(e%xpart)) nnz = nnz + e%xoff(size(e%xpart) + 1)
    if (e%full) nnz = 2 * nnz
  end function entries

  !> Write the list of `handle` into caller arrays of exactly its final size,
  !> rows in particle order, and free it (also when the sizes do not match).
  subroutine handoff_take(handle, n, nnz, off, idx, info)
    integer, intent(in) :: handle, n
    integer(i8), intent(in) :: nnz
    integer(i8), intent(out) :: off(n + 1)
    integer, intent(out) :: idx(nnz)
    integer, intent(out) :: info
    integer(i8) :: expected, k
    type(published), pointer :: e
    integer :: a, p, j

    info = ARPY_OK
    e => list_of(handle, .true.)
    if (.not. associated(e)) then
       info = ARPY_ERR_NO_RESULT
       return
    end if
    expected = entries(e)
    if (n /= e%n .or. nnz /= expected) then
       info = ARPY_ERR_SIZE
       deallocate(e)
       return
    end if
    if (.not. allocated(e%perm)) then           ! rows in particle order, in one piece (no extras): copies
       call copy_whole(n, nnz, e%off, e%idx, off, idx)
       deallocate(e)
       return
    end if
    associate (h_n => e%n, h_full => e%full, h_off => e%off, h_idx => e%idx, h_perm => e%perm)
      ! row lengths in particle order (each particle's row once: perm is a permutation; a full list
      ! adds the reverse entries), then offsets by a prefix sum
      off(1) = 0
      !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_ROWS) schedule(static)
      do a = 1, n
         off(h_perm(a) + 1) = h_off(a + 1) - h_off(a)
      end do
      !$omp end parallel do
      if (allocated(e%xpart)) then              ! the extra rows (few): their lengths added
         do j = 1, size(e%xpart)
            p = e%xpart(j)
            off(p + 1) = off(p + 1) + (e%xoff(j + 1) - e%xoff(j))
         end do
      end if
      if (h_full) then
         call count_reverse(n, h_off, h_idx, off)
         if (allocated(e%xpart)) then
            do k = 1, e%xoff(size(e%xpart) + 1)
               off(e%xidx(k) + 2) = off(e%xidx(k) + 2) + 1
            end do
         end if
      end if
      do p = 1, n
         off(p + 1) = off(p + 1) + off(p)
      end do
      if (.not. h_full) then
         call copy_rows(n, nnz, h_perm, h_off, h_idx, off, idx)
         if (allocated(e%xpart)) then           ! the extra rows at the ends of their particles' rows
            do j = 1, size(e%xpart)
               p = e%xpart(j)
               k = e%xoff(j + 1) - e%xoff(j)
               idx(off(p + 1) - k + 1:off(p + 1)) = e%xidx(e%xoff(j) + 1:e%xoff(j + 1))
            end do
         end if
      else
         if (allocated(e%xpart)) then
            call expand_rows(n, nnz, h_perm, h_off, h_idx, off, idx, info, e%xpart, e%xoff, e%xidx)
         else
            call expand_rows(n, nnz, h_perm, h_off, h_idx, off, idx, info)
         end if
         if (info /= ARPY_OK) then
            deallocate(e)
            return
         end if
      end if
    end associate
    deallocate(e)
  end subroutine handoff_take

  !> off = hoff and idx = hidx(1:nnz), in parallel blocks for large lists.
  subroutine copy_whole(n, nnz, hoff, hidx, off, idx)
    integer, intent(in) :: n, hidx(*)
    integer(i8), intent(in) :: nnz, hoff(n + 1)
    integer(i8), intent(out) :: off(n + 1)
    integer, intent(out) :: idx(nnz)
    integer :: nb, b
    integer(i8) :: k0, k1
    nb = team_size()
    if (n < MIN_PARALLEL_ROWS) nb = 1
    !$omp parallel do num_threads(nb) schedule(static, 1) private(k0, k1)
    do b = 1, nb
       k0 = ((n + 1_i8) * (b - 1)) / nb
       k1 = ((n + 1_i8) * b) / nb
       off(k0 + 1:k1) = hoff(k0 + 1:k1)
       k0 = (nnz * (b - 1)) / nb
       k1 = (nnz * b) / nb
       idx(k0 + 1:k1) = hidx(k0 + 1:k1)
    end do
    !$omp end parallel do
  end subroutine copy_whole

  !> Row a of a symmetric list in search order (hoff, hidx) copied to the row of particle perm(a) in
  !> the final arrays (off: offsets in particle order); rows in parallel for large lists, each entry
  !> written once.
  subroutine copy_rows(n, nnz, perm, hoff, hidx, off, idx)
    integer, intent(in) :: n, perm(n), hidx(*)
    integer(i8), intent(in) :: nnz, hoff(n + 1), off(n + 1)
    integer, intent(inout) :: idx(nnz)
    integer :: a
    integer(i8) :: s, len, o
    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_ROWS) schedule(static) private(a, s, len, o)
    do a = 1, n
       s = hoff(a)
       len = hoff(a + 1) - s
       o = off(perm(a))
       idx(o + 1:o + len) = hidx(s + 1:s + len)
    end do
    !$omp end parallel do
  end subroutine copy_rows

  !> off(q + 2) += 1 for every entry q (0-based) of a symmetric list: the reverse halves of the full
  !> list's row lengths.  In parallel, each thread counting the entries of the rows it owns.
  subroutine count_reverse(n, hoff, hidx, off)
    integer, intent(in) :: n, hidx(*)
    integer(i8), intent(in) :: hoff(n + 1)
    integer(i8), intent(inout) :: off(n + 1)
    integer :: nb, t, lo, hi, q
    integer(i8) :: k
    nb = team_size()
    if (n < MIN_PARALLEL_ROWS) nb = 1
    !$omp parallel do num_threads(nb) schedule(static, 1) private(lo, hi, k, q)
    do t = 1, nb
       call block_range(n, nb, t, lo, hi)
       do k = 1, hoff(n + 1)
          q = hidx(k) + 1
          if (q >= lo .and. q <= hi) off(q + 1) = off(q + 1) + 1
       end do
    end do
    !$omp end parallel do
  end subroutine count_reverse

  !> The full list from a symmetric one (rows as in copy_rows): each pair (p, q) of row a
  !> (p = perm(a)) goes to row p and to row q, in the order of the symmetric list.  In parallel, each
  !> thread owns a block of rows and goes through the whole list in order, writing only into its
  !> rows: every row is filled in the order of a serial pass.  The extra rows (xpart, xoff, xidx;
  !> type published) come after the others.
  subroutine expand_rows(n, nnz, perm, hoff, hidx, off, idx, info, xpart, xoff, xidx)
    integer, intent(in) :: n, perm(n), hidx(*)
    integer(i8), intent(in) :: nnz, hoff(n + 1), off(n + 1)
    integer, intent(inout) :: idx(nnz)
    integer, intent(out) :: info
    integer, intent(in), optional :: xpart(:), xidx(:)
    integer(i8), intent(in), optional :: xoff(:)
    integer(i8), allocatable :: fill(:)
    integer(i8) :: k
    integer :: nb, t, lo, hi, a, p, stat, j
    info = ARPY_OK
    allocate(fill(n), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    fill = off(1:n)
    nb = team_size()
    if (n < MIN_PARALLEL_ROWS) nb = 1
    !$omp parallel do num_threads(nb) schedule(static, 1) private(lo, hi, a, p, k, j)
    do t = 1, nb
       call block_range(n, nb, t, lo, hi)
       do a = 1, n
          p = perm(a)
          do k = hoff(a) + 1, hoff(a + 1)
             call put_pair(p, hidx(k) + 1, lo, hi, fill, idx)
          end do
       end do
       if (.not. present(xpart)) cycle
       do j = 1, size(xpart)
          p = xpart(j)
          do k = xoff(j) + 1, xoff(j + 1)
             call put_pair(p, xidx(k) + 1, lo, hi, fill, idx)
          end do
       end do
    end do
    !$omp end parallel do
  end subroutine expand_rows

  !> Pair (p, q) (1-based) of a full list: q appended to row p and p to row q, where the row lies
  !> in lo .. hi (the block of rows of the calling thread; fill: each row's last entry so far).
  pure subroutine put_pair(p, q, lo, hi, fill, idx)
    integer, intent(in) :: p, q, lo, hi
    integer(i8), intent(inout) :: fill(:)
    integer, intent(inout) :: idx(:)
    if (p >= lo .and. p <= hi) then
       fill(p) = fill(p) + 1
       idx(fill(p)) = q - 1
    end if
    if (q >= lo .and. q <= hi) then
       fill(q) = fill(q) + 1
       idx(fill(q)) = p - 1
    end if
  end subroutine put_pair

  !> Free the list of `handle`, if it names one.
  subroutine handoff_free(handle)
    integer, intent(in) :: handle
    type(published), pointer :: e
    e => list_of(handle, .true.)
    if (associated(e)) deallocate(e)
  end subroutine handoff_free

end module arpy_store
