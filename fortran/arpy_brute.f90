!> Brute-force neighbour search over all pairs: the O(n^2) reference baseline.
module arpy_brute
  use arpy_kinds, only: dp, i8, ARPY_OK
  use arpy_csr, only: row_builder, rb_init, rb_push
  implicit none
  private

  public :: brute_half

contains

  !> Symmetric list by brute force: row p holds every q > p with
  !> |x_p - x_q| <= min(rc_p, rc_q) + skin (0-based indices).
  subroutine brute_half(d, n, x, rc, skin, rb, info)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), rc(n), skin
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    integer :: p, q, k
    real(dp) :: r2, rm, dx
    call rb_init(rb, n, 8_i8 * n, info)
    if (info /= ARPY_OK) return
    do p = 1, n
       do q = p + 1, n
          r2 = 0.0_dp
          do k = 1, d
             dx = x(k, q) - x(k, p)
             r2 = r2 + dx * dx
          end do
          rm = min(rc(p), rc(q)) + skin
          if (r2 <= rm * rm) then
             call rb_push(rb, q - 1, info)
             if (info /= ARPY_OK) return
          end if
       end do
       rb%off(p + 1) = rb%nnz
    end do
  end subroutine brute_half

end module arpy_brute
