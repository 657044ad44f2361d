!> Self-organization pseudo forces (Reboux, Schrader, Sbalzarini, JCP 2012,
!> §2.3.2 and §3.1): pair potentials, the total energy W and its gradient.
!>
!> Normalized pair potentials (r in units of the local resolution):
!>   V1(r) = 0.8 * 2.5**(1 - 5r) - 2.5**(-4r)   Morse type, minimum at r = 1 (Eq. 2.12)
!>   V2(r) = r**(-2)/2 + r**(-6)/6              purely repulsive (Eq. 2.13)
!> both replaced below r = 0.5 by the straight line from 0 to V(0.5),
!> V(r) = 2 r V(0.5): a short-range attraction that makes particles closer
!> than half the local resolution fuse (§2.3.2).
!>
!> Scaled pair energy V_pq = D_pq**2 V(r_pq / D_pq), D_pq = min(D_p, D_q)
!> (Eq. 2.10), and W = sum_p sum_{q in N_p} V_pq (Eq. 2.11), over a
!> full list (each unordered pair in both rows, so W = 2 sum_pairs V_pq).
!> Gradient (Eqs. 3.3-3.4): with r = r_pq/D_pq and e = (x_p - x_q)/r_pq,
!>   dV_pq/dx_p = D_pq [V'(r) e + (2 V(r) - r V'(r)) grad_p D_pq],
!> where grad_p D_pq = grad D(x_p) if D_p < D_q and 0 otherwise (D_p is the
!> resolution field at x_p; the caller supplies its gradient, or zeros to
!> drop the term as the paper suggests once the field is resolved).
!>
!> vshift: subtracted from V (V - V(r_cut) makes W continuous when pairs
!> enter or leave lists cut at r_cut; the forces do not change).
!>
!> Periodic boxes: period(a) > 0 is the box edge along axis a; pair
!> separations then take the minimum image (the lists hold each pair once,
!> also across the boundary).  period(a) = 0: not periodic along a.
module arpy_selforg
  use arpy_kinds, only: dp, i8
  use arpy_threads, only: team_size, MIN_PARALLEL_POINTS
  implicit none
  private

  integer, parameter, public :: POT_V1 = 1, POT_V2 = 2, POT_V1_PURE = 3, POT_V2_PURE = 4
  real(dp), parameter :: RCORE = 0.5_dp
  !> Pairs closer than this (in units of D_pq) count as fused: zero pair force.
  real(dp), parameter, public :: RFUSED = 1.0e-3_dp

  public :: pair_potential, so_energy_rows, so_ratios, so_fuse

contains

  !> V(r) and V'(r) of a normalized potential, r >= 0: kind POT_V1 or POT_V2
  !> with the fusion core below r = 0.5; POT_V1_PURE or POT_V2_PURE without it
  !> (the potentials of Eqs. 2.12-2.13 as they are, for relaxing a fixed
  !> number of particles; r is then taken as at least RFUSED).
  elemental subroutine pair_potential(kind, r, v, dv)
    integer, intent(in) :: kind
    real(dp), intent(in) :: r
    real(dp), intent(out) :: v, dv
    real(dp), parameter :: l25 = log(2.5_dp)
    real(dp) :: rr
    rr = clamped(kind, r)
    v = potential_value(kind, rr)
    select case (kind)
    case (POT_V1, POT_V1_PURE)
       dv = -5.0_dp * l25 * 0.8_dp * 2.5_dp**(1.0_dp - 5.0_dp * rr) + 4.0_dp * l25 * 2.5_dp**(-4.0_dp * rr)
    case default
       dv = -1.0_dp / rr**3 - 1.0_dp / rr**7
    end select
    if (in_core(kind, r)) then
       ! the straight line from (0, 0) to (0.5, V(0.5))
       dv = v / RCORE
       v = dv * r
    end if
  end subroutine pair_potential

  !> V(r) alone, the same value as pair_potential's (for the energy without its gradient).
  elemental function pair_value(kind, r) result(v)
    integer, intent(in) :: kind
    real(dp), intent(in) :: r
    real(dp) :: v
    v = potential_value(kind, clamped(kind, r))
    if (in_core(kind, r)) v = (v / RCORE) * r
  end function pair_value

  !> r as the potentials take it: at least RCORE with the fusion core (below it the line), else at
  !> least RFUSED.
  elemental function clamped(kind, r) result(rr)
    integer, intent(in) :: kind
    real(dp), intent(in) :: r
    real(dp) :: rr
    if (kind == POT_V1 .or. kind == POT_V2) then
       rr = max(r, RCORE)
    else
       rr = max(r, RFUSED)
    end if
  end function clamped

  !> Whether r lies on the fusion core's straight line.
  elemental logical function in_core(kind, r)
    integer, intent(in) :: kind
    real(dp), intent(in) :: r
    in_core = (kind == POT_V1 .or. kind == POT_V2) .and. r < RCORE
  end function in_core

  !> Eq. 2.12 or 2.13 at rr.
  elemental function potential_value(kind, rr) result(v)
    integer, intent(in) :: kind
    real(dp), intent(in) :: rr
    real(dp) :: v
    select case (kind)
    case (POT_V1, POT_V1_PURE)
       v = 0.8_dp * 2.5_dp**(1.0_dp - 5.0_dp * rr) - 2.5_dp**(-4.0_dp * rr)
    case default
       v = 0.5_dp / rr**2 + 1.0_dp / (6.0_dp * rr**6)
    end select
  end function potential_value

  !> Per-particle energies e(p) = sum over row p of V_pq and the gradient g(:, p) = dW/dx_p for a
  !> full list (each pair in the rows of both its particles), so that W = sum_p e(p) (Eq. 2.11);
  !> without with_grad the energies alone (the same values) and g = 0.
  !> Each row is summed in its stored order by one thread and writes only its own outputs: the
  !> results are bitwise the same for any number of threads, and for any list method once the rows
  !> are in a canonical order.
  subroutine so_energy_rows(d, n, x, dres, gradd, period, off, idx, kind, vshift, with_grad, e, g)
    integer, intent(in) :: d, n, kind
    real(dp), intent(in) :: x(d, n), dres(n), gradd(d, n), period(d), vshift
    integer(i8), intent(in) :: off(n + 1)
    integer, intent(in) :: idx(*)
    logical, intent(in) :: with_grad
    real(dp), intent(out) :: e(n), g(d, n)
    integer :: p, q
    integer(i8) :: k
    real(dp) :: dpq, rpq, r, v, dv, s(d), ep, gp(d)
    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_POINTS) schedule(dynamic, 256) &
    !$omp private(p, q, k, dpq, rpq, r, v, dv, s, ep, gp)
    do p = 1, n
       ep = 0.0_dp
       gp = 0.0_dp
       do k = off(p) + 1, off(p + 1)
          q = idx(k) + 1
          call pair_geometry(d, x(:, p), x(:, q), dres(p), dres(q), period, s, rpq, dpq)
          r = rpq / dpq
          if (.not. with_grad) then
             ep = ep + dpq * dpq * (pair_value(kind, r) - vshift)
             cycle
          end if
          call pair_potential(kind, r, v, dv)
          v = v - vshift
          ep = ep + dpq * dpq * v
          ! d(2 V_pq)/dx_p; a pair closer than RFUSED D_pq sits at the bottom of the fusion core:
          ! no force (its direction is numerical noise, and any finite step would overshoot)
          if (r > RFUSED) gp = gp + (2.0_dp * dpq * dv / rpq) * s
          if (dres(p) < dres(q)) gp = gp + (2.0_dp * dpq * (2.0_dp * v - r * dv)) * gradd(:, p)
       end do
       e(p) = ep
       g(:, p) = gp
    end do
    !$omp end parallel do
  end subroutine so_energy_rows

  !> x_p - x_q, minimum image along the periodic axes (period > 0).
  pure function separation(d, xp, xq, period) result(e)
    integer, intent(in) :: d
    real(dp), intent(in) :: xp(d), xq(d), period(d)
    real(dp) :: e(d)
    e = xp - xq
    where (period > 0.0_dp) e = e - period * anint(e / period)
  end function separation

  !> Separation e = x_p - x_q (minimum image), its length and D_pq = min(D_p, D_q).
  pure subroutine pair_geometry(d, xp, xq, dp_, dq_, period, e, rpq, dpq)
    integer, intent(in) :: d
    real(dp), intent(in) :: xp(d), xq(d), dp_, dq_, period(d)
    real(dp), intent(out) :: e(d), rpq, dpq
    e = separation(d, xp, xq, period)
    rpq = sqrt(sum(e * e))
    dpq = min(dp_, dq_)
  end subroutine pair_geometry

  !> rho(k) = r_pq / D_pq of every entry k of a list (minimum image along periodic axes): the
  !> stopping ratio, the fusion candidates and the neighbour counts of the adaptation loop (§3.1).
  subroutine so_ratios(d, n, x, dres, period, off, idx, rho)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), dres(n), period(d)
    integer(i8), intent(in) :: off(n + 1)
    integer, intent(in) :: idx(*)
    real(dp), intent(out) :: rho(*)
    integer :: p, q
    integer(i8) :: k
    real(dp) :: s(d), rpq, dpq
    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_POINTS) schedule(dynamic, 256) &
    !$omp private(p, q, k, s, rpq, dpq)
    do p = 1, n
       do k = off(p) + 1, off(p + 1)
          q = idx(k) + 1
          call pair_geometry(d, x(:, p), x(:, q), dres(p), dres(q), period, s, rpq, dpq)
          rho(k) = rpq / dpq
       end do
    end do
    !$omp end parallel do
  end subroutine so_ratios

  !> Fusion as a greedy matching: the candidate pairs (a(i), b(i)) (0-based), visited in the given
  !> order, each fuse when neither particle has fused yet; a(i) moves to the midpoint
  !> x_a - (x_a - x_b) / 2 (minimum image) and b(i) dies (alive = 0).  Each particle fuses at most
  !> once, so the result depends only on the visiting order of the candidates.
  subroutine so_fuse(d, n, x, period, m, a, b, xo, alive, nfused)
    integer, intent(in) :: d, n, m, a(m), b(m)
    real(dp), intent(in) :: x(d, n), period(d)
    real(dp), intent(out) :: xo(d, n)
    integer, intent(out) :: alive(n), nfused
    integer :: i, p, q
    xo = x
    alive = 1               ! 1: not fused yet; 2: fused and kept; 0: fused away
    nfused = 0
    do i = 1, m
       p = a(i) + 1
       q = b(i) + 1
       if (alive(p) /= 1 .or. alive(q) /= 1) cycle
       xo(:, p) = x(:, p) - 0.5_dp * separation(d, x(:, p), x(:, q), period)
       alive(p) = 2
       alive(q) = 0
       nfused = nfused + 1
    end do
    alive = min(alive, 1)
  end subroutine so_fuse

end module arpy_selforg
