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
!> symmetric list (each unordered pair once, so W = 2 sum_pairs V_pq).
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
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC
  use arpy_threads, only: team_size, MIN_PARALLEL_POINTS
  implicit none
  private

  integer, parameter, public :: POT_V1 = 1, POT_V2 = 2, POT_V1_PURE = 3, POT_V2_PURE = 4
  real(dp), parameter :: RCORE = 0.5_dp
  !> Pairs closer than this (in units of D_pq) count as fused: zero pair force.
  real(dp), parameter, public :: RFUSED = 1.0e-3_dp

  public :: pair_potential, so_energy_gradient, so_scan

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
    logical :: core
    core = kind == POT_V1 .or. kind == POT_V2
    if (core) then
       rr = max(r, RCORE)
    else
       rr = max(r, RFUSED)
    end if
    select case (kind)
    case (POT_V1, POT_V1_PURE)
       v = 0.8_dp * 2.5_dp**(1.0_dp - 5.0_dp * rr) - 2.5_dp**(-4.0_dp * rr)
       dv = -5.0_dp * l25 * 0.8_dp * 2.5_dp**(1.0_dp - 5.0_dp * rr) + 4.0_dp * l25 * 2.5_dp**(-4.0_dp * rr)
    case default
       v = 0.5_dp / rr**2 + 1.0_dp / (6.0_dp * rr**6)
       dv = -1.0_dp / rr**3 - 1.0_dp / rr**7
    end select
    if (core .and. r < RCORE) then
       ! the straight line from (0, 0) to (0.5, V(0.5))
       dv = v / RCORE
       v = dv * r
    end if
  end subroutine pair_potential

  !> Total energy W and its gradient g(d, n) for the pairs of a symmetric list.  The terms of each
  !> pair are computed in parallel (rows of the list split between threads), then added up in list
  !> order by one thread: the sums are those of a serial pass, whatever the number of threads.
  subroutine so_energy_gradient(d, n, x, dres, gradd, period, off, idx, kind, vshift, energy, g, info)
    integer, intent(in) :: d, n, kind
    real(dp), intent(in) :: x(d, n), dres(n), gradd(d, n), period(d), vshift
    integer(i8), intent(in) :: off(n + 1)
    integer, intent(in) :: idx(*)
    real(dp), intent(out) :: energy, g(d, n)
    integer, intent(out) :: info
    real(dp), allocatable :: pe(:), pf(:, :), pt(:)
    integer :: p, q, stat
    integer(i8) :: k
    real(dp) :: dpq, rpq, r, v, dv, e(d)
    info = ARPY_OK
    energy = 0.0_dp
    g = 0.0_dp
    allocate(pe(off(n + 1)), pf(d, off(n + 1)), pt(off(n + 1)), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    ! per pair: its energy 2 V_pq, the force 2 D_pq V'(r) e on p (minus that on q), the factor of
    ! the grad D term
    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_POINTS) schedule(dynamic, 256) &
    !$omp private(p, q, k, dpq, rpq, r, v, dv, e)
    do p = 1, n
       do k = off(p) + 1, off(p + 1)
          q = idx(k) + 1
          call pair_geometry(d, x(:, p), x(:, q), dres(p), dres(q), period, e, rpq, dpq)
          r = rpq / dpq
          call pair_potential(kind, r, v, dv)
          v = v - vshift
          pe(k) = 2.0_dp * dpq * dpq * v
          ! a pair closer than RFUSED D_pq sits at the bottom of the fusion core: no force
          ! (its direction is numerical noise, and any finite step would overshoot)
          if (r > RFUSED) then
             e = e / rpq
          else
             e = 0.0_dp
          end if
          pf(:, k) = 2.0_dp * dpq * dv * e
          pt(k) = 2.0_dp * dpq * (2.0_dp * v - r * dv)
       end do
    end do
    !$omp end parallel do
    do p = 1, n
       do k = off(p) + 1, off(p + 1)
          q = idx(k) + 1
          energy = energy + pe(k)
          ! d(2 V_pq)/dx_p and d(2 V_pq)/dx_q
          g(:, p) = g(:, p) + pf(:, k)
          g(:, q) = g(:, q) - pf(:, k)
          if (dres(p) < dres(q)) then
             g(:, p) = g(:, p) + pt(k) * gradd(:, p)
          else if (dres(q) < dres(p)) then
             g(:, q) = g(:, q) + pt(k) * gradd(:, q)
          end if
       end do
    end do
  end subroutine so_energy_gradient

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

  !> One pass over a symmetric list for the adaptation loop (§3.1, §3.2.2 4(e)):
  !>  - cnt_all(p): neighbours of p, and ratio = max over pairs of D_pq/r_pq
  !>    (huge for coincident particles): the stopping criterion;
  !>  - greedy fusion in list order: a pair closer than D_pq/2 whose two
  !>    particles are both still alive becomes one particle at their midpoint
  !>    (kept at the lower index of the pair as stored, the other dies);
  !>    xo holds the moved positions, alive(p) = 0 for the dead, nfused counts them;
  !>  - cnt_alive(p): neighbours among the survivors (pairs of the same list)
  !>    closer than rcount D_pq (a margin inside the cutoff, for insertion).
  subroutine so_scan(d, n, x, dres, period, rcount, off, idx, xo, alive, cnt_all, cnt_alive, ratio, nfused, info)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), dres(n), period(d), rcount
    integer(i8), intent(in) :: off(n + 1)
    integer, intent(in) :: idx(*)
    real(dp), intent(out) :: xo(d, n), ratio
    integer, intent(out) :: alive(n), cnt_all(n), cnt_alive(n), nfused, info
    real(dp), allocatable :: rr(:), dd(:)
    integer :: p, q, stat
    integer(i8) :: k
    real(dp) :: e(d)
    info = ARPY_OK
    xo = x
    alive = 1
    cnt_all = 0
    cnt_alive = 0
    nfused = 0
    ratio = 0.0_dp
    allocate(rr(off(n + 1)), dd(off(n + 1)), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    ! the pair distances in parallel; the greedy fusion and the counts in list order
    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_POINTS) schedule(dynamic, 256) &
    !$omp private(p, q, k, e)
    do p = 1, n
       do k = off(p) + 1, off(p + 1)
          q = idx(k) + 1
          call pair_geometry(d, x(:, p), x(:, q), dres(p), dres(q), period, e, rr(k), dd(k))
       end do
    end do
    !$omp end parallel do
    do p = 1, n
       do k = off(p) + 1, off(p + 1)
          q = idx(k) + 1
          cnt_all(p) = cnt_all(p) + 1
          cnt_all(q) = cnt_all(q) + 1
          if (rr(k) > 0.0_dp) then
             ratio = max(ratio, dd(k) / rr(k))
          else
             ratio = huge(1.0_dp)
          end if
          if (rr(k) < 0.5_dp * dd(k) .and. alive(p) == 1 .and. alive(q) == 1) then
             e = separation(d, xo(:, p), xo(:, q), period)
             xo(:, p) = xo(:, p) - 0.5_dp * e
             alive(q) = 0
             nfused = nfused + 1
          end if
       end do
    end do
    do p = 1, n
       if (alive(p) == 0) cycle
       do k = off(p) + 1, off(p + 1)
          q = idx(k) + 1
          if (alive(q) == 0) cycle
          if (rr(k) > rcount * dd(k)) cycle
          cnt_alive(p) = cnt_alive(p) + 1
          cnt_alive(q) = cnt_alive(q) + 1
       end do
    end do
  end subroutine so_scan

end module arpy_selforg
