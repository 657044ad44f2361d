!> The pair test of every neighbour list under its cutoff rule (RULE_* of arpy_kinds): p and q are
!> neighbours iff |x_p - x_q|**2 <= reach**2, reach = min(rc_p, rc_q) + skin, max(rc_p, rc_q) + skin
!> or (rc_p + rc_q) + skin, each evaluated in that order, the squared distance summed axis by axis.
!> Brute force tests pair_reach; the cell lists keep the skin of the min and max rules in their
!> stored cutoffs and that of the sum rule apart (rule_skins), and test ranges of slots with
!> scan_ranges.
module arpy_pairs
  use arpy_kinds, only: dp, i8, RULE_MAX, RULE_SUM
  implicit none
  private

  public :: pair_reach, rule_skins, scan_ranges

contains

  !> The reach of a pair under a cutoff rule (arpy_kinds): min(ra, rb) + skin, max(ra, rb) + skin
  !> or (ra + rb) + skin, in that order (the test of every list builder).
  elemental real(dp) function pair_reach(rule, ra, rb, skin) result(r)
    integer, intent(in) :: rule
    real(dp), intent(in) :: ra, rb, skin
    select case (rule)
    case (RULE_MAX)
       r = max(ra, rb) + skin
    case (RULE_SUM)
       r = (ra + rb) + skin
    case default
       r = min(ra, rb) + skin
    end select
  end function pair_reach

  !> How a list under `rule` takes the skin: sskin is added to the cutoffs it stores (rcs: the
  !> min and max rules, whose reach min or max(rc_p + skin, rc_q + skin) is that of the rule
  !> exactly), pskin to the reach of each pair (the sum rule: (rc_p + rc_q) + skin); mult: the
  !> factor of the largest cutoff in the largest reach (mult rc_max + skin).
  pure subroutine rule_skins(rule, skin, sskin, pskin, mult)
    integer, intent(in) :: rule
    real(dp), intent(in) :: skin
    real(dp), intent(out) :: sskin, pskin, mult
    sskin = skin
    pskin = 0.0_dp
    mult = 1.0_dp
    if (rule == RULE_SUM) then
       sskin = 0.0_dp
       pskin = skin
       mult = 2.0_dp
    end if
  end subroutine rule_skins

  !> The distance test of every cell list: append to idx(nnz+1 : ) the
  !> 0-based particle index of every slot b of the ranges rs(r) .. re(r),
  !> r = 1 .. nr, with |xs(:, b) - xa|**2 <= rm**2, rm the pair's reach under
  !> `rule`: min(ra, rcs(b)), max(ra, rcs(b)) or (ra + rcs(b)) + pskin (the
  !> cutoffs carry the skin of the min and max rules, see rule_skins).  The
  !> caller has made room for every candidate, so the acceptance is
  !> branch-free; one loop per rule (the rule is chosen once per call).
  pure subroutine scan_ranges(xs, rcs, perm, xa, ra, nr, rs, re, idx, nnz, rule, pskin)
    real(dp), intent(in) :: xs(3, *), rcs(*), xa(3), ra, pskin
    integer, intent(in) :: perm(*), nr, rs(*), re(*), rule
    integer, intent(inout) :: idx(*)
    integer(i8), intent(inout) :: nnz
    integer :: r, b
    integer(i8) :: m
    real(dp) :: dx, dy, dz, rm
    m = nnz          ! (a local count: the acceptance adds 0 or 1 without a branch)
    select case (rule)
    case (RULE_MAX)
       do r = 1, nr
          do b = rs(r), re(r)
             dx = xs(1, b) - xa(1)
             dy = xs(2, b) - xa(2)
             dz = xs(3, b) - xa(3)
             rm = max(ra, rcs(b))
             idx(m + 1) = perm(b) - 1
             m = m + merge(1_i8, 0_i8, dx * dx + dy * dy + dz * dz <= rm * rm)
          end do
       end do
    case (RULE_SUM)
       do r = 1, nr
          do b = rs(r), re(r)
             dx = xs(1, b) - xa(1)
             dy = xs(2, b) - xa(2)
             dz = xs(3, b) - xa(3)
             rm = (ra + rcs(b)) + pskin
             idx(m + 1) = perm(b) - 1
             m = m + merge(1_i8, 0_i8, dx * dx + dy * dy + dz * dz <= rm * rm)
          end do
       end do
    case default
       do r = 1, nr
          do b = rs(r), re(r)
             dx = xs(1, b) - xa(1)
             dy = xs(2, b) - xa(2)
             dz = xs(3, b) - xa(3)
             rm = min(ra, rcs(b))
             idx(m + 1) = perm(b) - 1
             m = m + merge(1_i8, 0_i8, dx * dx + dy * dy + dz * dz <= rm * rm)
          end do
       end do
    end select
    nnz = m
  end subroutine scan_ranges

end module arpy_pairs
