!> Compressed sparse row (CSR) neighbour lists: a growable row builder and the
!> hand-off store through which a list of a priori unknown size reaches Python.
!>
!> A search publishes its symmetric list with rows in its own order (e.g. the
!> cell order of a cell list) plus the map from that order to particle
!> indices, and gets a handle for it.  Python then allocates arrays of the
!> final size and collects the list by its handle; only then are rows put
!> into particle order (and, for full lists, every pair written into both
!> rows), straight into Python's arrays.  Each published list has its own
!> handle, so builds never overwrite each other's results (a call made from a
!> signal handler between another call's build and collection is safe).
!>
!> Conventions: offsets are 0-based (off(1) = 0, off(n+1) = nnz) and the
!> stored neighbour indices are 0-based particle indices (default integer,
!> int32: at most 2**31-1 particles), so the arrays can be handed to NumPy
!> unchanged.  Row p (1-based here) occupies
!> idx(off(p)+1 : off(p+1)).
module arpy_csr
  use arpy_memory, only: advise_large
  use arpy_kinds, only: i8, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_NO_RESULT, ARPY_ERR_SIZE
  use arpy_threads, only: team_size, block_range, MIN_PARALLEL_ROWS
  implicit none
  private

  !> Rows are appended in order; entries of the current row with push.
  type, public :: row_builder
     integer :: n = 0                        !< number of rows
     integer(i8) :: nnz = 0                  !< entries stored so far
     integer(i8), allocatable :: off(:)      !< (n+1) row offsets
     integer, allocatable :: idx(:)          !< growable entry storage
  end type row_builder

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

  public :: list_capacity
  public :: rb_init, rb_push, rb_grow, rb_reserve, rb_join, rb_drop_ghost_pairs
  public :: handoff_publish, handoff_size, handoff_take, handoff_free
  public :: sort_rows, rows_sorted, sort_run, own_rows

  !> own_rows writes rows of up to this many entries in all in increasing order directly (two
  !> passes that write at random, fast while the rows stay in cache), larger ones as the list holds
  !> them and then sorts each row (one pass at random, the sorts in parallel).  Measured (2 cores):
  !> at 9e4 entries the fill takes 0.22 ms against 0.34 at 2 threads (0.55 at 1); at 5e5 both take
  !> the same at 2 threads; at 1.2e6 the first is 15 % slower.
  integer(i8), parameter :: IN_ORDER_MAX = 250000_i8

  !> published lists by handle (1-based); freed slots are reused.  Calls may come from several
  !> threads at once (the GIL is released): the slot table is touched only inside the critical
  !> section arpy_handoff, and each list by the one call that holds its handle.
  type(slot), allocatable, save :: store(:)

contains

  !> Prepare a builder for n rows with an initial capacity (>= 1).
  !> The ghost-ghost filter of symmetric lists (Awile et al. 2012, §2.4): with halo layers on
  !> half of the faces, ghost(bits /= 0)-ghost pairs whose d-bit halo strings share a bit
  !> (iand /= 0) are another subdomain's to compute and are dropped; pairs of a real particle
  !> (bits 0) and pairs of ghosts in different halos stay.  Row a is particle perm(a); entries
  !> are 0-based particle indices.  Compacts rb in place, rows and entries in their order.
  subroutine rb_drop_ghost_pairs(rb, perm, bits)
    type(row_builder), intent(inout) :: rb
    integer, intent(in) :: perm(:), bits(:)
    integer(i8) :: w, e, start
    integer :: a, bp, bq
    w = 0
    start = 0
    do a = 1, rb%n
       bp = bits(perm(a))
       do e = start + 1, rb%off(a + 1)
          bq = bits(rb%idx(e) + 1)
          if (bp /= 0 .and. iand(bp, bq) /= 0) cycle
          w = w + 1
          rb%idx(w) = rb%idx(e)
       end do
       start = rb%off(a + 1)
       rb%off(a + 1) = w
    end do
    rb%nnz = w
  end subroutine rb_drop_ghost_pairs

  !> First room for the symmetric list of `rows` particles in d dimensions: 8 entries a row in 2D,
  !> 16 in 3D (a lattice at cutoff 1.5 h has 4 and 9).  Room that is never written costs no memory
  !> (its pages are never touched), while running short costs a copy of the list, so the guess
  !> is generous.
  pure integer(i8) function list_capacity(d, rows) result(c)
    integer, intent(in) :: d, rows
    c = merge(16_i8, 8_i8, d == 3) * rows
  end function list_capacity

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
    call advise_large(rb%off)
    call advise_large(rb%idx)
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
    call advise_large(tmp)
    tmp(1:rb%nnz) = rb%idx(1:rb%nnz)
    call move_alloc(tmp, rb%idx)
  end subroutine rb_grow

  !> Make room for `need` entries after the first nnz, which are kept (the
  !> storage doubles as often as it must).  Hot loops test the size first and
  !> call this only when it is short.
  subroutine rb_reserve(rb, nnz, need, info)
    type(row_builder), intent(inout) :: rb
    integer(i8), intent(in) :: nnz, need
    integer, intent(out) :: info
    info = ARPY_OK
    rb%nnz = nnz
    do while (nnz + need > size(rb%idx, kind=i8))
       call rb_grow(rb, info)
       if (info /= ARPY_OK) return
    end do
  end subroutine rb_reserve

  !> Append the rows of the builders part(1:np), in order, to rb from entry nnz on: row r of part k
  !> is row first(k) + r of rb.  (Threads build parts of a list; joined in order, the list is the
  !> one a single thread builds.)
  subroutine rb_join(rb, nnz, np, part, first, info)
    type(row_builder), intent(inout) :: rb
    integer(i8), intent(inout) :: nnz
    integer, intent(in) :: np, first(np)
    type(row_builder), intent(in) :: part(np)
    integer, intent(out) :: info
    integer(i8) :: base(np + 1), e0, e1
    integer :: k, r, nb, t, r0, r1
    call rb_reserve(rb, nnz, sum(part%nnz), info)
    if (info /= ARPY_OK) return
    base(1) = nnz
    do k = 1, np
       base(k + 1) = base(k) + part(k)%nnz
    end do
    ! every part split among all threads (as many parts as threads would leave threads idle:
    ! a uniform grid's list at 2 threads has a single part to append)
    nb = team_size()
    if (base(np + 1) - base(1) < MIN_PARALLEL_ROWS) nb = 1
    do k = 1, np
       !$omp parallel do num_threads(nb) schedule(static, 1) private(e0, e1, r0, r1, r)
       do t = 1, nb
          e0 = (part(k)%nnz * (t - 1)) / nb
          e1 = (part(k)%nnz * t) / nb
          rb%idx(base(k) + e0 + 1:base(k) + e1) = part(k)%idx(e0 + 1:e1)
          call block_range(part(k)%n, nb, t, r0, r1)
          do r = r0, r1
             rb%off(first(k) + r + 1) = base(k) + part(k)%off(r + 1)
          end do
       end do
       !$omp end parallel do
    end do
    nnz = base(np + 1)
    rb%nnz = nnz
  end subroutine rb_join

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

  !> Sort the entries of every row by the rank of their index (rank(j + 1) for
  !> index j, 0-based): an insertion sort per row (rows are short), stable, rows
  !> in parallel from MIN_PARALLEL_ROWS entries; each row is written by one thread.
  subroutine sort_rows(n, nnz, off, idx, nr, rank)
    integer, intent(in) :: n, nr
    integer(i8), intent(in) :: nnz, off(n + 1), rank(nr)
    integer, intent(inout) :: idx(nnz)
    integer(i8) :: k, i, r
    integer :: p, j
    !$omp parallel do num_threads(team_size()) if(nnz >= MIN_PARALLEL_ROWS) schedule(static) private(k, i, r, j)
    do p = 1, n
       do k = off(p) + 2, off(p + 1)
          j = idx(k)
          r = rank(j + 1)
          i = k - 1
          do while (i > off(p))
             if (rank(idx(i) + 1) <= r) exit
             idx(i + 1) = idx(i)
             i = i - 1
          end do
          idx(i + 1) = j
       end do
    end do
    !$omp end parallel do
  end subroutine sort_rows

  !> Whether the entries of every row are in increasing order of the rank of their index (rank(j + 1)
  !> for index j, 0-based): the order sort_rows gives them.  Rows in parallel from MIN_PARALLEL_ROWS
  !> entries.
  logical function rows_sorted(n, nnz, off, idx, nr, rank) result(ok)
    integer, intent(in) :: n, nr
    integer(i8), intent(in) :: nnz, off(n + 1), rank(nr)
    integer, intent(in) :: idx(nnz)
    integer(i8) :: k
    integer :: p
    ok = .true.
    !$omp parallel do num_threads(team_size()) if(nnz >= MIN_PARALLEL_ROWS) schedule(static) private(k) &
    !$omp reduction(.and.: ok)
    do p = 1, n
       do k = off(p) + 2, off(p + 1)
          ok = ok .and. rank(idx(k - 1) + 1) < rank(idx(k) + 1)
       end do
    end do
    !$omp end parallel do
  end function rows_sorted

  !> The rows of the first n of the m particles of a symmetric list (each pair once) into out: each
  !> particle's partners, and with itself the particle itself, each row ascending (0-based).  The
  !> list is a search's rows: row a (off(a) + 1 .. off(a + 1) of idx, 0-based partners) belongs to
  !> particle perm(a) (a itself without perm).  Up to IN_ORDER_MAX entries the rows are written in
  !> increasing order directly (fill_in_order), larger ones as the list holds them and then sorted.
  subroutine own_rows(n, m, off, idx, itself, out, info, perm)
    integer, intent(in) :: n, m
    integer(i8), intent(in) :: off(m + 1)
    integer, intent(in) :: idx(*)
    logical, intent(in) :: itself
    type(row_builder), intent(inout) :: out
    integer, intent(out) :: info
    integer, intent(in), optional :: perm(m)
    integer, allocatable :: rowof(:), who(:)
    integer(i8), allocatable :: toff(:)
    integer(i8) :: e
    integer :: a, r, c, stat
    allocate(rowof(m), who(m), toff(m + 1), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    if (present(perm)) then
       who = perm
    else
       who = [(a, a = 1, m)]
    end if
    rowof(who) = [(a, a = 1, m)]
    ! row lengths: own entries, the rows that hold p, itself; toff: the transpose's (rows among
    ! the first n that hold q) lengths
    call rb_init(out, n, 0_i8, info)
    if (info /= ARPY_OK) return
    out%off = 0
    toff = 0
    do a = 1, m
       r = who(a)
       if (r <= n) out%off(r + 1) = out%off(r + 1) + (off(a + 1) - off(a))
       do e = off(a) + 1, off(a + 1)
          c = idx(e) + 1
          if (c <= n) out%off(c + 1) = out%off(c + 1) + 1
          if (r <= n) toff(c + 1) = toff(c + 1) + 1
       end do
    end do
    do r = 1, n
       out%off(r + 1) = out%off(r + 1) + out%off(r) + merge(1, 0, itself)
    end do
    out%nnz = out%off(n + 1)
    deallocate(out%idx)
    allocate(out%idx(max(out%nnz, 1_i8)), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    if (out%nnz <= IN_ORDER_MAX) then
       call fill_in_order(n, m, off, idx, rowof, itself, toff, out, info)
    else
       call fill_and_sort(n, m, off, idx, who, itself, out, info)
    end if
  end subroutine own_rows

  !> own_rows without a sort: q = 1, 2, ... is written into the rows of all of its partners in turn
  !> (those in its own row of the list, and from the transpose tr those among the first n whose own
  !> rows hold q: row q of tr), and into its own row with itself, so each row fills in increasing
  !> order.  Two passes that write at random, so for lists whose rows stay in cache; one thread
  !> (threads that each wrote their own rows would each read the whole list).  rowof(q): the row of
  !> the list that is particle q's; toff(q + 1): the length of row q of tr.
  subroutine fill_in_order(n, m, off, idx, rowof, itself, toff, out, info)
    integer, intent(in) :: n, m, rowof(m)
    integer(i8), intent(in) :: off(m + 1)
    integer, intent(in) :: idx(*)
    logical, intent(in) :: itself
    integer(i8), intent(inout) :: toff(m + 1)
    type(row_builder), intent(inout) :: out
    integer, intent(out) :: info
    integer(i8), allocatable :: at(:)
    integer, allocatable :: tr(:)
    integer(i8) :: e
    integer :: r, c, q, a, stat
    do q = 1, m
       toff(q + 1) = toff(q + 1) + toff(q)
    end do
    allocate(tr(max(toff(m + 1), 1_i8)), at(max(n, 1)), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    do r = 1, n                                ! rows in increasing r: each row of tr ascending
       a = rowof(r)
       do e = off(a) + 1, off(a + 1)
          c = idx(e) + 1
          toff(c) = toff(c) + 1
          tr(toff(c)) = r
       end do
    end do
    do q = m, 1, -1                            ! (the scatter moved each start to the next row's)
       toff(q + 1) = toff(q)
    end do
    toff(1) = 0
    at = out%off(1:n)
    do q = 1, m
       a = rowof(q)
       do e = off(a) + 1, off(a + 1)
          c = idx(e) + 1
          if (c > n) cycle
          at(c) = at(c) + 1
          out%idx(at(c)) = q - 1
       end do
       do e = toff(q) + 1, toff(q + 1)
          c = tr(e)
          at(c) = at(c) + 1
          out%idx(at(c)) = q - 1
       end do
       if (itself .and. q <= n) then
          at(q) = at(q) + 1
          out%idx(at(q)) = q - 1
       end if
    end do
    info = ARPY_OK
  end subroutine fill_in_order

  !> own_rows for large lists: each pair written into both rows as the list holds it (one pass at
  !> random), then every row sorted, in parallel from MIN_PARALLEL_ROWS entries, each by one thread
  !> (the same for any number).
  subroutine fill_and_sort(n, m, off, idx, who, itself, out, info)
    integer, intent(in) :: n, m, who(m)
    integer(i8), intent(in) :: off(m + 1)
    integer, intent(in) :: idx(*)
    logical, intent(in) :: itself
    type(row_builder), intent(inout) :: out
    integer, intent(out) :: info
    integer(i8), allocatable :: at(:)
    integer(i8) :: e
    integer :: a, r, c, stat
    allocate(at(max(n, 1)), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    info = ARPY_OK
    at = out%off(1:n)
    if (itself) then
       do r = 1, n
          at(r) = at(r) + 1
          out%idx(at(r)) = r - 1
       end do
    end if
    do a = 1, m
       r = who(a)
       do e = off(a) + 1, off(a + 1)
          c = idx(e) + 1
          if (r <= n) then
             at(r) = at(r) + 1
             out%idx(at(r)) = c - 1
          end if
          if (c <= n) then
             at(c) = at(c) + 1
             out%idx(at(c)) = r - 1
          end if
       end do
    end do
    !$omp parallel do num_threads(team_size()) if(out%nnz >= MIN_PARALLEL_ROWS) schedule(static)
    do r = 1, n
       call sort_run(out%idx, out%off(r) + 1, out%off(r + 1))
    end do
    !$omp end parallel do
  end subroutine fill_and_sort

  !> The entries idx(a:b) sorted in increasing order (an insertion sort: for short rows).
  pure subroutine sort_run(idx, a, b)
    integer, intent(inout) :: idx(:)
    integer(i8), intent(in) :: a, b
    integer(i8) :: k, i
    integer :: j
    do k = a + 1, b
       j = idx(k)
       i = k - 1
       do while (i >= a)
          if (idx(i) <= j) exit
          idx(i + 1) = idx(i)
          i = i - 1
       end do
       idx(i + 1) = j
    end do
  end subroutine sort_run

end module arpy_csr
