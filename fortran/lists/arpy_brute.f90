!> Brute-force neighbour search over all pairs: the O(n^2) reference baseline.
module arpy_brute
  use arpy_kinds, only: dp, i8, ARPY_OK, RULE_MIN
  use arpy_csr, only: row_builder, rb_init, rb_push, rb_reserve
  use arpy_pairs, only: pair_reach
  implicit none
  private

  public :: brute_half, brute_cross

contains

  !> Symmetric list by brute force: row p holds every q > p with
  !> |x_p - x_q| <= pair_reach(rule, rc_p, rc_q, skin) (0-based indices; rule: RULE_MIN if absent).
  subroutine brute_half(d, n, x, rc, skin, rb, info, rule)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), rc(n), skin
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    integer, intent(in), optional :: rule
    integer :: p, q, k, rl
    real(dp) :: r2, rm, dx
    rl = RULE_MIN
    if (present(rule)) rl = rule
    call rb_init(rb, n, 8_i8 * n, info)
    if (info /= ARPY_OK) return
    do p = 1, n
       do q = p + 1, n
          r2 = 0.0_dp
          do k = 1, d
             dx = x(k, q) - x(k, p)
             r2 = r2 + dx * dx
          end do
          rm = pair_reach(rl, rc(p), rc(q), skin)
          if (r2 <= rm * rm) then
             call rb_push(rb, q - 1, info)
             if (info /= ARPY_OK) return
          end if
       end do
       rb%off(p + 1) = rb%nnz
    end do
  end subroutine brute_half

  !> Cross list by brute force: row i holds every reference particle b, in increasing order, with
  !> |x_b - x_i|**2 <= pair_reach(rule, rcq_i, rcr_b, 0)**2 (rule: RULE_MIN if absent), the squares
  !> summed axis by axis as the cell lists' scan sums them (arpy_celllist.scan_ranges), so the rows
  !> are theirs bit for bit (0-based indices).  For few pairs (m n small), where building a tree
  !> would cost more.
  subroutine brute_cross(d, m, xq, rcq, n, xr, rcr, rb, info, rule)
    integer, intent(in) :: d, m, n
    real(dp), intent(in) :: xq(d, m), rcq(m), xr(d, n), rcr(n)
    type(row_builder), intent(inout) :: rb
    integer, intent(out) :: info
    integer, intent(in), optional :: rule
    integer :: i, b, k, rl
    integer(i8) :: nnz
    real(dp) :: r2, rm, dx
    rl = RULE_MIN
    if (present(rule)) rl = rule
    call rb_init(rb, m, 8_i8 * m, info)
    if (info /= ARPY_OK) return
    nnz = 0
    do i = 1, m
       call rb_reserve(rb, nnz, int(n, i8), info)       ! room for the whole row: accept branch-free
       if (info /= ARPY_OK) return
       do b = 1, n
          r2 = 0.0_dp
          do k = 1, d
             dx = xr(k, b) - xq(k, i)
             r2 = r2 + dx * dx
          end do
          rm = pair_reach(rl, rcq(i), rcr(b), 0.0_dp)
          rb%idx(nnz + 1) = b - 1
          nnz = nnz + merge(1_i8, 0_i8, r2 <= rm * rm)
       end do
       rb%off(i + 1) = nnz
    end do
    rb%nnz = nnz
  end subroutine brute_cross

end module arpy_brute
