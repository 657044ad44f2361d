!> Adaptive-resolution (AR) cell lists and Verlet lists (Awile, Buyukkececi,
!> Reboux, Sbalzarini, CPC 2012, Algorithms 1-3 and operations Op1-Op5).
!>
!> Domain and levels.  The domain [lo, hi] (default: the particles' bounding
!> box) is made cubic with edge D_m = max(hi - lo) anchored at lo (footnote 1);
!> if all particles coincide, D_m = max(rc).  Geometry uses the normalised
!> coordinates u = (x - lo) / D_m clipped to [0, 1], in which every cell corner
!> and midpoint is an exact dyadic number.  Level k (root = 0, cell edge
!> D_m / 2**k) holds the particles with D_m/2**k > rc >= D_m/2**(k+1); cutoffs
!> >= D_m/2 go to level 0.  The level-k cell of u has integer coordinates
!> c_i = min(floor(u_i 2**k), 2**k - 1).
!>
!> Level-order index J (the hash key).  Root J = 1; children of J are
!> J 2**d + l - 2**d + 2 (l = 0 .. 2**d - 1, axis 1 the most significant bit
!> of l, the split order of Algorithm 2); parent (J + 2**d - 2) / 2**d.  In
!> closed form J = F(k) + M_k(c) with F(k) = (2**(dk) - 1)/(2**d - 1) + 1 and
!> M_k the Morton (Z-order) code of c with axis 1 most significant.  J fits
!> int64 up to level 30 in 2D and 20 in 3D; deeper trees are refused
!> (ARPY_ERR_DEPTH).
!>
!> Build (Algorithm 1): levels are found by exact power-of-two comparisons and
!> particles are grouped by level with a counting sort (O(N), the same blocks
!> as the paper's sort by descending cutoff).  Algorithm 2 then partitions
!> every level block recursively and in place, cell by cell: at each step the
!> particles of a cell are split into its 2**d children (an in-place
!> multi-way partition on the child digit of their Morton code), down to the
!> block's level; small ranges finish with an insertion sort.  Every leaf cell
!> (own-level particles) and every cell crossed on the way down (its region
!> holds particles of a finer level: the "finer" flag that lets Algorithm 3
!> stop descending early) is entered in an open-addressing hash table keyed
!> by J.  Levels whose occupied region is compact are "dense": their cells
!> live in a plain array over that region instead of the hash, with the
!> first slot of every cell (empty ones included, as in a uniform cell
!> list), and all dense-level particles are put into their cells by one
!> counting sort in the arrays' row-major order; a stencil row is then one
!> contiguous slot range, and the cells above are flagged finer bottom-up.
!>
!> Lists (Algorithm 3): for each leaf cell, its 3**d stencil on its own level
!> is looked up once.  A particle on level k takes, on its own level, the
!> later particles of its cell and the particles of the stencil cells that
!> come later (larger J; on dense levels, later in the array): each pair
!> once; then, level by level while the stencil of the
!> level above holds finer particles, the particles of the full 3**d stencil
!> around its cell on each finer level.  Each unordered pair is found once, by
!> its coarser particle.  On the deepest level nothing is finer: when it is
!> dense its pairs are those of a uniform cell list over its array (the
!> uniform list's own loop, grid_rows).  The distance test is the brute-force
!> one, |x_p - x_q|**2 <= min(rc_p, rc_q)**2 with rc including the skin.
module arpy_arcells
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_DEPTH, &
       ARPY_ERR_OUTSIDE
  use arpy_csr, only: row_builder, rb_init, rb_reserve
  use arpy_celllist, only: bounding_box, gather_slots, grid_rows, range_total, scan_ranges
  implicit none
  private

  !> deepest level whose J still fits int64, for d = 2 and d = 3
  integer, parameter, public :: AR_MAXLEVEL(2:3) = [30, 20]

  integer(i8), parameter :: NOKEY = -1_i8
  integer, parameter :: SMALL = 24          !< ranges this short are insertion-sorted
  integer, parameter :: HBLOCK(2:3) = [4, 6] !< log2 of the hash block (2 levels of cells)
  integer(i8), parameter :: LOW31 = 2147483647_i8
  integer, parameter :: FINER_BIT = 62

  type, public :: ar_tree
     integer :: d = 0, n = 0
     integer :: maxlevel = -1                 !< deepest non-empty level
     real(dp) :: lo(3) = 0.0_dp               !< lower corner of the cube
     real(dp) :: dm = 1.0_dp                  !< cube edge D_m
     integer, allocatable :: perm(:)          !< slot -> particle (1-based)
     real(dp), allocatable :: xs(:, :)        !< (3, n) positions by slot (z = 0 in 2D)
     real(dp), allocatable :: rcs(:)          !< cutoffs (+ skin) by slot
     ! leaf cells (cells with own-level particles) of the hashed levels, in
     ! slot order (by level, then J): level k's are hleaf(k) .. hleaf(k+1)-1.
     ! The leaves of dense levels are their tables' non-empty cells (ndleaf).
     integer :: nleaf = 0, ndleaf = 0
     integer :: hleaf(0:32) = 1
     integer(i8), allocatable :: leaf_key(:)
     integer, allocatable :: leaf_first(:), leaf_last(:)
     ! hash table J -> own-level slot range [first, last] (first > last: none)
     ! and finer flag (1: the cell's region holds particles of finer levels):
     ! htab(1, s) = J (or NOKEY); htab(2, s) = first + last * 2**31 + finer * 2**62
     ! (one 16-byte entry per slot: a probe touches one cache line)
     integer :: nkey = 0
     integer(i8) :: hmask = -1
     integer :: hbits = 0
     integer(i8), allocatable :: htab(:, :)
     ! dense levels: a level whose occupied region is compact keeps its cells in
     ! a plain array over the bounding box of that region (cell coordinates
     ! dlo .. dlo + dext - 1), entry = the packed value of the hash (0: absent)
     ! and is not entered in the hash.  A perfect hash for those levels.
     ! dstart(i): the first own-level slot of table cell i, empty cells
     ! included (as the start array of a uniform cell list), so cell i owns
     ! slots dstart(i) .. dstart(i+1) - 1; each level's table is followed by
     ! one sentinel entry (dval = 0, dstart = the level's last slot + 1).
     logical :: dense(0:31) = .false.
     integer(i8) :: dlo(3, 0:31) = 0, dext(3, 0:31) = 1, doff(0:31) = 0
     integer :: ndense = 0                    !< non-empty dense entries
     integer(i8), allocatable :: dval(:)
     integer, allocatable :: dstart(:)
  end type ar_tree

  public :: ar_build, ar_half_list, ar_cross_list, ar_level_of
  public :: ar_first_index
  public :: ar_find_cell, ar_lookup, ar_children, ar_parent, ar_neighbor_cells
  public :: entry_first, entry_last, entry_finer, ar_ncells, ar_entries
  public :: ar_nleaves, ar_leaves

contains

  ! ------------------------------------------------------------------ keys

  !> First level-order index on level k: F(k) = (2**(d k) - 1)/(2**d - 1) + 1.
  pure function ar_first_index(d, k) result(f)
    integer, intent(in) :: d, k
    integer(i8) :: f
    ! constant divisors, so no integer division instruction is emitted
    if (d == 2) then
       f = (ishft(1_i8, 2 * k) - 1_i8) / 3_i8 + 1_i8
    else
       f = (ishft(1_i8, 3 * k) - 1_i8) / 7_i8 + 1_i8
    end if
  end function ar_first_index

  !> Spread the low 31 bits of v to the even bit positions (2D Morton).
  pure function spread2(v) result(r)
    integer(i8), intent(in) :: v
    integer(i8) :: r
    r = iand(v, 2147483647_i8)
    r = iand(ior(r, ishft(r, 16)), 281470681808895_i8)
    r = iand(ior(r, ishft(r, 8)), 71777214294589695_i8)
    r = iand(ior(r, ishft(r, 4)), 1085102592571150095_i8)
    r = iand(ior(r, ishft(r, 2)), 3689348814741910323_i8)
    r = iand(ior(r, ishft(r, 1)), 6148914691236517205_i8)
  end function spread2

  !> Spread the low 21 bits of v to every third bit position (3D Morton).
  pure function spread3(v) result(r)
    integer(i8), intent(in) :: v
    integer(i8) :: r
    r = iand(v, 2097151_i8)
    r = iand(ior(r, ishft(r, 32)), 8725724278095871_i8)
    r = iand(ior(r, ishft(r, 16)), 8725728556220671_i8)
    r = iand(ior(r, ishft(r, 8)), 1157144660301377551_i8)
    r = iand(ior(r, ishft(r, 4)), 1207822528635744451_i8)
    r = iand(ior(r, ishft(r, 2)), 1317624576693539401_i8)
  end function spread3

  !> Inverse of spread2: gather the even bits of v.
  pure function compact2(v) result(r)
    integer(i8), intent(in) :: v
    integer(i8) :: r
    r = iand(v, 6148914691236517205_i8)
    r = iand(ior(r, ishft(r, -1)), 3689348814741910323_i8)
    r = iand(ior(r, ishft(r, -2)), 1085102592571150095_i8)
    r = iand(ior(r, ishft(r, -4)), 71777214294589695_i8)
    r = iand(ior(r, ishft(r, -8)), 281470681808895_i8)
    r = iand(ior(r, ishft(r, -16)), 4294967295_i8)
  end function compact2

  !> Inverse of spread3: gather every third bit of v.
  pure function compact3(v) result(r)
    integer(i8), intent(in) :: v
    integer(i8) :: r
    r = iand(v, 1317624576693539401_i8)
    r = iand(ior(r, ishft(r, -2)), 1207822528635744451_i8)
    r = iand(ior(r, ishft(r, -4)), 1157144660301377551_i8)
    r = iand(ior(r, ishft(r, -8)), 8725728556220671_i8)
    r = iand(ior(r, ishft(r, -16)), 8725724278095871_i8)
    r = iand(ior(r, ishft(r, -32)), 2097151_i8)
  end function compact3

  !> Cell coordinates from a Morton code (inverse of ar_morton).
  pure subroutine morton_coords(d, m, c)
    integer, intent(in) :: d
    integer(i8), intent(in) :: m
    integer(i8), intent(out) :: c(3)
    c = 0
    if (d == 2) then
       c(1) = compact2(ishft(m, -1))
       c(2) = compact2(m)
    else
       c(1) = compact3(ishft(m, -2))
       c(2) = compact3(ishft(m, -1))
       c(3) = compact3(m)
    end if
  end subroutine morton_coords

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

  !> Morton code of integer cell coordinates c(1:d), axis 1 most significant.
  pure function ar_morton(d, c) result(m)
    integer, intent(in) :: d
    integer(i8), intent(in) :: c(3)
    integer(i8) :: m
    if (d == 2) then
       m = ior(ishft(spread2(c(1)), 1), spread2(c(2)))
    else
       m = ior(ior(ishft(spread3(c(1)), 2), ishft(spread3(c(2)), 1)), spread3(c(3)))
    end if
  end function ar_morton

  !> Level of a cutoff: the k >= 0 with D_m/2**k > rc >= D_m/2**(k+1) (exact:
  !> products with powers of two).  Levels beyond 62 are reported as 63.
  pure function ar_level_of(rc, dm) result(k)
    real(dp), intent(in) :: rc, dm
    integer :: k
    if (rc * 2.0_dp >= dm) then
       k = 0
       return
    end if
    ! estimate from the binary exponents, then make it exact
    k = int(iand(ishft(transfer(dm, 0_i8), -52), 2047_i8) &
         - iand(ishft(transfer(rc, 0_i8), -52), 2047_i8)) - 2
    k = min(max(k, 0), 62)
    do while (rc * pow2(k + 1) < dm)
       k = k + 1
       if (k == 63) return
    end do
    do while (k > 0)
       if (rc * pow2(k) < dm) exit
       k = k - 1
    end do
  end function ar_level_of

  !> 2**k as a real (exact), 0 <= k <= 63.
  elemental function pow2(k) result(p)
    integer, intent(in) :: k
    real(dp) :: p
    p = real(ishft(1_i8, min(k, 62)), dp) * merge(2.0_dp, 1.0_dp, k == 63)
  end function pow2

  !> Integer cell coordinate on a level with 2**k cells per axis (p2 = 2**k,
  !> top = 2**k - 1) of a coordinate y along an axis starting at lo.
  elemental function axis_cell(y, lo, dm, p2, top) result(c)
    real(dp), intent(in) :: y, lo, dm, p2
    integer(i8), intent(in) :: top
    integer(i8) :: c
    c = min(int(min(max((y - lo) / dm, 0.0_dp), 1.0_dp) * p2, i8), top)
  end function axis_cell

  !> Integer cell coordinates on level k of a point (clamped to the cube).
  pure subroutine cell_coords(t, y, k, c)
    type(ar_tree), intent(in) :: t
    real(dp), intent(in) :: y(3)
    integer, intent(in) :: k
    integer(i8), intent(out) :: c(3)
    c = 0
    c(1:t%d) = axis_cell(y(1:t%d), t%lo(1:t%d), t%dm, pow2(k), ishft(1_i8, k) - 1_i8)
  end subroutine cell_coords

  ! ------------------------------------------------------------------ hash table

  !> Slot of a key.  Keys are cut into blocks of 2**HBLOCK consecutive J
  !> (a 4 x 4 block of cells in 2D, 4 x 4 x 4 in 3D): the block is placed by
  !> Fibonacci hashing (top bits of block * 2**64/phi, wrapping: the core is
  !> compiled with -fwrapv), the key's position inside the block is kept.
  !> Neighbouring cells thus share cache lines, while sparse or strided key
  !> sets still spread evenly over the table.
  pure function hash_slot(t, key) result(h)
    type(ar_tree), intent(in) :: t
    integer(i8), intent(in) :: key
    integer(i8) :: h
    integer :: hb
    hb = HBLOCK(t%d)
    h = ishft(ishft(key, -hb) * (-7046029254386353131_i8), -(64 - t%hbits + hb))
    h = ior(ishft(h, hb), iand(key, ishft(1_i8, hb) - 1_i8))
  end function hash_slot

  !> Slot range [first, last] and finer flag of a packed table value.
  elemental function entry_first(v) result(first)
    integer(i8), intent(in) :: v
    integer :: first
    first = int(iand(v, LOW31))
  end function entry_first

  elemental function entry_last(v) result(last)
    integer(i8), intent(in) :: v
    integer :: last
    last = int(iand(ishft(v, -31), LOW31))
  end function entry_last

  elemental function entry_finer(v) result(finer)
    integer(i8), intent(in) :: v
    logical :: finer
    finer = btest(v, FINER_BIT)
  end function entry_finer

  !> An empty table for about `capacity` keys (it grows at load 0.6).
  subroutine hash_init(t, capacity, info)
    type(ar_tree), intent(inout) :: t
    integer(i8), intent(in) :: capacity
    integer, intent(out) :: info
    integer :: stat
    info = ARPY_OK
    t%hbits = HBLOCK(t%d) + 2
    do while (0.6_dp * real(ishft(1_i8, t%hbits), dp) < real(capacity, dp))
       t%hbits = t%hbits + 1
    end do
    t%hmask = ishft(1_i8, t%hbits) - 1_i8
    if (allocated(t%htab)) deallocate(t%htab)
    allocate(t%htab(2, 0:t%hmask), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    t%htab(1, :) = NOKEY
    t%nkey = 0
  end subroutine hash_init

  !> Insert key (or find it); returns its slot.  New entries hold an empty
  !> range (first = 1, last = 0) and no finer flag.
  recursive subroutine hash_insert(t, key, slot, info)
    type(ar_tree), intent(inout) :: t
    integer(i8), intent(in) :: key
    integer(i8), intent(out) :: slot
    integer, intent(out) :: info
    integer(i8), allocatable :: old(:, :)
    integer(i8) :: s, s2
    info = ARPY_OK
    if (real(t%nkey + 1, dp) > 0.6_dp * real(t%hmask + 1, dp)) then
       call move_alloc(t%htab, old)
       call hash_init(t, 2_i8 * (t%nkey + 1), info)
       if (info /= ARPY_OK) return
       do s = 0, size(old, 2, kind=i8) - 1
          if (old(1, s) == NOKEY) cycle
          call hash_insert(t, old(1, s), s2, info)
          if (info /= ARPY_OK) return
          t%htab(2, s2) = old(2, s)
       end do
    end if
    slot = hash_slot(t, key)
    do
       if (t%htab(1, slot) == key) return
       if (t%htab(1, slot) == NOKEY) exit
       slot = iand(slot + 1, t%hmask)
    end do
    t%htab(1, slot) = key
    t%htab(2, slot) = 1_i8
    t%nkey = t%nkey + 1
  end subroutine hash_insert

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
       if (v == 0) return
       found = .true.
       first = entry_first(v)
       last = entry_last(v)
       finer = entry_finer(v)
       return
    end if
    if (t%hmask < 0) return
    slot = hash_slot(t, key)
    do
       if (t%htab(1, slot) == key) then
          found = .true.
          first = entry_first(t%htab(2, slot))
          last = entry_last(t%htab(2, slot))
          finer = entry_finer(t%htab(2, slot))
          return
       end if
       if (t%htab(1, slot) == NOKEY) return
       slot = iand(slot + 1, t%hmask)
    end do
  end subroutine ar_lookup

  ! ------------------------------------------------------------------ Op1-Op5

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

  !> Level and integer coordinates of cell J (inverse of F(k) + Morton).
  pure subroutine ar_decode(d, key, k, c)
    integer, intent(in) :: d
    integer(i8), intent(in) :: key
    integer, intent(out) :: k
    integer(i8), intent(out) :: c(3)
    k = 0
    do while (k < AR_MAXLEVEL(d))
       if (ar_first_index(d, k + 1) > key) exit
       k = k + 1
    end do
    call morton_coords(d, key - ar_first_index(d, k), c)
  end subroutine ar_decode

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

  ! ------------------------------------------------------------------ build

  !> Algorithms 1 and 2: build the AR tree of n particles.
  !> lo_in, hi_in: the domain if has_domain (particles outside it are an
  !> error, ARPY_ERR_OUTSIDE, bad = particle); else the bounding box.
  subroutine ar_build(d, n, x, rc, skin, has_domain, lo_in, hi_in, t, info, bad)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), rc(n), skin, lo_in(d), hi_in(d)
    logical, intent(in) :: has_domain
    type(ar_tree), intent(inout) :: t
    integer, intent(out) :: info, bad
    integer, allocatable :: cnt(:), slot_of_level(:)
    ! plev: each particle's level, then its table index.  8 bytes, as the
    ! uniform list's cell array: freed before the list is built, it leaves room
    ! for the list's row offsets (8 bytes per particle).  With 4 bytes, glibc
    ! put the offsets on top of the heap and gave the heap back to the system
    ! after every call (1e4 page faults per call at N = 1e6, 30 ms).
    integer(i8), allocatable :: plev(:)
    integer(i8), allocatable :: key(:)
    integer(i8) :: c(3), slot, top
    real(dp), allocatable :: bmin(:, :), bmax(:, :)
    real(dp) :: hi(3), p2, rmin(3), rmax(3)
    integer :: p, p0, k, s, stat, lstart, nhashed

    info = ARPY_OK
    bad = 0
    t%d = d
    t%n = n
    t%lo = 0.0_dp
    hi = 0.0_dp
    if (has_domain) then
       t%lo(1:d) = lo_in
       hi(1:d) = hi_in
       do p = 1, n
          if (any(x(:, p) < lo_in) .or. any(x(:, p) > hi_in)) then
             info = ARPY_ERR_OUTSIDE
             bad = p
             return
          end if
       end do
    else if (n > 0) then
       call bounding_box(d, n, x, t%lo, hi)
    end if
    t%dm = maxval(hi(1:d) - t%lo(1:d))
    if (.not. (t%dm > 0.0_dp)) t%dm = maxval(rc) + skin
    if (n == 0) t%dm = 1.0_dp

    ! ---- Algorithm 1: levels, grouped by a counting sort
    allocate(plev(n), stat=stat)
    if (stat /= 0) goto 90
    ! levels, and per level the particle count and bounding box (for plan_dense)
    t%maxlevel = 0
    allocate(cnt(0:64), bmin(3, 0:63), bmax(3, 0:63), stat=stat)
    if (stat /= 0) goto 90
    cnt = 0
    bmin = huge(1.0_dp)
    bmax = -huge(1.0_dp)
    p0 = 1
    do while (p0 <= n)                    ! runs of one level (equal cutoffs are common)
       k = ar_level_of(rc(p0) + skin, t%dm)
       p = p0
       do while (p < n)
          if (rc(p + 1) /= rc(p)) then
             if (ar_level_of(rc(p + 1) + skin, t%dm) /= k) exit
          end if
          p = p + 1
       end do
       plev(p0:p) = k
       cnt(k + 1) = cnt(k + 1) + (p - p0 + 1)
       call bounding_box(d, p - p0 + 1, x(:, p0:p), rmin, rmax)
       bmin(1:d, k) = min(bmin(1:d, k), rmin(1:d))
       bmax(1:d, k) = max(bmax(1:d, k), rmax(1:d))
       p0 = p + 1
    end do
    do k = 63, 0, -1
       if (cnt(k + 1) > 0) exit
    end do
    t%maxlevel = max(k, 0)
    if (t%maxlevel > AR_MAXLEVEL(d)) then
       info = ARPY_ERR_DEPTH
       bad = maxloc(plev, dim=1)
       return
    end if
    allocate(slot_of_level(0:t%maxlevel + 1), stat=stat)
    if (stat /= 0) goto 90
    cnt(0) = 1
    do k = 1, t%maxlevel + 1
       cnt(k) = cnt(k) + cnt(k - 1)
    end do
    slot_of_level = cnt          ! first slot of each level; cnt(maxlevel+1) = n + 1

    if (allocated(t%perm)) deallocate(t%perm)     ! (each on its own: a caller may
    if (allocated(t%xs)) deallocate(t%xs)         !  have moved perm out of the tree)
    if (allocated(t%rcs)) deallocate(t%rcs)
    allocate(t%perm(n), t%xs(3, n), t%rcs(n), stat=stat)
    if (stat /= 0) goto 90

    ! ---- the cell table: dense arrays for compact levels, the hash for the rest
    call plan_dense(t, d, n, bmin, bmax, slot_of_level, info)
    if (info /= ARPY_OK) return
    ! slots: by level, and on dense levels by cell (one counting sort)
    call place_slots(t, d, n, x, plev, slot_of_level, nhashed)
    call hash_init(t, 16_i8 + nhashed, info)
    if (info /= ARPY_OK) return

    ! ---- Algorithm 2 on each level block, keyed by the Morton code on that level
    !      (on dense levels the counting sort above has found the cells)
    if (allocated(t%leaf_key)) deallocate(t%leaf_key, t%leaf_first, t%leaf_last)
    allocate(t%leaf_key(max(nhashed, 1)), t%leaf_first(max(nhashed, 1)), &
         t%leaf_last(max(nhashed, 1)), stat=stat)
    if (stat /= 0) goto 90
    t%nleaf = 0
    t%ndleaf = 0
    t%hleaf = 1
    do k = 0, t%maxlevel
       t%hleaf(k) = t%nleaf + 1
       lstart = slot_of_level(k)
       if (slot_of_level(k + 1) == lstart) cycle
       if (t%dense(k)) then
          call dense_cells(t, k, lstart, info)
          if (info /= ARPY_OK) return
          cycle
       end if
       if (.not. allocated(key)) then     ! Morton keys, for the hashed levels only
          allocate(key(n), stat=stat)
          if (stat /= 0) goto 90
       end if
       p2 = pow2(k)
       top = ishft(1_i8, k) - 1_i8
       c = 0
       do s = lstart, slot_of_level(k + 1) - 1
          p = t%perm(s)
          c(1:d) = axis_cell(x(:, p), t%lo(1:d), t%dm, p2, top)
          key(s) = ar_morton(d, c)
       end do
       call partition(t, key, t%perm, lstart, slot_of_level(k + 1) - 1, 0, k, 0_i8, info)
       if (info /= ARPY_OK) return
    end do
    t%hleaf(t%maxlevel + 1:) = t%nleaf + 1
    ! the root: level-0 particles are its own; finer if anything else exists
    if (t%maxlevel > 0) then
       call hash_insert(t, 1_i8, slot, info)
       if (info /= ARPY_OK) return
       t%htab(2, slot) = ibset(t%htab(2, slot), FINER_BIT)
    end if

    ! ---- gather positions and cutoffs into slot order
    call gather_slots(d, n, x, rc, skin, t%perm, t%xs, t%rcs)
    return
90  info = ARPY_ERR_ALLOC
  end subroutine ar_build

  !> Put the particles into slots: level by level (Algorithm 1's blocks,
  !> first_slot(k) the first slot of level k), and within a dense level by
  !> cell in the table's row-major order (axis 1 fastest), all in one
  !> counting sort over the particles.  This is Algorithm 2 on the dense
  !> levels: the same cells as the recursive partition, found directly, and
  !> a cell's forward neighbours become a few contiguous slot ranges, as in
  !> a uniform cell list.  On exit dstart(i) holds the slot after the last
  !> of dense cell i (dense_cells turns it into the first), and plev is
  !> overwritten (dense: table index; other levels: -(level + 1)).
  !> nhashed: the number of particles on the other (hashed) levels.
  subroutine place_slots(t, d, n, x, plev, first_slot, nhashed)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n)
    integer(i8), intent(inout) :: plev(n)
    integer, intent(in) :: first_slot(0:)
    integer, intent(out) :: nhashed
    integer(i8) :: i, top, cnt, pos, off, s2, s3, c0(3)
    integer :: cur(0:t%maxlevel)
    real(dp) :: p2, lo(3), dm
    integer :: p, k, kp
    kp = -1
    p2 = 1.0_dp
    top = 0
    off = 0
    s2 = 0
    s3 = 0
    c0 = 0
    lo = t%lo
    dm = t%dm
    do p = 1, n
       k = int(plev(p))
       if (.not. t%dense(k)) then
          plev(p) = -(k + 1)
          cycle
       end if
       if (k /= kp) then          ! the level's table, in scalars (runs of one level are common)
          kp = k
          p2 = pow2(k)
          top = ishft(1_i8, k) - 1_i8
          s2 = t%dext(1, k)
          s3 = t%dext(1, k) * t%dext(2, k)
          c0 = t%dlo(:, k)
          off = t%doff(k) - c0(1) - s2 * c0(2) - s3 * c0(3)
       end if
       ! dense_slot of the particle's cell
       i = off + axis_cell(x(1, p), lo(1), dm, p2, top) + s2 * axis_cell(x(2, p), lo(2), dm, p2, top)
       if (d == 3) i = i + s3 * axis_cell(x(d, p), lo(3), dm, p2, top)
       plev(p) = i
       t%dstart(i) = t%dstart(i) + 1
    end do
    ! counts -> first slots, level by level; the sentinel after each table
    nhashed = 0
    do k = 0, t%maxlevel
       cur(k) = first_slot(k)
       if (.not. t%dense(k)) then
          nhashed = nhashed + (first_slot(k + 1) - first_slot(k))
          cycle
       end if
       pos = first_slot(k)
       do i = t%doff(k), t%doff(k) + product(t%dext(:, k)) - 1
          cnt = t%dstart(i)
          t%dstart(i) = int(pos)
          pos = pos + cnt
       end do
       t%dstart(i) = int(pos)            ! = first_slot(k + 1)
    end do
    do p = 1, n
       i = plev(p)
       if (i >= 0) then
          t%perm(t%dstart(i)) = p
          t%dstart(i) = t%dstart(i) + 1
       else
          k = int(-i) - 1
          t%perm(cur(k)) = p
          cur(k) = cur(k) + 1
       end if
    end do
  end subroutine place_slots

  !> Finish dense level k (first slot s0) after place_slots: dstart back to
  !> each cell's first slot, every non-empty cell's slot range into the
  !> table (these cells are the level's leaves), and every such cell's
  !> ancestors flagged finer, bottom-up until one already is.
  subroutine dense_cells(t, k, s0, info)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: k, s0
    integer, intent(out) :: info
    integer(i8) :: c(3), i, pos, last, cx, cy, cz, parent(3)
    info = ARPY_OK
    c = 0
    parent = -1
    pos = s0
    i = t%doff(k) - 1
    do cz = t%dlo(3, k), t%dlo(3, k) + t%dext(3, k) - 1
       do cy = t%dlo(2, k), t%dlo(2, k) + t%dext(2, k) - 1
          do cx = t%dlo(1, k), t%dlo(1, k) + t%dext(1, k) - 1
             i = i + 1
             last = t%dstart(i) - 1
             t%dstart(i) = int(pos)
             if (last < pos) cycle
             t%dval(i) = pos + ishft(last, 31)
             t%ndense = t%ndense + 1
             t%ndleaf = t%ndleaf + 1
             pos = last + 1
             c = [cx, cy, cz]
             if (all(ishft(c, -1) == parent)) cycle   ! the previous cell's parent: flagged
             parent = ishft(c, -1)
             call mark_ancestors(t, k, c, info)
             if (info /= ARPY_OK) return
          end do
       end do
    end do
  end subroutine dense_cells

  !> Flag the ancestors (levels k-1 .. 1) of cell c on level k as holding
  !> finer particles, stopping at the first that already is (its own
  !> ancestors are then flagged too).
  subroutine mark_ancestors(t, k, c, info)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: k
    integer(i8), intent(in) :: c(3)
    integer, intent(out) :: info
    integer(i8) :: cc(3), slot, v
    integer :: j
    info = ARPY_OK
    cc = c
    do j = k - 1, 1, -1
       cc = ishft(cc, -1)
       if (t%dense(j)) then
          slot = dense_slot(t, j, cc)     ! an ancestor lies in its level's box
          v = t%dval(slot)
          if (entry_finer(v)) return
          if (v == 0) then
             t%ndense = t%ndense + 1
             v = 1_i8                     ! empty own range
          end if
          t%dval(slot) = ibset(v, FINER_BIT)
       else
          call hash_insert(t, ar_first_index(t%d, j) + ar_morton(t%d, cc), slot, info)
          if (info /= ARPY_OK) return
          if (entry_finer(t%htab(2, slot))) return
          t%htab(2, slot) = ibset(t%htab(2, slot), FINER_BIT)
       end if
    end do
  end subroutine mark_ancestors

  !> Choose the dense levels.  Every cell of level j that exists holds a
  !> particle of level >= j, so it lies inside the level-j cells spanned by
  !> the bounding box of those particles.  Level j is kept dense when that
  !> box has at most 4 cells per such particle (+1024), within a total budget
  !> of 4 n + 4096 cells (12 bytes each).  bmin/bmax: on entry the bounding
  !> box of each level's own particles; first_slot: each level's first slot
  !> (as in ar_build).
  subroutine plan_dense(t, d, n, bmin, bmax, first_slot, info)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: d, n, first_slot(0:)
    real(dp), intent(inout) :: bmin(:, 0:), bmax(:, 0:)
    integer, intent(out) :: info
    real(dp) :: cells
    integer(i8) :: cum(0:t%maxlevel + 1), total, budget, clo(3), chi(3)
    integer :: j, stat
    info = ARPY_OK
    t%dense = .false.
    t%ndense = 0
    cum = 0
    do j = 0, t%maxlevel
       cum(j) = first_slot(j + 1) - first_slot(j)
    end do
    do j = t%maxlevel - 1, 0, -1
       bmin(:, j) = min(bmin(:, j), bmin(:, j + 1))
       bmax(:, j) = max(bmax(:, j), bmax(:, j + 1))
       cum(j) = cum(j) + cum(j + 1)
    end do
    budget = 4_i8 * n + 4096_i8
    total = 0
    do j = 1, t%maxlevel
       if (cum(j) == 0) cycle
       clo = 0
       chi = 0
       clo(1:d) = axis_cell(bmin(1:d, j), t%lo(1:d), t%dm, pow2(j), ishft(1_i8, j) - 1_i8)
       chi(1:d) = axis_cell(bmax(1:d, j), t%lo(1:d), t%dm, pow2(j), ishft(1_i8, j) - 1_i8)
       cells = product(real(chi - clo + 1, dp))
       if (cells > real(4_i8 * cum(j) + 1024_i8, dp) .or. real(total, dp) + cells > real(budget, dp)) cycle
       t%dense(j) = .true.
       t%dlo(:, j) = clo
       t%dext(:, j) = chi - clo + 1
       t%doff(j) = total
       total = total + int(cells, i8) + 1_i8     ! + the sentinel
    end do
    if (allocated(t%dval)) deallocate(t%dval)
    if (allocated(t%dstart)) deallocate(t%dstart)
    allocate(t%dval(0:max(total, 1_i8) - 1), t%dstart(0:max(total, 1_i8) - 1), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    t%dval = 0
    t%dstart = 0
  end subroutine plan_dense

  !> Number of cells in the table (hash entries and non-empty dense entries).
  pure function ar_ncells(t) result(nc)
    type(ar_tree), intent(in) :: t
    integer :: nc
    nc = t%nkey + t%ndense
  end function ar_ncells

  !> Every cell of the table: its J and packed value (see htab), hash
  !> entries first, then the dense levels.
  subroutine ar_entries(t, keys, vals)
    type(ar_tree), intent(in) :: t
    integer(i8), intent(out) :: keys(:), vals(:)
    integer(i8) :: s, i
    integer :: e, j
    e = 0
    do s = 0, t%hmask
       if (t%htab(1, s) == NOKEY) cycle
       e = e + 1
       keys(e) = t%htab(1, s)
       vals(e) = t%htab(2, s)
    end do
    do j = 1, 31
       if (.not. t%dense(j)) cycle
       do i = t%doff(j), t%doff(j) + product(t%dext(:, j)) - 1
          if (t%dval(i) == 0) cycle
          e = e + 1
          keys(e) = dense_key(t, j, i)
          vals(e) = t%dval(i)
       end do
    end do
  end subroutine ar_entries

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
    integer(i8) :: i
    integer :: e, k, li
    e = 0
    do k = 0, t%maxlevel
       if (t%dense(k)) then
          do i = t%doff(k), t%doff(k) + product(t%dext(:, k)) - 1
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

  !> Record the cell with Morton prefix `prefix` at depth `depth` of a level-k
  !> block: a leaf (depth == k: own-level slots s0..s1) or a cell crossed on
  !> the way down (0 < depth < k: it holds finer particles).
  subroutine record_cell(t, depth, k, prefix, s0, s1, info)
    type(ar_tree), intent(inout) :: t
    integer, intent(in) :: depth, k, s0, s1
    integer(i8), intent(in) :: prefix
    integer, intent(out) :: info
    integer(i8) :: slot, key, c(3), v
    info = ARPY_OK
    if (depth == 0 .and. k > 0) return  ! the root's finer flag is set by ar_build
    key = ar_first_index(t%d, depth) + prefix
    if (t%dense(depth)) then            ! (then depth < k: dense levels are not partitioned)
       call morton_coords(t%d, prefix, c)
       slot = dense_index(t, depth, c)
       v = t%dval(slot)
       if (v == 0) then
          t%ndense = t%ndense + 1
          v = 1_i8                       ! empty own range: first = 1, last = 0
       end if
       t%dval(slot) = ibset(v, FINER_BIT)
       return
    else
       call hash_insert(t, key, slot, info)
       if (info /= ARPY_OK) return
       if (depth < k) then
          t%htab(2, slot) = ibset(t%htab(2, slot), FINER_BIT)
          return
       end if
       t%htab(2, slot) = ior(iand(t%htab(2, slot), ibset(0_i8, FINER_BIT)), &
            int(s0, i8) + ishft(int(s1, i8), 31))
    end if
    if (depth < k) return
    t%nleaf = t%nleaf + 1
    t%leaf_key(t%nleaf) = key
    t%leaf_first(t%nleaf) = s0
    t%leaf_last(t%nleaf) = s1
  end subroutine record_cell

  !> Algorithm 2: partition slots s0..s1 (all on level k, inside the cell with
  !> Morton prefix `prefix` at depth `depth`) recursively and in place into
  !> the cells below, recording every cell it creates.  Each step splits a
  !> cell into its descendants up to L levels down (2**(d L) buckets, an
  !> in-place "American flag" multi-way partition on the next d L bits of the
  !> Morton key): the paper's nested binary splits, L levels at a time, with
  !> L as large as keeps about 8 particles per bucket (at most 8 levels in
  !> 2D, 5 in 3D).
  recursive subroutine partition(t, key, perm, s0, s1, depth, k, prefix, info)
    type(ar_tree), intent(inout) :: t
    integer(i8), intent(inout) :: key(:)
    integer, intent(inout) :: perm(:)
    integer, intent(in) :: s0, s1, depth, k
    integer(i8), intent(in) :: prefix
    integer, intent(out) :: info
    integer, parameter :: LMAX(2:3) = [8, 5]
    integer :: nch, shift, nl, l, b, s, e, pt, pc, dd, stat
    integer, allocatable :: cstart(:), nxt(:)
    integer(i8) :: kt, kc, mask, last_anc(8), anc

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
    shift = t%d * (k - depth - nl)        ! position of the bucket digit in the key
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

  !> Finish a short range: insertion sort by key (this is the same partition
  !> for a handful of particles), then record the cells below depth from the
  !> runs of equal key prefixes.
  subroutine sorted_cells(t, key, perm, s0, s1, depth, k, info)
    type(ar_tree), intent(inout) :: t
    integer(i8), intent(inout) :: key(:)
    integer, intent(inout) :: perm(:)
    integer, intent(in) :: s0, s1, depth, k
    integer, intent(out) :: info
    integer :: s, l, pt, dd, e, dnew
    integer(i8) :: kt
    info = ARPY_OK
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

  ! ------------------------------------------------------------------ lists

  !> Append to the current row every slot b of the ranges rs(r)..re(r),
  !> r = 1..nr, within the min-rule cutoff of (xa, ra).  Room is made first,
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
    call scan_ranges(t%xs, t%rcs, t%perm, xa, ra, nr, rs, re, rb%idx, nnz)
  end subroutine scan_row

  !> Op5 with Op2: the 3**d stencil around cell c on level k (cells outside
  !> [0, 2**k) dropped).  Appends the own-level slot range of every existing
  !> stencil cell that comes after the cell `above` (all of them for above <
  !> 0) to rs/re, joining ranges that continue the previous one, and tells
  !> whether any stencil cell holds finer particles.  Cells are ordered by J,
  !> or on a dense level by their table index (the order of their slots).
  !> On the deepest level nothing is finer, so only cells after `above` are
  !> looked up.
  subroutine stencil_ranges(t, k, c, above, nr, rs, re, finer)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k
    integer(i8), intent(in) :: c(3), above
    integer, intent(inout) :: nr, rs(:), re(:)
    logical, intent(out) :: finer
    integer(i8) :: f, m, key, slot, v, sx(-1:1), sy(-1:1), sz(-1:1)
    integer :: oz_hi, ox, oy, oz
    logical :: deepest
    if (t%dense(k)) then
       call dense_stencil(t, k, c, above, nr, rs, re, finer)
       return
    end if
    f = ar_first_index(t%d, k)
    m = ishft(1_i8, k)
    deepest = k == t%maxlevel
    ! Morton parts of the neighbouring coordinates (-1: outside the grid)
    do ox = -1, 1
       if (t%d == 2) then
          sx(ox) = ishft(spread2(c(1) + ox), 1)
          sy(ox) = spread2(c(2) + ox)
          sz(ox) = 0
       else
          sx(ox) = ishft(spread3(c(1) + ox), 2)
          sy(ox) = ishft(spread3(c(2) + ox), 1)
          sz(ox) = spread3(c(3) + ox)
       end if
       if (c(1) + ox < 0 .or. c(1) + ox >= m) sx(ox) = -1
       if (c(2) + ox < 0 .or. c(2) + ox >= m) sy(ox) = -1
       if (t%d == 3 .and. (c(3) + ox < 0 .or. c(3) + ox >= m)) sz(ox) = -1
    end do
    oz_hi = merge(1, 0, t%d == 3)
    finer = .false.
    do oz = -oz_hi, oz_hi
       if (sz(oz) < 0) cycle
       do oy = -1, 1
          if (sy(oy) < 0) cycle
          do ox = -1, 1
             if (sx(ox) < 0) cycle
             key = f + ior(ior(sx(ox), sy(oy)), sz(oz))
             if (deepest .and. key <= above) cycle
             ! Op2: probe the hash table
             slot = hash_slot(t, key)
             do
                if (t%htab(1, slot) == key .or. t%htab(1, slot) == NOKEY) exit
                slot = iand(slot + 1, t%hmask)
             end do
             if (t%htab(1, slot) /= key) cycle
             v = t%htab(2, slot)
             finer = finer .or. entry_finer(v)
             if (key > above) call add_range(entry_first(v), entry_last(v), nr, rs, re)
          end do
       end do
    end do
  end subroutine stencil_ranges

  !> stencil_ranges on a dense level: the table index orders the cells, so
  !> each row of the stencil (axis 1) is three consecutive entries, and their
  !> own-level particles one slot range read from dstart.
  subroutine dense_stencil(t, k, c, above, nr, rs, re, finer)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k
    integer(i8), intent(in) :: c(3), above
    integer, intent(inout) :: nr, rs(:), re(:)
    logical, intent(out) :: finer
    integer(i8) :: cl(3), row, slot, xlo, xhi, first
    integer :: oz_hi, oy, oz
    logical :: deepest
    deepest = k == t%maxlevel
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
          row = t%doff(k) + t%dext(1, k) * ((cl(2) + oy) + t%dext(2, k) * (cl(3) + oz))
          if (.not. deepest) then
             do slot = row + xlo, row + xhi
                finer = finer .or. entry_finer(t%dval(slot))
             end do
          end if
          first = max(row + xlo, above + 1)
          if (first <= row + xhi) call add_range(t%dstart(first), t%dstart(row + xhi + 1) - 1, nr, rs, re)
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

  !> Algorithm 3, symmetric list: row a (slot order) lists the neighbours
  !> found by the particle in slot a (0-based particle indices).  Leaf cells
  !> in slot order: on dense levels the non-empty table cells, whose
  !> coordinates the loop knows; on hashed levels the recorded leaves.
  subroutine ar_half_list(t, rb, info)
    type(ar_tree), intent(in) :: t
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    integer :: li, k
    integer(i8) :: c(3), nnz, i, cx, cy, cz

    call rb_init(rb, t%n, 8_i8 * t%n, info)
    if (info /= ARPY_OK) return
    nnz = 0
    c = 0
    do k = 0, t%maxlevel
       if (t%dense(k) .and. k == t%maxlevel) then
          ! the deepest level holds nothing finer: its pairs are those of a
          ! uniform cell list over its table
          call grid_rows(t%dstart(t%doff(k):), t%dext(:, k), t%xs, t%rcs, t%perm, rb, nnz, info)
          if (info /= ARPY_OK) return
       else if (t%dense(k)) then
          i = t%doff(k) - 1
          do cz = t%dlo(3, k), t%dlo(3, k) + t%dext(3, k) - 1
             do cy = t%dlo(2, k), t%dlo(2, k) + t%dext(2, k) - 1
                do cx = t%dlo(1, k), t%dlo(1, k) + t%dext(1, k) - 1
                   i = i + 1
                   if (t%dstart(i + 1) == t%dstart(i)) cycle
                   c = [cx, cy, cz]
                   call leaf_pairs(t, k, c, i, t%dstart(i), t%dstart(i + 1) - 1, rb, nnz, info)
                   if (info /= ARPY_OK) return
                end do
             end do
          end do
       else
          do li = t%hleaf(k), t%hleaf(k + 1) - 1
             ! the cell's coordinates from its J (Morton code), no division
             if (k > 0) call morton_coords(t%d, t%leaf_key(li) - ar_first_index(t%d, k), c)
             call leaf_pairs(t, k, c, t%leaf_key(li), t%leaf_first(li), t%leaf_last(li), rb, nnz, info)
             if (info /= ARPY_OK) return
          end do
       end if
    end do
    rb%nnz = nnz
  end subroutine ar_half_list

  !> The rows of leaf cell c on level k (slots s0 .. s1; `above` = its J, or
  !> on a dense level its table index): on its own level the later particles
  !> of the cell and of the stencil cells that come after it (Op5, looked up
  !> once per cell), then on finer levels the full stencils.
  subroutine leaf_pairs(t, k, c, above, s0, s1, rb, nnz, info)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: k, s0, s1
    integer(i8), intent(in) :: c(3), above
    type(row_builder), intent(inout) :: rb
    integer(i8), intent(inout) :: nnz
    integer, intent(out) :: info
    integer, parameter :: MAXR = 1 + 27 * 31
    integer :: a, delta, nr_own, nr, re_own
    integer(i8) :: cf(3), need
    integer :: rs(MAXR), re(MAXR)
    logical :: finer_own, finer
    real(dp) :: xa(3), ra

    info = ARPY_OK
    ! own level: range 1 = the rest of the cell (set per particle), then
    ! the stencil cells that come later
    nr_own = 1
    rs(1) = s0
    re(1) = s1
    if (k == 0) then
       finer_own = t%maxlevel > 0
    else
       call stencil_ranges(t, k, c, above, nr_own, rs, re, finer_own)
    end if
    re_own = re(nr_own)
    if (.not. finer_own) then
       ! no finer level: every row of the cell searches the same ranges (less
       ! the particles before it), so room is checked against one bound
       need = range_total(nr_own, rs, re)
       do a = s0, s1
          if (nnz + need > size(rb%idx, kind=i8)) then
             call rb_reserve(rb, nnz, need, info)
             if (info /= ARPY_OK) return
          end if
          rs(1) = a + 1
          call scan_ranges(t%xs, t%rcs, t%perm, t%xs(:, a), t%rcs(a), nr_own, rs, re, rb%idx, nnz)
          rb%off(a + 1) = nnz
       end do
       return
    end if
    do a = s0, s1
       xa = t%xs(:, a)
       ra = t%rcs(a)
       rs(1) = a + 1            ! range 1: the rest of the cell (and what follows it)
       nr = nr_own
       re(nr) = re_own          ! a finer range may have been joined to it
       ! finer levels: the full stencil, while the level above holds finer particles
       finer = finer_own
       delta = k
       do while (finer .and. delta < t%maxlevel)
          delta = delta + 1
          call cell_coords(t, xa, delta, cf)
          call stencil_ranges(t, delta, cf, -1_i8, nr, rs, re, finer)
       end do
       call scan_row(t, xa, ra, nr, rs, re, rb, nnz, info)
       if (info /= ARPY_OK) return
       rb%off(a + 1) = nnz
    end do
  end subroutine leaf_pairs

  !> Cross-set list: row i lists the particles q of the tree (0-based particle
  !> indices) with |xq_i - x_q| <= min(rcq_i, rc_q).  Queries may lie outside
  !> the tree's domain.
  subroutine ar_cross_list(t, m, xq, rcq, rb, info)
    type(ar_tree), intent(in) :: t
    integer, intent(in) :: m
    real(dp), intent(in) :: xq(t%d, m), rcq(m)
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    integer, parameter :: MAXR = 1 + 27 * 31
    integer :: i, j, l, nr, rs(MAXR), re(MAXR), root_first, root_last
    integer(i8) :: c(3), nnz
    logical :: found, finer, finer_root
    real(dp) :: xa(3), u

    call rb_init(rb, m, 8_i8 * m, info)
    if (info /= ARPY_OK) return
    nnz = 0
    ! level 0: every level-0 particle (their cutoffs may exceed the domain)
    call ar_lookup(t, 1_i8, found, root_first, root_last, finer_root)
    do i = 1, m
       xa = 0.0_dp
       xa(1:t%d) = xq(:, i)
       nr = 1
       rs(1) = root_first        ! (set per query: later ranges may be joined to it)
       re(1) = root_last
       finer = finer_root
       j = 0
       do while (finer .and. j < t%maxlevel)
          j = j + 1
          ! unclamped cell coordinates: the query may lie outside the cube
          c = 0
          do l = 1, t%d
             u = min(max((xa(l) - t%lo(l)) / t%dm, -2.0_dp), 3.0_dp)
             c(l) = floor(u * pow2(j), i8)
          end do
          call stencil_ranges(t, j, c, -1_i8, nr, rs, re, finer)
       end do
       call scan_row(t, xa, rcq(i), nr, rs, re, rb, nnz, info)
       if (info /= ARPY_OK) return
       rb%off(i + 1) = nnz
    end do
    rb%nnz = nnz
  end subroutine ar_cross_list

end module arpy_arcells
