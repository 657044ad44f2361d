!> Handles for AR trees that Python keeps between calls (arpy.ARCellList).
!> A handle is a positive integer; freed slots are reused.
module arpy_registry
  use arpy_kinds, only: ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_NO_RESULT, ARPY_ERR_DIM
  use arpy_artree, only: ar_tree
  implicit none
  private

  type(ar_tree), allocatable, target, save :: trees(:)
  logical, allocatable, save :: used(:)

  public :: registry_new, registry_get, registry_free

contains

  !> Reserve a handle.
  subroutine registry_new(handle, info)
    integer, intent(out) :: handle
    integer, intent(out) :: info
    type(ar_tree), allocatable :: tmp(:)
    logical, allocatable :: utmp(:)
    integer :: h, nold, stat
    info = ARPY_OK
    if (.not. allocated(trees)) then
       allocate(trees(4), used(4), stat=stat)
       if (stat /= 0) then
          info = ARPY_ERR_ALLOC
          return
       end if
       used = .false.
    end if
    do h = 1, size(trees)
       if (.not. used(h)) then
          used(h) = .true.
          handle = h
          return
       end if
    end do
    nold = size(trees)
    allocate(tmp(2 * nold), utmp(2 * nold), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    utmp = .false.
    utmp(1:nold) = used
    tmp(1:nold) = trees
    call move_alloc(tmp, trees)
    call move_alloc(utmp, used)
    used(nold + 1) = .true.
    handle = nold + 1
  end subroutine registry_new

  !> Pointer to the tree of a handle (null if the handle is not in use).
  !> With d: also check that the tree has that dimension (ARPY_ERR_DIM).
  subroutine registry_get(handle, t, info, d)
    integer, intent(in) :: handle
    type(ar_tree), pointer, intent(out) :: t
    integer, intent(out) :: info
    integer, intent(in), optional :: d
    info = ARPY_OK
    t => null()
    if (.not. allocated(trees)) then
       info = ARPY_ERR_NO_RESULT
    else if (handle < 1 .or. handle > size(trees)) then
       info = ARPY_ERR_NO_RESULT
    else if (.not. used(handle)) then
       info = ARPY_ERR_NO_RESULT
    else
       t => trees(handle)
       if (present(d)) then
          if (d /= t%d) info = ARPY_ERR_DIM
       end if
    end if
  end subroutine registry_get

  !> Release a handle and the memory of its tree.
  subroutine registry_free(handle)
    integer, intent(in) :: handle
    type(ar_tree) :: empty
    if (.not. allocated(trees)) return
    if (handle < 1 .or. handle > size(trees)) return
    trees(handle) = empty
    used(handle) = .false.
  end subroutine registry_free

end module arpy_registry
