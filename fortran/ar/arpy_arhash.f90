!> The cell table of the AR tree: packed cell entries and the open-addressing
!> hash table J -> entry.
!>
!> An entry packs a cell's own-level slot range [first, last] (first > last:
!> none) and its finer flag (set: the cell's region holds particles of finer
!> levels) into one int64: first + last * 2**31 + finer * 2**62.  The hash
!> keeps key and entry side by side, tab(1, s) = J (or NOKEY) and
!> tab(2, s) = entry: one 16-byte slot, so a probe touches one cache line.
!>
!> A presence bitmap stands in front of the table for the keys below jbits:
!> bit J is set when J is in the table.  Most lookups of a list's stencils
!> ask for empty cells of a sparse level (a level is hashed because it has
!> many more cells than particles); the bitmap, at PRESENCE_BITS bits per
!> key the table was sized for, answers them from a few hundred kilobytes
!> instead of a probe into a table of many megabytes (measured: see
!> benchmarks/results/rules.md).  It changes no answer, only its cost.
module arpy_arhash
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC
  implicit none
  private

  integer(i8), parameter, public :: NOKEY = -1_i8       !< key of an empty hash slot
  integer(i8), parameter, public :: EMPTY_ENTRY = 1_i8  !< entry of a cell without own slots (first = 1, last = 0)
  integer(i8), parameter, public :: NO_ENTRY = 0_i8     !< entry of an absent cell in a dense table
  integer, parameter, public :: FINER_BIT = 62          !< bit of the finer flag in an entry
  integer(i8), parameter :: LOW31 = 2147483647_i8
  integer, parameter :: HBLOCK(2:3) = [4, 6]             !< log2 of the hash block (2 levels of cells)
  integer(i8), parameter :: PRESENCE_BITS = 64_i8        !< bits of the presence bitmap per key of the capacity

  type, public :: ar_hash
     integer :: nkey = 0                      !< keys in the table
     integer(i8) :: mask = -1                 !< slots - 1 (-1: no table yet)
     integer :: bits = 0                      !< log2 of the number of slots
     integer :: block = 0                     !< log2 of the block size (HBLOCK)
     integer(i8), allocatable :: tab(:, :)    !< (2, 0:mask): key, entry
     integer(i8) :: jbits = 0                 !< keys below this have a presence bit
     integer(i8), allocatable :: present(:)   !< (0:(jbits - 1) / 64): bit J of the bitmap is bit mod(J, 64) of word J / 64
  end type ar_hash

  public :: entry_pack, entry_first, entry_last, entry_finer
  public :: hash_init, hash_insert, hash_find, hash_flag_finer

contains

  !> The entry of own-level slot range first .. last, without finer flag.
  elemental function entry_pack(first, last) result(v)
    integer(i8), intent(in) :: first, last
    integer(i8) :: v
    v = first + ishft(last, 31)
  end function entry_pack

  !> Slot range [first, last] and finer flag of an entry.
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

  !> Slot of a key.  Keys are cut into blocks of 2**block consecutive J
  !> (a 4 x 4 block of cells in 2D, 4 x 4 x 4 in 3D): the block is placed by
  !> Fibonacci hashing (top bits of block * 2**64/phi, wrapping: the core is
  !> compiled with -fwrapv), the key's position inside the block is kept.
  !> Neighbouring cells thus share cache lines, while sparse or strided key
  !> sets still spread evenly over the table.
  pure function hash_slot(h, key) result(s)
    type(ar_hash), intent(in) :: h
    integer(i8), intent(in) :: key
    integer(i8) :: s
    integer :: hb
    hb = h%block
    s = ishft(ishft(key, -hb) * (-7046029254386353131_i8), -(64 - h%bits + hb))
    s = ior(ishft(s, hb), iand(key, ishft(1_i8, hb) - 1_i8))
  end function hash_slot

  !> An empty table of the cells of a d-dimensional tree for about
  !> `capacity` keys.
  subroutine hash_init(h, d, capacity, info)
    type(ar_hash), intent(inout) :: h
    integer, intent(in) :: d
    integer(i8), intent(in) :: capacity
    integer, intent(out) :: info
    integer :: stat
    h%block = HBLOCK(d)
    call hash_alloc(h, capacity, info)
    if (info /= ARPY_OK) return
    h%jbits = 64_i8 * ((PRESENCE_BITS * max(capacity, 1_i8) + 63_i8) / 64_i8)
    if (allocated(h%present)) deallocate(h%present)
    allocate(h%present(0:h%jbits / 64_i8 - 1_i8), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    h%present = 0
  end subroutine hash_init

  !> Empty slots for about `capacity` keys (the table grows at load 0.6).
  subroutine hash_alloc(h, capacity, info)
    type(ar_hash), intent(inout) :: h
    integer(i8), intent(in) :: capacity
    integer, intent(out) :: info
    integer :: stat
    info = ARPY_OK
    h%bits = h%block + 2
    do while (0.6_dp * real(ishft(1_i8, h%bits), dp) < real(capacity, dp))
       h%bits = h%bits + 1
    end do
    h%mask = ishft(1_i8, h%bits) - 1_i8
    if (allocated(h%tab)) deallocate(h%tab)
    allocate(h%tab(2, 0:h%mask), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    h%tab(1, :) = NOKEY
    h%nkey = 0
  end subroutine hash_alloc

  !> Insert key (or find it); returns its slot.  New entries are
  !> EMPTY_ENTRY.
  recursive subroutine hash_insert(h, key, slot, info)
    type(ar_hash), intent(inout) :: h
    integer(i8), intent(in) :: key
    integer(i8), intent(out) :: slot
    integer, intent(out) :: info
    integer(i8), allocatable :: old(:, :)
    integer(i8) :: s, s2
    info = ARPY_OK
    if (real(h%nkey + 1, dp) > 0.6_dp * real(h%mask + 1, dp)) then
       call move_alloc(h%tab, old)
       call hash_alloc(h, 2_i8 * (h%nkey + 1), info)
       if (info /= ARPY_OK) return
       do s = 0, size(old, 2, kind=i8) - 1
          if (old(1, s) == NOKEY) cycle
          call hash_insert(h, old(1, s), s2, info)
          if (info /= ARPY_OK) return
          h%tab(2, s2) = old(2, s)
       end do
    end if
    slot = hash_probe(h, key)
    if (h%tab(1, slot) == key) return
    h%tab(1, slot) = key
    h%tab(2, slot) = EMPTY_ENTRY
    h%nkey = h%nkey + 1
    if (key >= 0 .and. key < h%jbits) h%present(ishft(key, -6)) = ibset(h%present(ishft(key, -6)), int(iand(key, 63_i8)))
  end subroutine hash_insert

  !> Set the finer flag of the entry in slot s.
  subroutine hash_flag_finer(h, s)
    type(ar_hash), intent(inout) :: h
    integer(i8), intent(in) :: s
    h%tab(2, s) = ibset(h%tab(2, s), FINER_BIT)
  end subroutine hash_flag_finer

  !> Slot of key, or -1 if the table does not hold it.
  pure function hash_find(h, key) result(slot)
    type(ar_hash), intent(in) :: h
    integer(i8), intent(in) :: key
    integer(i8) :: slot
    slot = -1
    if (h%mask < 0) return
    if (key >= 0 .and. key < h%jbits) then
       if (.not. btest(h%present(ishft(key, -6)), int(iand(key, 63_i8)))) return
    end if
    slot = hash_probe(h, key)
    if (h%tab(1, slot) /= key) slot = -1
  end function hash_find

  !> Linear probing from the slot of key: the slot that holds key, or else
  !> the empty slot where it belongs.
  pure function hash_probe(h, key) result(slot)
    type(ar_hash), intent(in) :: h
    integer(i8), intent(in) :: key
    integer(i8) :: slot
    slot = hash_slot(h, key)
    do
       if (h%tab(1, slot) == key .or. h%tab(1, slot) == NOKEY) return
       slot = iand(slot + 1, h%mask)
    end do
  end function hash_probe

end module arpy_arhash
