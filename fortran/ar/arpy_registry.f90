!> Handles for AR trees that Python keeps between calls (arpy.ARCellList).
!> A handle is a positive integer; freed slots are reused.
module arpy_registry
  use arpy_kinds, only: ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_NO_RESULT, ARPY_ERR_DIM
  use arpy_artree, only: ar_tree
  implicit none
  private

  !> A slot of the registry: the tree of one handle (null: free).  Trees live behind pointers, so
  !> growing the table never moves a tree another call is using.
  type :: slot
     type(ar_tree), pointer :: tree => null()
  end type slot

  !> Calls may come from several threads at once (the GIL is released): the table is touched only
  !> inside the critical section arpy_registry.
  type(slot), allocatable, save :: trees(:)

  public :: registry_new, registry_get, registry_free

contains

  !> Reserve a handle with a new, empty tree.
  subroutine registry_new(handle, info)
    integer, intent(out) :: handle
    integer, intent(out) :: info
    type(ar_tree), pointer :: t
    type(slot), allocatable :: tmp(:)
    integer :: h, stat
    info = ARPY_OK
    handle = 0
    allocate(t, stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    !$omp critical (arpy_registry)
    if (.not. allocated(trees)) allocate(trees(4), stat=stat)
    if (stat == 0) then
       do h = 1, size(trees)
          if (.not. associated(trees(h)%tree)) exit
       end do
       if (h > size(trees)) then
          allocate(tmp(2 * size(trees)), stat=stat)
          if (stat == 0) then
             tmp(1:size(trees)) = trees
             call move_alloc(tmp, trees)
          end if
       end if
       if (stat == 0) then
          trees(h)%tree => t
          handle = h
       end if
    end if
    !$omp end critical (arpy_registry)
    if (stat /= 0) then
       deallocate(t)
       info = ARPY_ERR_ALLOC
    end if
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
    !$omp critical (arpy_registry)
    if (allocated(trees)) then
       if (handle >= 1 .and. handle <= size(trees)) t => trees(handle)%tree
    end if
    !$omp end critical (arpy_registry)
    if (.not. associated(t)) then
       info = ARPY_ERR_NO_RESULT
    else if (present(d)) then
       if (d /= t%d) info = ARPY_ERR_DIM
    end if
  end subroutine registry_get

  !> Release a handle and the memory of its tree.
  subroutine registry_free(handle)
    integer, intent(in) :: handle
    type(ar_tree), pointer :: t
    t => null()
    !$omp critical (arpy_registry)
    if (allocated(trees)) then
       if (handle >= 1 .and. handle <= size(trees)) then
          t => trees(handle)%tree
          trees(handle)%tree => null()
       end if
    end if
    !$omp end critical (arpy_registry)
    if (associated(t)) deallocate(t)
  end subroutine registry_free

end module arpy_registry
