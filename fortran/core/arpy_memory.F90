!> Large work arrays on huge pages (Linux, where meson defines ARPY_MADVISE; elsewhere nothing happens).
!>
!> A fresh array of many megabytes costs one page fault per 4 KiB page the first time it is
!> written: a neighbour list of 1e6 particles touches about 15,000 such pages, and the faults
!> took about a third of its time.  advise_large asks the kernel (madvise, MADV_HUGEPAGE) to back
!> the 2 MiB-aligned part of an array of LARGE_BYTES or more with transparent huge pages, so that
!> part faults 512 times less often.  It is advice only: the kernel may ignore it (huge pages
!> "never", none free), and no value changes.  The advice is given right after the allocation,
!> before the array is written.  set_huge_pages(.false.) turns it off (arpy.set_huge_pages).
module arpy_memory
  use, intrinsic :: iso_c_binding, only: c_ptr, c_loc, c_size_t, c_int, c_intptr_t
  use arpy_kinds, only: dp, i8
  implicit none
  private

  public :: advise_large, set_huge_pages, huge_pages_on

  !> Arrays smaller than this are left alone (they rarely span a whole aligned 2 MiB page).
  integer(i8), parameter :: LARGE_BYTES = 4194304_i8
  integer(c_intptr_t), parameter :: HUGE_PAGE = 2097152_c_intptr_t
  !> Linux's MADV_HUGEPAGE
  integer(c_int), parameter :: MADV_HUGEPAGE = 14_c_int

  logical, save :: enabled = .true.

#ifdef ARPY_MADVISE
  interface
     function c_madvise(addr, length, advice) bind(C, name="madvise") result(r)
       import :: c_ptr, c_size_t, c_int
       type(c_ptr), value :: addr
       integer(c_size_t), value :: length
       integer(c_int), value :: advice
       integer(c_int) :: r
     end function c_madvise
  end interface
#endif

  !> Advise huge pages for a contiguous array (rank 1 or 2; real(dp), default or i8 integers).
  interface advise_large
     module procedure advise_r1, advise_r2, advise_i1, advise_i2, advise_l1
  end interface advise_large

contains

  !> Turn the advice on or off for later allocations.
  subroutine set_huge_pages(on)
    logical, intent(in) :: on
    enabled = on
  end subroutine set_huge_pages

  !> Whether the advice is on.
  logical function huge_pages_on()
    huge_pages_on = enabled
  end function huge_pages_on

  !> The advice for nbytes from address p: the whole 2 MiB pages inside them.
  subroutine advise_bytes(p, nbytes)
    type(c_ptr), intent(in) :: p
    integer(i8), intent(in) :: nbytes
    integer(c_intptr_t) :: a0, a1
    integer(c_int) :: r
    if (.not. enabled .or. nbytes < LARGE_BYTES) return
#ifdef ARPY_MADVISE
    a0 = transfer(p, a0)
    a1 = a0 + int(nbytes, c_intptr_t)
    a0 = ((a0 + HUGE_PAGE - 1) / HUGE_PAGE) * HUGE_PAGE
    a1 = (a1 / HUGE_PAGE) * HUGE_PAGE
    if (a1 <= a0) return
    r = c_madvise(transfer(a0, p), int(a1 - a0, c_size_t), MADV_HUGEPAGE)   ! (advice: r unused)
#else
    a0 = transfer(p, a0)       ! (no huge-page advice on this system)
    a1 = 0
    r = 0
#endif
  end subroutine advise_bytes

  subroutine advise_r1(a)
    real(dp), intent(in), target, contiguous :: a(:)
    if (size(a) > 0) call advise_bytes(c_loc(a), 8_i8 * size(a, kind=i8))
  end subroutine advise_r1

  subroutine advise_r2(a)
    real(dp), intent(in), target, contiguous :: a(:, :)
    if (size(a) > 0) call advise_bytes(c_loc(a), 8_i8 * size(a, kind=i8))
  end subroutine advise_r2

  subroutine advise_i1(a)
    integer, intent(in), target, contiguous :: a(:)
    if (size(a) > 0) call advise_bytes(c_loc(a), 4_i8 * size(a, kind=i8))
  end subroutine advise_i1

  subroutine advise_i2(a)
    integer, intent(in), target, contiguous :: a(:, :)
    if (size(a) > 0) call advise_bytes(c_loc(a), 4_i8 * size(a, kind=i8))
  end subroutine advise_i2

  subroutine advise_l1(a)
    integer(i8), intent(in), target, contiguous :: a(:)
    if (size(a) > 0) call advise_bytes(c_loc(a), 8_i8 * size(a, kind=i8))
  end subroutine advise_l1

end module arpy_memory
