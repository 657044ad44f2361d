!> DC-PSE operators (Reboux, Schrader, Sbalzarini, JCP 2012, Appendix A and B):
!> kernel weights of derivatives, the Laplacian and the interpolating kernel
!> on irregular particles of varying size, one Cholesky factorisation per
!> collocation point for all operators (below MAX_INLINE unknowns here, above
!> it by LAPACK).
!>
!> Per collocation point p (position x_p, core size eps_p) with source
!> neighbours q:
!>   z_q = (x_q - x_p) / eps_p                       scaled offsets
!>   w_q = exp(-c**2 |z_q|**2 / 2)                   weights (the kernel carries w**2)
!>   V(q, k) = z_q**e_k                              monomials of degree < m
!>   A = (W V)^T (W V)                               moment matrix, Cholesky factor
!>   A c_i = b_i                                     one solve per operator
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
!> DC_SINGULAR (the factorization failed), DC_ILLCOND (condition number of A above
!> max_cond; the figure is ||A||_1 times an upper bound of ||A^-1||_1 formed
!> from the inverse Cholesky factor: never below the true 1-norm condition
!> number, at most a factor n above it, and much cheaper than LAPACK's
!> dpocon for these small systems).  Weights of a failed point are zero.
module arpy_dcpse
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC
  use arpy_threads, only: team_size
  implicit none
  private

  integer, parameter, public :: DC_OK = 0, DC_FEW = 1, DC_SINGULAR = 2, DC_ILLCOND = 3
  !> operator kinds
  integer, parameter, public :: OP_DERIV = 0, OP_LAPLACIAN = 1, OP_INTERP = 2
  !> operator forms: a (off-particle) and b (at the source particles)
  integer, parameter, public :: FORM_A = 0, FORM_B = 1

  public :: dcpse_nmono, dcpse_monomials, dcpse_assemble

  external :: dpotrf, dpotrs

  !> Systems of up to this many unknowns (order m <= 10 in 2D, m <= 6 in 3D) are factored and
  !> solved here, larger ones by LAPACK (dpotrf, dpotrs): the sums of
  !> these small systems then run in one fixed order on every processor (LAPACK libraries pick
  !> kernels by CPU, whose sums differ in the last bits), and the threads share no library state
  !> (OpenBLAS takes a lock for the work buffer of every call).
  integer, parameter :: MAX_INLINE = 56

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
  !> At most a factor n above the true value; never below it.  L^-1 is built
  !> row by row, kept transposed (mt(j, i) = (L^-1)(i, j)): entry (i, j) is
  !> -(l(i, j) m(j, j) + ... + l(i, i-1) m(i-1, j)) / l(i, i), subtracted in
  !> that order in a register; the entries of a row are independent sums.
  function inverse_norm1(n, l, mt) result(est)
    integer, intent(in) :: n
    real(dp), intent(in) :: l(n, n)
    real(dp), intent(out) :: mt(n, n)
    real(dp) :: est, s
    integer :: i, j, k
    mt = 0.0_dp
    do i = 1, n
       do j = 1, i - 1
          s = 0.0_dp
          do k = j, i - 1
             s = s - l(i, k) * mt(j, k)
          end do
          mt(j, i) = s / l(i, i)
       end do
       mt(i, i) = 1.0_dp / l(i, i)
    end do
    est = maxval(sum(abs(mt), dim=2)) * maxval(sum(abs(mt), dim=1))
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

    integer :: stat, nall, n0, nb, p, kmax, ord(nops), failed
    integer, allocatable :: exps(:, :), parent(:), var(:)
    real(dp), allocatable :: v(:, :), b(:, :), a(:, :), rhs(:, :), rhs0(:, :), s(:), w2(:), work(:, :)

    nall = dcpse_nmono(d, m)
    n0 = merge(2, 1, form == FORM_B)     ! first basis function used (form b: no constant)
    nb = nall - n0 + 1                   ! unknowns per point
    ierr = ARPY_OK
    rcond = 0.0_dp                       ! (data and diag: each point zeroes its own, in parallel)
    nnb = 0
    status = 0
    kmax = 1
    do p = 1, ncol
       kmax = max(kmax, int(off(p + 1) - off(p)))
    end do
    allocate(exps(d, nall), parent(nall), var(nall), rhs0(nb, nops), stat=stat)
    if (stat /= 0) then
       ierr = ARPY_ERR_ALLOC
       return
    end if
    call dcpse_monomials(d, m, exps)
    call monomial_chain(d, nall, exps, parent, var)
    call operator_rhs(d, nall, n0, nops, opkind, alpha, exps, ord, rhs0)
    ! the points in parallel, each thread with its own workspace; v(k, q): monomial k at neighbour q
    failed = 0
    !$omp parallel num_threads(team_size()) default(shared) private(p, v, b, a, rhs, s, w2, work, stat) &
    !$omp reduction(max: failed)
    allocate(v(nall, kmax), b(kmax, nb), a(nb, nb), rhs(nb, nops), s(kmax), w2(kmax), work(nb, nb), stat=stat)
    if (stat /= 0) failed = 1
    !$omp do schedule(dynamic, 64)
    do p = 1, ncol
       if (stat /= 0) cycle
       call point_weights(d, nsrc, src_x, col_x(:, p), col_eps(p), int(off(p + 1) - off(p)), &
            idx(off(p) + 1:off(p + 1)), c, form, n0, nall, nops, opkind, ord, a_src, max_cond, parent, var, &
            rhs0, v, b, a, rhs, s, w2, work, nnz, off(p), data, ncol, p, diag, nnb(p), rcond(p), status(p))
    end do
    !$omp end do
    if (stat == 0) deallocate(v, b, a, rhs, s, w2, work)
    !$omp end parallel
    if (failed /= 0) ierr = ARPY_ERR_ALLOC
  end subroutine dcpse_assemble

  !> Monomial k = monomial parent(k) times z(var(k)): one product per entry of the Vandermonde matrix.
  subroutine monomial_chain(d, nall, exps, parent, var)
    integer, intent(in) :: d, nall, exps(d, nall)
    integer, intent(out) :: parent(nall), var(nall)
    integer :: k, j, i
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
  end subroutine monomial_chain

  !> The derivative order of each operator (for the eps**(-|alpha|) factor) and the right-hand sides
  !> that are the same at every point: derivatives (Eq. A.4: alpha! at monomial alpha) and the
  !> Laplacian (Eq. A.6: 2 at every 2 e_j); the interpolating kernel's are built per point.
  subroutine operator_rhs(d, nall, n0, nops, opkind, alpha, exps, ord, rhs0)
    integer, intent(in) :: d, nall, n0, nops, opkind(nops), alpha(d, nops), exps(d, nall)
    integer, intent(out) :: ord(nops)
    real(dp), intent(out) :: rhs0(nall - n0 + 1, nops)
    integer :: i, k, j, deg
    real(dp) :: fac
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
  end subroutine operator_rhs

  !> Collocation point p at x_p (core size eps) with its nk source neighbours nbr (0-based): the
  !> scaled Vandermonde matrix and weights, the moment matrix and its Cholesky factor, one solve per
  !> operator, the weights data(k0 + q, i) (and diag(p, i) in form b).  v, b, a, rhs, s, w2, work:
  !> workspace.
  subroutine point_weights(d, nsrc, src_x, x_p, eps, nk, nbr, c, form, n0, nall, nops, opkind, ord, a_src, &
       max_cond, parent, var, rhs0, v, b, a, rhs, s, w2, work, nnz, k0, data, ncol, p, diag, nnb, rcond, status)
    integer, intent(in) :: d, nsrc, nk, nbr(nk), form, n0, nall, nops, opkind(nops), ord(nops)
    integer, intent(in) :: parent(nall), var(nall)
    real(dp), intent(in) :: src_x(d, nsrc), x_p(d), eps, c, a_src(nsrc), max_cond, rhs0(nall - n0 + 1, nops)
    real(dp), contiguous, intent(inout) :: v(:, :), b(:, :), a(:, :), rhs(:, :), s(:), w2(:), work(:, :)
    integer(i8), intent(in) :: nnz, k0
    integer, intent(in) :: ncol, p
    real(dp), intent(inout) :: data(nnz, nops), diag(ncol, nops)
    integer, intent(out) :: nnb, status
    real(dp), intent(out) :: rcond
    integer :: nb, i, q, k, info
    real(dp) :: scalef(nops), dist, t(4)

    nb = nall - n0 + 1
    rcond = 0.0_dp
    data(k0 + 1:k0 + nk, :) = 0.0_dp         ! a failed point keeps zero weights
    diag(p, :) = 0.0_dp
    call stencil_matrix(d, nsrc, src_x, x_p, eps, nk, nbr, c, form, n0, nall, parent, var, v, b, w2, nnb)
    if (nnb < nb) then
       status = DC_FEW
       return
    end if
    call factor_moments(nb, nk, b, a, work, max_cond, rcond, status)
    if (status /= DC_OK) return
    ! right-hand sides: the same for every point, but for the interpolating kernel
    rhs = rhs0
    do i = 1, nops
       scalef(i) = eps**(-ord(i))
       if (opkind(i) /= OP_INTERP) cycle
       ! s_q = Q(|x_p - x_q| / a_q); b = e_1 - V^T s
       do q = 1, nk
          dist = sqrt(sum((src_x(:, nbr(q) + 1) - x_p)**2)) / a_src(nbr(q) + 1)
          s(q) = 0.0_dp
          if (dist <= 1.0_dp) s(q) = 1.0_dp - dist * dist * (6.0_dp - dist * (8.0_dp - 3.0_dp * dist))
       end do
       ! rhs(k) = -(sum over q of v(k, q) s_q, in order over q), every k at once
       rhs(:, i) = 0.0_dp
       do q = 1, nk
          rhs(:, i) = rhs(:, i) + v(n0:nall, q) * s(q)
       end do
       rhs(:, i) = -rhs(:, i)
       rhs(1, i) = rhs(1, i) + 1.0_dp
    end do
    if (nb <= MAX_INLINE) then
       do i = 1, nops
          call cholesky_solve(nb, a, rhs(:, i))
       end do
    else
       call dpotrs('L', nb, nops, a, nb, rhs, nb, info)
    end if
    ! weights: w**2 (V c), scaled; interpolation adds the spline
    do i = 1, nops
       ! each weight's dot product summed in order over k, four neighbours at once
       q = 1
       do while (q + 3 <= nk)
          call dot4(nb, v(n0:nall, q:q + 3), rhs(:, i), t)
          data(k0 + q:k0 + q + 3, i) = scalef(i) * w2(q:q + 3) * t
          q = q + 4
       end do
       do q = q, nk
          data(k0 + q, i) = scalef(i) * w2(q) * dot_product(v(n0:nall, q), rhs(:, i))
       end do
       if (opkind(i) == OP_INTERP) then
          do q = 1, nk
             data(k0 + q, i) = data(k0 + q, i) + s(q)
          end do
       end if
       if (form == FORM_B) diag(p, i) = -sum(data(k0 + 1:k0 + nk, i))
    end do
  end subroutine point_weights

  !> The scaled Vandermonde matrix v(k, q) of the nk neighbours of x_p, the weighted one
  !> b(q, :) = w_q v(n0:, q), the kernel's w_q**2, and the usable neighbours (form b: a source at
  !> x_p itself adds nothing to the moments, also where r2 underflows: such a stencil is then
  !> reported singular, not short).
  subroutine stencil_matrix(d, nsrc, src_x, x_p, eps, nk, nbr, c, form, n0, nall, parent, var, v, b, w2, nnb)
    integer, intent(in) :: d, nsrc, nk, nbr(nk), form, n0, nall, parent(nall), var(nall)
    real(dp), intent(in) :: src_x(d, nsrc), x_p(d), eps, c
    real(dp), contiguous, intent(inout) :: v(:, :), b(:, :), w2(:)
    integer, intent(out) :: nnb
    integer :: q, k
    real(dp) :: z(3), r2, fac
    nnb = 0
    do q = 1, nk
       z = 0.0_dp
       z(1:d) = (src_x(:, nbr(q) + 1) - x_p) / eps
       r2 = z(1) * z(1) + z(2) * z(2) + z(3) * z(3)
       if (form == FORM_A .or. any(src_x(:, nbr(q) + 1) /= x_p)) nnb = nnb + 1
       fac = exp(-0.5_dp * c * c * r2)      ! w_q; the kernel carries w_q**2
       w2(q) = fac * fac
       v(1, q) = 1.0_dp
       if (n0 == 1) b(q, 1) = fac
       do k = 2, nall
          v(k, q) = v(parent(k), q) * z(var(k))
          b(q, k - n0 + 1) = fac * v(k, q)       ! (as it is made: not read back from memory)
       end do
    end do
  end subroutine stencil_matrix

  !> A = B^T B of the nk rows of b, its Cholesky factor (in a), and the reciprocal condition
  !> estimate; status DC_SINGULAR, DC_ILLCOND (above max_cond) or DC_OK.
  subroutine factor_moments(nb, nk, b, a, work, max_cond, rcond, status)
    integer, intent(in) :: nb, nk
    real(dp), contiguous, intent(in) :: b(:, :)
    real(dp), intent(in) :: max_cond
    real(dp), contiguous, intent(inout) :: a(:, :), work(:, :)
    real(dp), intent(out) :: rcond
    integer, intent(out) :: status
    integer :: i, j, info
    real(dp) :: anorm
    rcond = 0.0_dp
    ! a(i, j) = the dot product of columns i and j of b, each summed in order over the rows; four
    ! entries of a column at once (four independent sums the processor overlaps, each in that order)
    ! (the first block of a column may start above the diagonal: a(i, j), i < j, is then the same
    ! sum of the same products as a(j, i), which the last loop writes there anyway)
    do j = 1, nb
       i = max(1, nb - 4 * ((nb - j + 4) / 4) + 1)
       if (nb < 4) i = j
       do while (i + 3 <= nb)
          call dot4(nk, b(1:nk, i:i + 3), b(1:nk, j), a(i:i + 3, j))
          i = i + 4
       end do
       do i = i, nb
          a(i, j) = dot_product(b(1:nk, i), b(1:nk, j))
       end do
       do i = j + 1, nb
          a(j, i) = a(i, j)
       end do
    end do
    anorm = 0.0_dp
    do j = 1, nb
       anorm = max(anorm, sum(abs(a(:, j))))
    end do
    if (nb <= MAX_INLINE) then
       call cholesky(nb, a, info)
    else
       call dpotrf('L', nb, a, nb, info)
    end if
    if (info /= 0) then
       status = DC_SINGULAR
       return
    end if
    rcond = 1.0_dp / (anorm * inverse_norm1(nb, a, work))
    if (rcond * max_cond < 1.0_dp) then
       status = DC_ILLCOND
       return
    end if
    status = DC_OK
  end subroutine factor_moments

  !> Cholesky factorization A = L L^T in the lower triangle of a (the strict upper triangle is
  !> left as it is), as LAPACK's dpotrf('L'): column j less the products of the columns before it,
  !> in that order, its root on the diagonal, the rest divided by it.  info = j > 0 if the leading
  !> minor of order j is not positive definite (or not a number).
  pure subroutine cholesky(n, a, info)
    integer, intent(in) :: n
    real(dp), intent(inout) :: a(:, :)
    integer, intent(out) :: info
    integer :: j, k
    info = 0
    do j = 1, n
       do k = 1, j - 1
          a(j:n, j) = a(j:n, j) - a(j:n, k) * a(j, k)
       end do
       if (.not. a(j, j) > 0.0_dp) then
          info = j
          return
       end if
       a(j, j) = sqrt(a(j, j))
       a(j + 1:n, j) = a(j + 1:n, j) / a(j, j)
    end do
  end subroutine cholesky

  !> Solve L L^T x = b in place (b <- x), L from cholesky: L y = b forward by columns, then
  !> L^T x = y backward, each entry less its dot product with the entries found, in order.
  pure subroutine cholesky_solve(n, l, b)
    integer, intent(in) :: n
    real(dp), intent(in) :: l(:, :)
    real(dp), intent(inout) :: b(:)
    integer :: j, k
    real(dp) :: s
    do j = 1, n
       b(j) = b(j) / l(j, j)
       b(j + 1:n) = b(j + 1:n) - b(j) * l(j + 1:n, j)
    end do
    do j = n, 1, -1
       s = b(j)
       do k = j + 1, n
          s = s - l(k, j) * b(k)
       end do
       b(j) = s / l(j, j)
    end do
  end subroutine cholesky_solve

  !> s(c) = the dot product of column c (1..4) of g(1:m, :) with w(1:m), each summed in order over the
  !> rows like dot_product (four independent sums the processor overlaps).
  pure subroutine dot4(m, g, w, s)
    integer, intent(in) :: m
    real(dp), intent(in) :: g(:, :), w(:)
    real(dp), intent(out) :: s(4)
    integer :: r
    s = 0.0_dp
    do r = 1, m
       s(1) = s(1) + g(r, 1) * w(r)
       s(2) = s(2) + g(r, 2) * w(r)
       s(3) = s(3) + g(r, 3) * w(r)
       s(4) = s(4) + g(r, 4) * w(r)
    end do
  end subroutine dot4

end module arpy_dcpse
