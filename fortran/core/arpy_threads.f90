!> How many threads the core's parallel loops use.
!>
!> By default OpenMP decides (OMP_NUM_THREADS, or threadpoolctl's limit, else every core); a
!> positive count set from Python (arpy.set_num_threads) overrides it.  Results do not depend on
!> the count: every parallel loop writes each output element from exactly one iteration, and no
!> floating-point sum is split between threads.
module arpy_threads
  !$ use omp_lib, only: omp_get_max_threads, omp_get_num_procs
  implicit none
  private

  !> 0: OpenMP's default; n > 0: n threads
  integer, save :: requested = 0

  !> Loops over fewer rows than this run on one thread (a team costs more than it saves).
  integer, parameter, public :: DEFAULT_MIN_PARALLEL_ROWS = 20000
  !> The same for loops whose every row does about a microsecond of work (a tree search, a row of
  !> pair potentials, a row of the uniform cell list): smaller loops gain.
  integer, parameter, public :: DEFAULT_MIN_PARALLEL_POINTS = 2000

  !> The thresholds the loops read: the defaults above, lowered only by set_parallel_thresholds
  !> (the tests, so that small inputs take the parallel branches; results do not depend on them).
  integer, protected, public :: MIN_PARALLEL_ROWS = DEFAULT_MIN_PARALLEL_ROWS
  integer, protected, public :: MIN_PARALLEL_POINTS = DEFAULT_MIN_PARALLEL_POINTS

  public :: set_threads, team_size, core_count, block_range, set_parallel_thresholds

contains

  !> Ask for n threads in the core's parallel loops (n <= 0: OpenMP's default).
  subroutine set_threads(n)
    integer, intent(in) :: n
    requested = max(n, 0)
  end subroutine set_threads

  !> The number of threads the next parallel loop of the calling thread will use.
  integer function team_size()
    team_size = 1
    !$ team_size = omp_get_max_threads()
    if (requested > 0) team_size = requested
  end function team_size

  !> The number of processors OpenMP sees (1 without OpenMP).
  integer function core_count()
    core_count = 1
    !$ core_count = omp_get_num_procs()
  end function core_count

  !> Loops over rows (points) run in parallel from `rows` (`points`) on; a value <= 0 restores
  !> the default.  old_rows, old_points: the thresholds before.
  subroutine set_parallel_thresholds(rows, points, old_rows, old_points)
    integer, intent(in) :: rows, points
    integer, intent(out) :: old_rows, old_points
    old_rows = MIN_PARALLEL_ROWS
    old_points = MIN_PARALLEL_POINTS
    MIN_PARALLEL_ROWS = merge(rows, DEFAULT_MIN_PARALLEL_ROWS, rows > 0)
    MIN_PARALLEL_POINTS = merge(points, DEFAULT_MIN_PARALLEL_POINTS, points > 0)
  end subroutine set_parallel_thresholds

  !> Block t of nb of the items 1 .. n: items lo .. hi (the blocks of a parallel loop over
  !> contiguous blocks, in order; empty when n < nb).
  pure subroutine block_range(n, nb, t, lo, hi)
    integer, intent(in) :: n, nb, t
    integer, intent(out) :: lo, hi
    lo = int((int(n, kind(1_8)) * (t - 1)) / nb) + 1
    hi = int((int(n, kind(1_8)) * t) / nb)
  end subroutine block_range

end module arpy_threads
