!> The f2py boundary of the arpy core, DC-PSE: the kernel weights of operators at collocation points.
!>
!> Flat external (non-module) routines with explicit-shape arguments and an `info` status code, as
!> f2py calls them; their signatures are declared for f2py in _core.pyf (the contract with
!> Python): keep the two in step.

!> DC-PSE kernel weights of nops operators at ncol collocation points, one
!> Cholesky factorisation per point (see arpy_dcpse).  Sources carry
!> positions src_x and, for the interpolating kernel, spline radii a_src;
!> collocation points carry positions col_x and core sizes col_eps.
!> off/idx: CSR lists of each collocation point's sources (0-based).
!> form: FORM_A (off-particle) or FORM_B (at the source particles).
subroutine arpy_dcpse(d, nsrc, src_x, a_src, ncol, col_x, col_eps, nnz, off, idx, m, c, form, &
     nops, opkind, alpha, max_cond, data, diag, nnb, rcond, status, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_OPERATOR
  use arpy_checks, only: check_particles, check_csr
  use arpy_dcpse, only: dcpse_assemble, OP_DERIV, OP_LAPLACIAN, OP_INTERP, DC_OK, FORM_A, FORM_B
  implicit none
  integer, intent(in) :: d, nsrc, ncol, m, form, nops
  integer(i8), intent(in) :: nnz
  real(dp), intent(in) :: src_x(d, nsrc), a_src(nsrc), col_x(d, ncol), col_eps(ncol), c, max_cond
  integer(i8), intent(in) :: off(ncol + 1)
  integer, intent(in) :: idx(nnz), opkind(nops), alpha(d, nops)
  real(dp), intent(out) :: data(nnz, nops), diag(ncol, nops), rcond(ncol)
  integer, intent(out) :: nnb(ncol), status(ncol), info, bad
  integer :: i
  data = 0.0_dp
  diag = 0.0_dp
  rcond = 0.0_dp
  nnb = 0
  status = DC_OK
  call check_particles(d, nsrc, src_x, a_src, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  call check_particles(d, ncol, col_x, col_eps, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  call check_csr(ncol, nsrc, nnz, off, idx, info, bad)
  if (info /= ARPY_OK) return
  if (m < 1 .or. (form /= FORM_A .and. form /= FORM_B) .or. .not. (c > 0.0_dp) .or. .not. (max_cond > 1.0_dp)) then
     info = ARPY_ERR_OPERATOR
     return
  end if
  do i = 1, nops
     select case (opkind(i))
     case (OP_DERIV)
        if (any(alpha(:, i) < 0) .or. sum(alpha(:, i)) >= m .or. (form == FORM_B .and. sum(alpha(:, i)) == 0)) then
           info = ARPY_ERR_OPERATOR
           return
        end if
     case (OP_LAPLACIAN)
        if (m < 3) then
           info = ARPY_ERR_OPERATOR
           return
        end if
     case (OP_INTERP)
        if (form /= FORM_A) then
           info = ARPY_ERR_OPERATOR
           return
        end if
     case default
        info = ARPY_ERR_OPERATOR
        return
     end select
  end do
  call dcpse_assemble(d, nsrc, src_x, ncol, col_x, col_eps, nnz, off, idx, m, c, form, &
       nops, opkind, alpha, a_src, max_cond, data, diag, nnb, rcond, status, info)
end subroutine arpy_dcpse
