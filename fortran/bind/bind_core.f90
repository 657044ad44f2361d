!> The f2py boundary of the arpy core, shared settings and helpers: the threads of the parallel
!> loops and the sizes from which they run in parallel, huge-page advice, per-column extremes and sums rounded once.
!>
!> Flat external (non-module) routines with explicit-shape arguments and an `info` status code, as
!> f2py calls them; their signatures are declared for f2py in _core.pyf (the contract with
!> Python): keep the two in step.

!> Threads of the core's parallel loops: n > 0 threads, n <= 0 OpenMP's default.
subroutine arpy_set_threads(n)
  use arpy_threads, only: set_threads
  implicit none
  integer, intent(in) :: n
  call set_threads(n)
end subroutine arpy_set_threads

!> The threads the next parallel loop of this thread will use, and the processors OpenMP sees.
subroutine arpy_get_threads(n, max_threads)
  use arpy_threads, only: team_size, core_count
  implicit none
  integer, intent(out) :: n, max_threads
  n = team_size()
  max_threads = core_count()
end subroutine arpy_get_threads

!> Huge-page advice for the core's large arrays: on /= 0 on, 0 off; was: the setting before.
subroutine arpy_set_huge_pages(on, was)
  use arpy_memory, only: set_huge_pages, huge_pages_on
  implicit none
  integer, intent(in) :: on
  integer, intent(out) :: was
  was = merge(1, 0, huge_pages_on())
  call set_huge_pages(on /= 0)
end subroutine arpy_set_huge_pages

!> The sizes from which the core's loops over rows (points) run in parallel: rows, points > 0 set
!> them, <= 0 restore the defaults (20000 rows, 2000 points); old_rows, old_points: the sizes before.
!> For tests (small inputs through the parallel branches); results do not depend on them.
subroutine arpy_set_parallel_thresholds(rows, points, old_rows, old_points)
  use arpy_threads, only: set_parallel_thresholds
  implicit none
  integer, intent(in) :: rows, points
  integer, intent(out) :: old_rows, old_points
  call set_parallel_thresholds(rows, points, old_rows, old_points)
end subroutine arpy_set_parallel_thresholds

!> Per-column least and largest entries of an (n, d) array (x(d, n) here, n >= 1; NaN where a
!> column holds a NaN), in parallel.
subroutine arpy_column_extremes(d, n, x, lo, hi)
  use arpy_kinds, only: dp
  use arpy_checks, only: column_extremes
  implicit none
  integer, intent(in) :: d, n
  real(dp), intent(in) :: x(d, n)
  real(dp), intent(out) :: lo(d), hi(d)
  call column_extremes(d, n, x, lo, hi)
end subroutine arpy_column_extremes

!> The first of the m boxes (lo(d, m), hi(d, m), their ids) holding each point of x(d, n), -1 if none;
!> the upper faces at top(d) belong to the boxes there (arpy_boxes.box_owners).
subroutine arpy_box_owners(d, n, m, x, lo, hi, top, ids, owner)
  use arpy_kinds, only: dp, i8
  use arpy_boxes, only: box_owners
  implicit none
  integer, intent(in) :: d, n, m
  real(dp), intent(in) :: x(d, n), lo(d, m), hi(d, m), top(d)
  integer(i8), intent(in) :: ids(m)
  integer(i8), intent(out) :: owner(n)
  call box_owners(d, n, m, x, lo, hi, top, ids, owner)
end subroutine arpy_box_owners

!> s = the sum of x rounded once (math.fsum's value); ok = 0 if a term is not finite or a partial
!> sum overflows (then s = 0).
subroutine arpy_exact_sum(n, x, s, ok)
  use arpy_kinds, only: dp
  use arpy_sums, only: exact_sum
  implicit none
  integer, intent(in) :: n
  real(dp), intent(in) :: x(n)
  real(dp), intent(out) :: s
  integer, intent(out) :: ok
  logical :: done
  call exact_sum(n, x, s, done)
  ok = merge(1, 0, done)
end subroutine arpy_exact_sum

!> p(1:np): nonoverlapping partials whose exact sum is that of x; ok = 0 (np = 0) if a term is not
!> finite, a partial sum overflows or the partials outgrow p.
subroutine arpy_exact_partials(n, x, p, np, ok)
  use arpy_kinds, only: dp
  use arpy_sums, only: MAXP, exact_partials
  implicit none
  integer, intent(in) :: n
  real(dp), intent(in) :: x(n)
  real(dp), intent(out) :: p(64)
  integer, intent(out) :: np, ok
  logical :: done
  real(dp) :: q(MAXP)
  call exact_partials(n, x, q, np, done)
  p = 0.0_dp
  p(1:np) = q(1:np)
  ok = merge(1, 0, done)
end subroutine arpy_exact_partials
