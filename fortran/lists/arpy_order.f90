!> Particles in cache order: the permutation that sorts points along the
!> Morton (Z-order) curve of a fine grid over a cube.
!>
!> The cube [lo, lo + 2**B / s) is cut into 2**B cells per axis (B = 30 in
!> 2D, 20 in 3D: the 60-bit codes of the AR tree's deepest level, axis 1 the
!> most significant bit).  A point's cell is c_i = floor((x_i - lo_i) s),
!> clamped to [0, 2**B - 1]; points are ordered by the Morton code of their
!> cell, ties (points in one cell) by their input index.  Points next to each
!> other on the curve are close in space, so the cell lists, DC-PSE
!> assembly and pair loops that run over particles in this order read their
!> neighbours' data from nearby memory.
module arpy_order
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC
  use arpy_arkeys, only: ar_morton
  use arpy_arpartition, only: insertion_sort
  use arpy_threads, only: team_size, MIN_PARALLEL_ROWS
  implicit none
  private

  !> bits of one pass of the radix sort
  integer, parameter :: DIGIT = 12

  public :: morton_order, radix_sort

contains

  !> perm (0-based): the points x(:, perm + 1) in Morton order of their cells
  !> (see the module header); s > 0 is the number of cells per unit length.
  subroutine morton_order(d, n, x, lo, s, perm, info)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), lo(d), s
    integer, intent(out) :: perm(n), info
    integer(i8), allocatable :: key(:)
    integer(i8) :: c(3), top
    real(dp) :: u
    integer :: i, j, bits, stat

    info = ARPY_OK
    bits = merge(30, 20, d == 2)
    top = ishft(1_i8, bits) - 1_i8
    allocate(key(n), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_ROWS) schedule(static) private(c, u, j)
    do i = 1, n
       c = 0
       do j = 1, d
          u = (x(j, i) - lo(j)) * s
          if (u <= 0.0_dp) then
             c(j) = 0
          else if (u >= real(top, dp)) then
             c(j) = top
          else
             c(j) = int(u, i8)
          end if
       end do
       key(i) = ar_morton(d, c)
       perm(i) = i - 1
    end do
    !$omp end parallel do
    call sort_keys(n, key, perm, d, d * bits, info)
  end subroutine morton_order

  !> Stable sort of key(1:n) (values in [0, 2**nbits), nbits a multiple of d) carrying perm:
  !> one counting sort on the top bits (about n cells of the curve), then every cell that holds
  !> more than one key sorted on its own (insertion sort when small, else radix sort), cells in
  !> parallel (each writes only its own range: the result does not depend on the threads).
  subroutine sort_keys(n, key, perm, d, nbits, info)
    integer, intent(in) :: n, d, nbits
    integer(i8), intent(inout) :: key(n)
    integer, intent(inout) :: perm(n)
    integer, intent(out) :: info
    integer(i8), allocatable :: key2(:)
    integer, allocatable :: perm2(:), first(:)
    integer :: top, low, nb, i, b, stat, total, m, cinfo

    info = ARPY_OK
    if (n < 2) return
    top = d * max(1, min(24 / d, ceiling(log(real(n, dp)) / log(2.0_dp) / d)))
    top = min(top, nbits)
    low = nbits - top
    nb = 2**top
    allocate(key2(n), perm2(n), first(0:nb), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    first = 0
    do i = 1, n
       b = int(ishft(key(i), -low))
       first(b + 1) = first(b + 1) + 1
    end do
    do b = 1, nb
       first(b) = first(b) + first(b - 1)
    end do
    do i = 1, n                                       ! first(b): slots used so far below cell b + 1
       b = int(ishft(key(i), -low))
       first(b) = first(b) + 1
       key2(first(b)) = key(i)
       perm2(first(b)) = perm(i)
    end do
    ! now first(b) is the last slot of cell b (1-based), first(b - 1) the one before its first
    total = 0
    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_ROWS) schedule(dynamic, 1024) &
    !$omp& private(m, cinfo) reduction(max: total)
    do b = 0, nb - 1
       m = first(b) - merge(0, first(max(b - 1, 0)), b == 0)
       if (m > 1) then
          call sort_cell(key2(first(b) - m + 1:first(b)), perm2(first(b) - m + 1:first(b)), m, low, cinfo)
          total = max(total, cinfo)
       end if
    end do
    !$omp end parallel do
    if (total /= ARPY_OK) info = total
    key = key2
    perm = perm2
  end subroutine sort_keys

  !> The keys of one cell (equal above bit `low`) sorted, stably, carrying perm.
  subroutine sort_cell(k, p, m, low, info)
    integer, intent(in) :: m, low
    integer(i8), intent(inout) :: k(m)
    integer, intent(inout) :: p(m)
    integer, intent(out) :: info
    info = ARPY_OK
    if (m > 32) then
       call radix_sort(m, k, p, low, info)
    else
       call insertion_sort(k, p, 1, m)
    end if
  end subroutine sort_cell

  !> Stable least-significant-digit radix sort of key(1:n) (values in
  !> [0, 2**nbits)), carrying perm along; digits that every key shares are
  !> skipped.
  subroutine radix_sort(n, key, perm, nbits, info)
    integer, intent(in) :: n, nbits
    integer(i8), intent(inout) :: key(n)
    integer, intent(inout) :: perm(n)
    integer, intent(out) :: info
    integer(i8), allocatable :: key2(:)
    integer, allocatable :: perm2(:)
    integer :: cnt(0:2**DIGIT - 1)
    integer :: shift, i, b, total, stat
    logical :: in_second

    info = ARPY_OK
    if (n < 2) return
    allocate(key2(n), perm2(n), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    in_second = .false.
    do shift = 0, nbits - 1, DIGIT
       cnt = 0
       if (in_second) then
          call histogram(key2)
       else
          call histogram(key)
       end if
       if (maxval(cnt) == n) cycle             ! every key has this digit
       total = 0
       do b = 0, 2**DIGIT - 1                  ! exclusive prefix sums: the first slot of each digit
          i = cnt(b)
          cnt(b) = total
          total = total + i
       end do
       if (in_second) then
          call scatter(key2, perm2, key, perm)
       else
          call scatter(key, perm, key2, perm2)
       end if
       in_second = .not. in_second
    end do
    if (in_second) then
       key = key2
       perm = perm2
    end if

  contains

    subroutine histogram(k)
      integer(i8), intent(in) :: k(n)
      integer :: q
      do q = 1, n
         b = int(iand(ishft(k(q), -shift), int(2**DIGIT - 1, i8)))
         cnt(b) = cnt(b) + 1
      end do
    end subroutine histogram

    subroutine scatter(k, p, k_out, p_out)
      integer(i8), intent(in) :: k(n)
      integer, intent(in) :: p(n)
      integer(i8), intent(out) :: k_out(n)
      integer, intent(out) :: p_out(n)
      integer :: q
      do q = 1, n
         b = int(iand(ishft(k(q), -shift), int(2**DIGIT - 1, i8)))
         cnt(b) = cnt(b) + 1
         k_out(cnt(b)) = k(q)
         p_out(cnt(b)) = p(q)
      end do
    end subroutine scatter

  end subroutine radix_sort

end module arpy_order
