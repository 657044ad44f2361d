!> The f2py boundary of the arpy core, self-organizing particles and the resolution field: energies,
!> gradients and distance ratios over a list, fusion, the pair potentials, Eq. 2.9's scan and the
!> Shepard interpolation of the resolution.
!>
!> Flat external (non-module) routines with explicit-shape arguments and an `info` status code, as
!> f2py calls them; their signatures are declared for f2py in _core.pyf (the contract with
!> Python): keep the two in step.

!> Self-organization: total energy W and gradient over a symmetric list
!> (see arpy_selforg); kind = POT_V1, POT_V2, POT_V1_PURE or POT_V2_PURE;
!> dres = D_p (> 0), gradd = grad D at the particles (zeros to drop that term); grad = 0: the
!> energies alone (the same values), g = 0.
subroutine arpy_so_energy(d, n, x, dres, gradd, period, nnz, off, idx, kind, vshift, grad, e, g, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_METHOD
  use arpy_checks, only: check_particles, check_csr
  use arpy_selforg, only: so_energy_rows, POT_V1, POT_V2, POT_V1_PURE, POT_V2_PURE
  implicit none
  integer, intent(in) :: d, n, kind, grad
  integer(i8), intent(in) :: nnz
  real(dp), intent(in) :: x(d, n), dres(n), gradd(d, n), period(d), vshift
  integer(i8), intent(in) :: off(n + 1)
  integer, intent(in) :: idx(nnz)
  real(dp), intent(out) :: e(n), g(d, n)
  integer, intent(out) :: info, bad
  e = 0.0_dp
  g = 0.0_dp
  call check_particles(d, n, x, dres, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  select case (kind)
  case (POT_V1, POT_V2, POT_V1_PURE, POT_V2_PURE)
  case default
     info = ARPY_ERR_METHOD
     return
  end select
  call check_csr(n, n, nnz, off, idx, info, bad)
  if (info /= ARPY_OK) return
  call so_energy_rows(d, n, x, dres, gradd, period, off, idx, kind, vshift, grad /= 0, e, g)
end subroutine arpy_so_energy

!> r_pq / D_pq of every entry of a list (arpy_selforg.so_ratios); period(a) > 0: periodic edge
!> along axis a.
subroutine arpy_so_ratios(d, n, x, dres, period, nnz, off, idx, rho, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK
  use arpy_checks, only: check_particles, check_csr
  use arpy_selforg, only: so_ratios
  implicit none
  integer, intent(in) :: d, n
  integer(i8), intent(in) :: nnz
  real(dp), intent(in) :: x(d, n), dres(n), period(d)
  integer(i8), intent(in) :: off(n + 1)
  integer, intent(in) :: idx(nnz)
  real(dp), intent(out) :: rho(nnz)
  integer, intent(out) :: info, bad
  rho = 0.0_dp
  call check_particles(d, n, x, dres, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  call check_csr(n, n, nnz, off, idx, info, bad)
  if (info /= ARPY_OK) return
  call so_ratios(d, n, x, dres, period, off, idx, rho)
end subroutine arpy_so_ratios

!> Greedy fusion of the candidate pairs (a(i), b(i)) in the given order (arpy_selforg.so_fuse).
!> info = ARPY_ERR_LIST (bad = i) if a pair's indices are out of range or equal.
subroutine arpy_so_fuse(d, n, x, period, m, a, b, xo, alive, nfused, info, bad)
  use arpy_kinds, only: dp, ARPY_OK, ARPY_ERR_LIST
  use arpy_selforg, only: so_fuse
  implicit none
  integer, intent(in) :: d, n, m, a(m), b(m)
  real(dp), intent(in) :: x(d, n), period(d)
  real(dp), intent(out) :: xo(d, n)
  integer, intent(out) :: alive(n), nfused, info, bad
  integer :: i
  xo = x
  alive = 1
  nfused = 0
  info = ARPY_OK
  bad = 0
  do i = 1, m
     if (min(a(i), b(i)) < 0 .or. max(a(i), b(i)) >= n .or. a(i) == b(i)) then
        info = ARPY_ERR_LIST
        bad = i - 1
        return
     end if
  end do
  call so_fuse(d, n, x, period, m, a, b, xo, alive, nfused)
end subroutine arpy_so_fuse

!> The normalized pair potential (kind = POT_V1, POT_V2, POT_V1_PURE or
!> POT_V2_PURE) and its derivative at r(m).
subroutine arpy_pair_potential(kind, m, r, v, dv)
  use arpy_kinds, only: dp
  use arpy_selforg, only: pair_potential
  implicit none
  integer, intent(in) :: kind, m
  real(dp), intent(in) :: r(m)
  real(dp), intent(out) :: v(m), dv(m)
  call pair_potential(kind, r, v, dv)
end subroutine arpy_pair_potential

!> Eq. 2.9's scan (arpy_grade.grade_scan): dout(p) = min(target(p), min over the sources q of
!> max(st(q), |x_p - x_q| / rstar)).  Positions finite, targets finite and > 0 (check_particles),
!> rstar finite and > 0 (ARPY_ERR_BAD_RC), at least one source when there are particles (ARPY_ERR_SIZE).
subroutine arpy_grade(d, n, x, target, m, src, st, rstar, dout, info, bad)
  use, intrinsic :: ieee_arithmetic, only: ieee_is_finite
  use arpy_kinds, only: dp, ARPY_OK, ARPY_ERR_BAD_RC, ARPY_ERR_SIZE
  use arpy_checks, only: check_particles
  use arpy_grade, only: grade_scan
  implicit none
  integer, intent(in) :: d, n, m
  real(dp), intent(in) :: x(d, n), target(n), src(d, m), st(m), rstar
  real(dp), intent(out) :: dout(n)
  integer, intent(out) :: info, bad
  dout = 0.0_dp
  call check_particles(d, n, x, target, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  call check_particles(d, m, src, st, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  if (.not. ieee_is_finite(rstar) .or. .not. (rstar > 0.0_dp)) then
     info = ARPY_ERR_BAD_RC
     return
  end if
  if (n > 0 .and. m == 0) then
     info = ARPY_ERR_SIZE
     return
  end if
  call grade_scan(d, n, x, target, m, src, st, rstar, dout)
end subroutine arpy_grade

!> The Shepard interpolation of D at the m points y from the ns sources xs (cutoffs rcs, values ds)
!> over the cross list off / idx (arpy_grade.shepard_rows): out, and ok(p) = 1 where a source reaches
!> y_p.  info = ARPY_ERR_LIST (bad: the row) for a list that does not index the sources,
!> ARPY_ERR_ALLOC without workspace.
subroutine arpy_shepard(d, m, y, ns, xs, rcs, ds, nnz, off, idx, out, ok, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC
  use arpy_checks, only: check_csr
  use arpy_grade, only: shepard_rows
  implicit none
  integer, intent(in) :: d, m, ns
  integer(i8), intent(in) :: nnz
  real(dp), intent(in) :: y(d, m), xs(d, ns), rcs(ns), ds(ns)
  integer(i8), intent(in) :: off(m + 1)
  integer, intent(in) :: idx(nnz)
  real(dp), intent(out) :: out(m)
  integer, intent(out) :: ok(m), info, bad
  integer :: failed
  out = 0.0_dp
  ok = 0
  call check_csr(m, ns, nnz, off, idx, info, bad)
  if (info /= ARPY_OK) return
  call shepard_rows(d, m, y, ns, xs, rcs, ds, off, idx, out, ok, failed)
  if (failed /= 0) info = ARPY_ERR_ALLOC
end subroutine arpy_shepard
