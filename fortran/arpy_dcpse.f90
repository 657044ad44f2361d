!> DC-PSE operators (Reboux, Schrader, Sbalzarini, JCP 2012, Appendix A and B):
!> kernel weights of derivatives, the Laplacian and the interpolating kernel
!> on irregular particles of varying size, one LAPACK Cholesky factorisation
!> per collocation point for all operators.
!>
!> Per collocation point p (position x_p, core size eps_p) with source
!> neighbours q:
!>   z_q = (x_q - x_p) / eps_p                       scaled offsets
!>   w_q = exp(-c**2 |z_q|**2 / 2)                   weights (the kernel carries w**2)
!>   V(q, k) = z_q**e_k                              monomials of degree < m
!>   A = (W V)^T (W V)                               moment matrix, Cholesky (dpotrf)
!>   A c_i = b_i                                     one solve per operator (dpotrs)
!>   data(q, i) = eps_p**(-|alpha|) w_q**2 (V c_i)_q
!> Right-hand sides: derivative alpha: b = alpha! at monomial alpha (Eq. A.4);
!> Laplacian: b = 2 at every 2 e_j (Eq. A.6); interpolating kernel (form a
!> only, Eqs. A.9-A.11): b = e_1 - V^T s with s_q = Q(|x_p - x_q| / a_q) the
!> quartic spline Q(r) = 1 - 6r**2 + 8r**3 - 3r**4 (r <= 1), and
!> data = w**2 (V c) + s (Kronecker property: exact at source particles).
!>
!> Two forms.  Form a (off-particle, vanishing zeroth moment, Eqs. A.5/A.7):
!> (L f)_p = sum_q data_q f_q.  Form b (at source particles, Eq. A.8): the
!> constant monomial is dropped (free zeroth moment) and
!> (L f)_p = sum_q data_q (f_q - f_p): diag_p = -sum_q data_q.
!>
!> Status per point: DC_OK, DC_FEW (fewer usable neighbours than unknowns),
!> DC_SINGULAR (dpotrf failed), DC_ILLCOND (condition number of A above
!> max_cond; the figure is ||A||_1 times an upper bound of ||A^-1||_1 formed
!> from the inverse Cholesky factor: never below the true 1-norm condition
!> number, at most a factor n above it, and much cheaper than LAPACK's
!> dpocon for these small systems).  Weights of a failed point are zero.
module arpy_dcpse
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC
  implicit none
  private

  integer, parameter, public :: DC_OK = 0, DC_FEW = 1, DC_SINGULAR = 2, DC_ILLCOND = 3
  !> operator kinds
  integer, parameter, public :: OP_DERIV = 0, OP_LAPLACIAN = 1, OP_INTERP = 2
  !> operator forms: a (off-particle) and b (at the source particles)
  integer, parameter, public :: FORM_A = 0, FORM_B = 1

  public :: dcpse_nmono, dcpse_monomials, dcpse_assemble

  external :: dpotrf, dpotrs

contains

  !> Number of monomials of degree < m in d variables: binomial(m - 1 + d, d).
  pure function dcpse_nmono(d, m) result(nm)
    integer, intent(in) :: d, m
    integer :: nm, i
    nm = 1
    do i = 1, d
       nm = nm * (m - 1 + i) / i
    end do
  end function dcpse_nmono

  !> Exponents of the monomials of degree < m, exps(1:d, k): by degree, and
  !> within a degree lexicographically descending (x**2, xy, y**2, ...).
  pure subroutine dcpse_monomials(d, m, exps)
    integer, intent(in) :: d, m
    integer, intent(out) :: exps(:, :)
    integer :: g, k, v(0:m), j, i
    k = 0
    do g = 0, m - 1
       ! nondecreasing sequences v(1..g) of variable indices 1..d, lexicographic
       v(1:g) = 1
       do
          k = k + 1
          exps(1:d, k) = 0
          do j = 1, g
             exps(v(j), k) = exps(v(j), k) + 1
          end do
          ! next sequence
          i = g
          do while (i >= 1)
             if (v(i) < d) exit
             i = i - 1
          end do
          if (i < 1) exit
          v(i) = v(i) + 1
          v(i + 1:g) = v(i)
       end do
    end do
  end subroutine dcpse_monomials

  !> Upper bound of the 1-norm of A^-1 for A = L L^T (L lower triangular,
  !> the lower triangle of l): ||A^-1||_1 <= ||L^-T||_1 ||L^-1||_1 =
  !> ||L^-1||_inf ||L^-1||_1, with L^-1 formed explicitly (n**3/6 products).
  !> At most a factor n above the true value; never below it.
  function inverse_norm1(n, l, minv) result(est)
    integer, intent(in) :: n
    real(dp), intent(in) :: l(n, n)
    real(dp), intent(out) :: minv(n, n)
    real(dp) :: est, t
    integer :: i, j, k
    minv = 0.0_dp
    do j = 1, n                              ! column j of L^-1: L m = e_j
       minv(j, j) = 1.0_dp / l(j, j)
       do k = j, n - 1                        ! forward substitution, column-oriented
          t = minv(k, j)
          do i = k + 1, n
             minv(i, j) = minv(i, j) - l(i, k) * t
          end do
          minv(k + 1, j) = minv(k + 1, j) / l(k + 1, k + 1)
       end do
    end do
    est = maxval(sum(abs(minv), dim=1)) * maxval(sum(abs(minv), dim=2))
  end function inverse_norm1

  !> Kernel weights of nops operators at ncol collocation points.
  !>   off(ncol+1), idx(nnz): CSR neighbour lists, 0-based, into the sources
  !>   form: FORM_A (off-particle) or FORM_B (at the source particles)
  !>   opkind(nops): OP_DERIV (multi-index alpha(1:d, i)), OP_LAPLACIAN, OP_INTERP
  !>   a_src(nsrc): quartic-spline radii of the sources (OP_INTERP only)
  !> Outputs: data(nnz, nops), diag(ncol, nops) (form b), nnb(ncol) usable
  !> neighbours, rcond(ncol) reciprocal condition estimate of A, status(ncol).
  subroutine dcpse_assemble(d, nsrc, src_x, ncol, col_x, col_eps, nnz, off, idx, m, c, form, &
       nops, opkind, alpha, a_src, max_cond, data, diag, nnb, rcond, status, ierr)
    integer, intent(in) :: d, nsrc, ncol, m, form, nops
    integer(i8), intent(in) :: nnz
    real(dp), intent(in) :: src_x(d, nsrc), col_x(d, ncol), col_eps(ncol), c, a_src(nsrc)
    real(dp), intent(in) :: max_cond
    integer(i8), intent(in) :: off(ncol + 1)
    integer, intent(in) :: idx(nnz), opkind(nops), alpha(d, nops)
    real(dp), intent(out) :: data(nnz, nops), diag(ncol, nops), rcond(ncol)
    integer, intent(out) :: nnb(ncol), status(ncol)
    integer, intent(out) :: ierr                 !< ARPY_OK or ARPY_ERR_ALLOC

    integer :: stat, nall, n0, nb, p, q, k, j, i, info, kmax, nk, deg, ord(nops)
    integer, allocatable :: exps(:, :), parent(:), var(:)
    real(dp), allocatable :: v(:, :), b(:, :), a(:, :), rhs(:, :), rhs0(:, :), s(:), w2(:), work(:, :)
    real(dp) :: z(3), r2, eps, anorm, fac, scalef(nops), dist
    integer(i8) :: k0

    nall = dcpse_nmono(d, m)
    n0 = merge(2, 1, form == FORM_B)     ! first basis function used (form b: no constant)
    nb = nall - n0 + 1                   ! unknowns per point
    ierr = ARPY_OK
    data = 0.0_dp
    diag = 0.0_dp
    rcond = 0.0_dp
    nnb = 0
    status = 0
    allocate(exps(d, nall), parent(nall), var(nall), stat=stat)
    if (stat /= 0) then
       ierr = ARPY_ERR_ALLOC
       return
    end if
    call dcpse_monomials(d, m, exps)
    ! monomial k = monomial parent(k) times z(var(k)): one product per entry
    parent(1) = 0
    var(1) = 0
    do k = 2, nall
       var(k) = findloc(exps(:, k) > 0, .true., dim=1)
       do j = 1, k - 1
          if (all(exps(:, j) + merge(1, 0, [(i == var(k), i = 1, d)]) == exps(:, k))) then
             parent(k) = j
             exit
          end if
       end do
    end do
    kmax = 1
    do p = 1, ncol
       kmax = max(kmax, int(off(p + 1) - off(p)))
    end do
    ! v(k, q): monomial k at neighbour q (one column per neighbour)
    allocate(v(nall, kmax), b(kmax, nb), a(nb, nb), rhs(nb, nops), rhs0(nb, nops), s(kmax), w2(kmax), &
         work(nb, nb), stat=stat)
    if (stat /= 0) then
       ierr = ARPY_ERR_ALLOC
       return
    end if

    ! the derivative order of each operator (for the eps**(-|alpha|) factor)
    do i = 1, nops
       select case (opkind(i))
       case (OP_DERIV)
          ord(i) = sum(alpha(:, i))
       case (OP_LAPLACIAN)
          ord(i) = 2
       case default
          ord(i) = 0
       end select
    end do

    ! right-hand sides of the derivatives (Eq. A.4: alpha! at monomial alpha)
    ! and of the Laplacian (Eq. A.6: 2 at every 2 e_j)
    rhs0 = 0.0_dp
    do i = 1, nops
       do k = n0, nall
          select case (opkind(i))
          case (OP_DERIV)
             if (all(exps(:, k) == alpha(:, i))) then
                fac = 1.0_dp
                do j = 1, d
                   do deg = 2, alpha(j, i)
                      fac = fac * deg
                   end do
                end do
                rhs0(k - n0 + 1, i) = fac
             end if
          case (OP_LAPLACIAN)
             if (sum(exps(:, k)) == 2 .and. maxval(exps(:, k)) == 2) rhs0(k - n0 + 1, i) = 2.0_dp
          end select
       end do
    end do

    do p = 1, ncol
       k0 = off(p)
       nk = int(off(p + 1) - k0)
       eps = col_eps(p)
       ! scaled Vandermonde matrix, weights, usable neighbours
       nnb(p) = 0
       do q = 1, nk
          z = 0.0_dp
          z(1:d) = (src_x(:, idx(k0 + q) + 1) - col_x(:, p)) / eps
          r2 = z(1) * z(1) + z(2) * z(2) + z(3) * z(3)
          ! a coincident source adds nothing to the moments of form b (also where
          ! r2 underflows: such a stencil is then reported singular, not short)
          if (form == FORM_A .or. any(src_x(:, idx(k0 + q) + 1) /= col_x(:, p))) nnb(p) = nnb(p) + 1
          fac = exp(-0.5_dp * c * c * r2)      ! w_q; the kernel carries w_q**2
          w2(q) = fac * fac
          v(1, q) = 1.0_dp
          do k = 2, nall
             v(k, q) = v(parent(k), q) * z(var(k))
          end do
          b(q, 1:nb) = fac * v(n0:nall, q)
       end do
       if (nnb(p) < nb) then
          status(p) = DC_FEW
          cycle
       end if
       ! A = B^T B (lower triangle), its 1-norm, Cholesky, condition estimate
       do j = 1, nb
          do i = j, nb
             a(i, j) = dot_product(b(1:nk, i), b(1:nk, j))
             a(j, i) = a(i, j)
          end do
       end do
       anorm = 0.0_dp
       do j = 1, nb
          anorm = max(anorm, sum(abs(a(:, j))))
       end do
       call dpotrf('L', nb, a, nb, info)
       if (info /= 0) then
          status(p) = DC_SINGULAR
          cycle
       end if
       rcond(p) = 1.0_dp / (anorm * inverse_norm1(nb, a, work))
       if (rcond(p) * max_cond < 1.0_dp) then
          status(p) = DC_ILLCOND
          cycle
       end if
       status(p) = DC_OK
       ! right-hand sides: the same for every point, but for the interpolating kernel
       rhs = rhs0
       do i = 1, nops
          scalef(i) = eps**(-ord(i))
          if (opkind(i) /= OP_INTERP) cycle
          ! s_q = Q(|x_p - x_q| / a_q); b = e_1 - V^T s
          do q = 1, nk
             dist = sqrt(sum((src_x(:, idx(k0 + q) + 1) - col_x(:, p))**2)) / a_src(idx(k0 + q) + 1)
             s(q) = 0.0_dp
             if (dist <= 1.0_dp) s(q) = 1.0_dp - dist * dist * (6.0_dp - dist * (8.0_dp - 3.0_dp * dist))
          end do
          do k = n0, nall
             rhs(k - n0 + 1, i) = -dot_product(v(k, 1:nk), s(1:nk))
          end do
          rhs(1, i) = rhs(1, i) + 1.0_dp
       end do
       call dpotrs('L', nb, nops, a, nb, rhs, nb, info)
       ! weights: w**2 (V c), scaled; interpolation adds the spline
       do i = 1, nops
          do q = 1, nk
             data(k0 + q, i) = scalef(i) * w2(q) * dot_product(v(n0:nall, q), rhs(:, i))
             if (opkind(i) == OP_INTERP) data(k0 + q, i) = data(k0 + q, i) + s(q)
          end do
          if (form == FORM_B) diag(p, i) = -sum(data(k0 + 1:k0 + nk, i))
       end do
    end do
  end subroutine dcpse_assemble

end module arpy_dcpse
