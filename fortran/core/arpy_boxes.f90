!> Which box of a decomposition holds each point (arpy.distributed.Decomposition.locate).
module arpy_boxes
  use arpy_kinds, only: dp, i8
  use arpy_threads, only: team_size, MIN_PARALLEL_ROWS
  implicit none
  private

  public :: box_owners

contains

  !> owner(p) = ids(b) of the first of the m boxes b holding x(:, p), -1 if none: lo(:, b) <= x and,
  !> along each axis, x < hi(k, b), or x <= top(k) where hi(k, b) = top(k) (the upper face of the
  !> decomposed box belongs to the boxes there).  A NaN coordinate lies in no box.  Points in
  !> parallel from MIN_PARALLEL_ROWS; each point's answer is its own, so any thread count gives it.
  subroutine box_owners(d, n, m, x, lo, hi, top, ids, owner)
    integer, intent(in) :: d, n, m
    real(dp), intent(in) :: x(d, n), lo(d, m), hi(d, m), top(d)
    integer(i8), intent(in) :: ids(m)
    integer(i8), intent(out) :: owner(n)
    integer :: p, b, k, nt
    logical :: inside
    nt = team_size()
    if (n < MIN_PARALLEL_ROWS) nt = 1
    !$omp parallel do num_threads(nt) schedule(static) private(b, k, inside)
    do p = 1, n
       owner(p) = -1_i8
       do b = 1, m
          inside = .true.
          do k = 1, d
             if (.not. (x(k, p) >= lo(k, b) .and. &
                  (x(k, p) < hi(k, b) .or. (hi(k, b) == top(k) .and. x(k, p) <= top(k))))) then
                inside = .false.
                exit
             end if
          end do
          if (inside) then
             owner(p) = ids(b)
             exit
          end if
       end do
    end do
    !$omp end parallel do
  end subroutine box_owners

end module arpy_boxes
