!> Compressed sparse row (CSR) neighbour lists: the growable row builder that every search fills,
!> and the rows of a list in particle order (sorted rows, a particle's own rows).  How a list of a
!> priori unknown size reaches Python: arpy_store.
!>
!> Conventions: offsets are 0-based (off(1) = 0, off(n+1) = nnz) and the
!> stored neighbour indices are 0-based particle indices (default integer,
!> int32: at most 2**31-1 particles), so the arrays can be handed to NumPy
!> unchanged.  Row p (1-based here) occupies
!> idx(off(p)+1 : off(p+1)).
module arpy_csr
  use arpy_memory, only: advise_large
  use arpy_kinds, only: i8, ARPY_OK, ARPY_ERR_ALLOC
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

  public :: list_capacity
  public :: rb_init, rb_push, rb_grow, rb_reserve, rb_join, rb_drop_ghost_pairs
  public :: sort_rows, rows_sorted, sort_run, own_rows

  !> own_rows writes rows of up to this many entries in all in increasing order directly (two
  !> passes that write at random, fast while the rows stay in cache), larger ones as the list holds
  !> them and then sorts each row (one pass at random, the sorts in parallel).  Measured (2 cores):
  !> at 9e4 entries the fill takes 0.22 ms against 0.34 at 2 threads (0.55 at 1); at 5e5 both take
  !> the same at 2 threads; at 1.2e6 the first is 15 % slower.
  integer(i8), parameter :: IN_ORDER_MAX = 250000_i8

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
  !> entries; the scan ends at the first entry out of order (a list to be sorted is seldom sorted
  !> in its first rows), on every thread once one has found one.
  logical function rows_sorted(n, nnz, off, idx, nr, rank) result(ok)
    integer, intent(in) :: n, nr
    integer(i8), intent(in) :: nnz, off(n + 1), rank(nr)
    integer, intent(in) :: idx(nnz)
    integer(i8) :: k
    integer :: p
    logical :: going
    ok = .true.
    !$omp parallel do num_threads(team_size()) if(nnz >= MIN_PARALLEL_ROWS) schedule(static) private(k, going) &
    !$omp shared(ok)
    do p = 1, n
       !$omp atomic read
       going = ok
       if (.not. going) cycle
       do k = off(p) + 2, off(p + 1)
          if (rank(idx(k - 1) + 1) >= rank(idx(k) + 1)) then
             !$omp atomic write
             ok = .false.
             exit
          end if
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
