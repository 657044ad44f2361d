!> The f2py boundary of the arpy core, neighbour lists: the search by any method, in free space
!> and periodic boxes (with their images), cross lists, row operations on lists, the k nearest
!> points, cache order and the benchmark hook that only builds.
!>
!> Flat external (non-module) routines with explicit-shape arguments and an `info` status code, as
!> f2py calls them; their signatures are declared for f2py in _core.pyf (the contract with
!> Python): keep the two in step.
!>
!> Lists of unknown length are built inside the core and kept in a hand-off
!> store under a handle of their own; the build returns the handle and the
!> final size, and Python collects the list into exactly sized arrays
!> (arpy_result_take) or drops it (arpy_result_free).

!> Neighbour list of n particles in d dimensions (x(d, n), cutoffs rc(n)) under the cutoff
!> rule `rule` (RULE_* of arpy_kinds): |x_p - x_q| <= min(rc_p, rc_q) + skin,
!> max(rc_p, rc_q) + skin or (rc_p + rc_q) + skin.
!> method: METHOD_BRUTE, METHOD_CELL (uniform cell list) or METHOD_AR (AR
!> cell list, domain = bounding box).
!> symmetric: 1 = each unordered pair once (row min(p, q) is not guaranteed),
!> 0 = both directions.  bad: 1-based index of an offending particle.
!> in_cells: 0 = rows and entries are the particles; 1 = they are the positions of the particles
!> in the search's order, order(a) (0-based) the particle at position a (the list of x(:, order + 1),
!> handed off without a permutation); order is written only then.
!> result: the hand-off handle of the list (0 on error).  order(m): the caller's array, m = n when
!> in_cells = 1 (else ARPY_ERR_SIZE), any m otherwise.
subroutine arpy_neighbors(d, n, x, rc, skin, method, rule, symmetric, in_cells, lh, nnz, m, order, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_SIZE, ARPY_ERR_METHOD, RULE_MIN, RULE_SUM
  use arpy_checks, only: check_particles, particle_extremes
  use arpy_csr, only: row_builder
  use arpy_store, only: handoff_publish, handoff_size
  use arpy_search, only: half_list
  implicit none
  integer, intent(in) :: d, n, method, rule, symmetric, in_cells, m
  real(dp), intent(in) :: x(d, n), rc(n), skin
  integer, intent(out) :: lh
  integer(i8), intent(out) :: nnz
  integer(i8), intent(inout) :: order(m)
  integer, intent(out) :: info, bad
  type(row_builder) :: rb
  type(particle_extremes) :: ext
  integer, allocatable :: perm(:)

  nnz = -1
  lh = 0
  bad = 0
  info = ARPY_OK
  if (in_cells == 1 .and. m /= n) info = ARPY_ERR_SIZE
  if (rule < RULE_MIN .or. rule > RULE_SUM) info = ARPY_ERR_METHOD
  if (info /= ARPY_OK) return
  call check_particles(d, n, x, rc, skin, info, bad, ext)
  if (info /= ARPY_OK) return
  if (in_cells == 1) then
     call half_list(d, n, x, rc, skin, method, rb, perm, info, bad, order, ext, rule)
  else
     call half_list(d, n, x, rc, skin, method, rb, perm, info, bad, ext=ext, rule=rule)
  end if
  if (info /= ARPY_OK) return
  call handoff_publish(rb, symmetric == 0, lh, info, perm)
  if (info /= ARPY_OK) return
  call handoff_size(lh, nnz)
end subroutine arpy_neighbors

!> The list of n particles in a periodic box [lo, hi] (periodic(ax) /= 0 along its periodic
!> axes) by the minimum image.  The uniform list (method "cell") wraps its grid around the box
!> when that leaves at least 3 cells along every periodic axis; otherwise, and for the other
!> methods, the particles' own list gets the pairs of their images (reach rc + skin) queried
!> against them (arpy_search.periodic_list).  Handed off like a free-space list.  The caller has
!> checked that the particles lie in the box and that the largest reach of a pair under the rule
!> is below half the smallest periodic edge.  rule: as for arpy_neighbors (under the max and sum
!> rules, see arpy_search for the images).
subroutine arpy_periodic_neighbors(d, n, x, rc, skin, method, rule, symmetric, lo, hi, periodic, lh, nnz, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_METHOD, METHOD_CELL, RULE_MIN, RULE_SUM
  use arpy_checks, only: check_particles, particle_extremes
  use arpy_celllist, only: cell_grid, grid_build, grid_half_list
  use arpy_csr, only: row_builder
  use arpy_store, only: handoff_publish, handoff_size
  use arpy_search, only: periodic_list, image_count, image_fill, face_band, image_skin
  implicit none
  integer, intent(in) :: d, n, method, rule, symmetric, periodic(d)
  real(dp), intent(in) :: x(d, n), rc(n), skin, lo(d), hi(d)
  integer, intent(out) :: lh
  integer(i8), intent(out) :: nnz
  integer, intent(out) :: info, bad
  type(row_builder) :: rb
  integer, allocatable :: perm(:), src(:), band(:), xpart(:), xidx(:)
  integer(i8), allocatable :: xoff(:)
  real(dp), allocatable :: xg(:, :)
  type(cell_grid) :: g
  type(particle_extremes) :: ext
  integer :: m, stat, nband
  real(dp) :: iskin

  nnz = -1
  lh = 0
  bad = 0
  info = ARPY_OK
  if (rule < RULE_MIN .or. rule > RULE_SUM) info = ARPY_ERR_METHOD
  if (info /= ARPY_OK) return
  call check_particles(d, n, x, rc, skin, info, bad, ext)
  if (info /= ARPY_OK) return
  if (method == METHOD_CELL) then
     ! the uniform grid tiles the box and wraps: no images (at least 3 cells per periodic axis)
     call grid_build(d, n, x, rc, skin, g, info, lo, hi, periodic /= 0, ext, rule)
     if (info /= ARPY_OK) return
     if (all(g%nc(1:d) >= 3 .or. periodic == 0)) then
        call grid_half_list(g, rb, info)
        if (info /= ARPY_OK) return
        call move_alloc(g%perm, perm)
        call handoff_publish(rb, symmetric == 0, lh, info, perm)
        if (info /= ARPY_OK) return
        call handoff_size(lh, nnz)
        return
     end if
  end if
  ! the images of the particles within their reach of a periodic face (candidates: the band
  ! within the largest reach)
  iskin = image_skin(rule, ext%rhi, skin)
  call face_band(d, n, x, ext%rhi + iskin, lo, hi, periodic /= 0, band, nband, info)
  if (info /= ARPY_OK) return
  call image_count(d, n, x, rc, iskin, lo, hi, periodic /= 0, m, band(1:nband))
  allocate(xg(d, m), src(m), stat=stat)
  if (stat /= 0) then
     info = ARPY_ERR_ALLOC
     return
  end if
  call image_fill(d, n, x, rc, iskin, lo, hi, periodic /= 0, m, xg, src, info, band(1:nband))
  if (info /= ARPY_OK) return
  call periodic_list(d, n, x, rc, skin, method, m, xg, src, ext, rb, perm, xpart, xoff, xidx, info, bad, rule)
  if (info /= ARPY_OK) return
  call handoff_publish(rb, symmetric == 0, lh, info, perm, xpart, xoff, xidx)
  if (info /= ARPY_OK) return
  call handoff_size(lh, nnz)
end subroutine arpy_periodic_neighbors

!> Periodic images of n particles with reaches r (cutoff + skin) in the box [lo, hi]
!> (periodic(ax) /= 0 along its periodic axes): their number m (arpy_images_count), then the
!> images xg(d, m) and their sources src(m), 0-based (arpy_images): by shift (s in {-1, 0, 1}
!> per axis, the first axis slowest), then by particle.
subroutine arpy_images_count(d, n, x, r, lo, hi, periodic, m)
  use arpy_kinds, only: dp
  use arpy_search, only: image_count
  implicit none
  integer, intent(in) :: d, n, periodic(d)
  real(dp), intent(in) :: x(d, n), r(n), lo(d), hi(d)
  integer, intent(out) :: m
  call image_count(d, n, x, r, 0.0_dp, lo, hi, periodic /= 0, m)
end subroutine arpy_images_count

subroutine arpy_images(d, n, x, r, lo, hi, periodic, m, xg, src, info)
  use arpy_kinds, only: dp
  use arpy_search, only: image_fill
  implicit none
  integer, intent(in) :: d, n, m, periodic(d)
  real(dp), intent(in) :: x(d, n), r(n), lo(d), hi(d)
  real(dp), intent(out) :: xg(d, m)
  integer, intent(out) :: src(m), info
  call image_fill(d, n, x, r, 0.0_dp, lo, hi, periodic /= 0, m, xg, src, info)
end subroutine arpy_images

!> Collect the list published under handle `lh` into offsets(n+1),
!> indices(nnz), and free it.
subroutine arpy_result_take(lh, n, nnz, offsets, indices, info)
  use arpy_kinds, only: i8
  use arpy_store, only: handoff_take
  implicit none
  integer, intent(in) :: lh, n
  integer(i8), intent(in) :: nnz
  integer(i8), intent(inout) :: offsets(n + 1)
  integer, intent(inout) :: indices(nnz)
  integer, intent(out) :: info
  call handoff_take(lh, n, nnz, offsets, indices, info)
end subroutine arpy_result_take

!> Drop the list published under handle `lh` without collecting it.
subroutine arpy_result_free(lh)
  use arpy_store, only: handoff_free
  implicit none
  integer, intent(in) :: lh
  call handoff_free(lh)
end subroutine arpy_result_free

!> The cross list of m query points against n reference particles by brute force
!> (arpy_brute.brute_cross: rows ascending, the cell lists' test), handed off like a search's
!> list.  bad: the first invalid reference particle, else the first invalid query (info says which
!> check failed; the caller names them).  rule: the cutoff rule (RULE_* of arpy_kinds, no skin).
subroutine arpy_cross_brute(d, m, xq, rcq, n, xr, rcr, rule, lh, nnz, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_METHOD, RULE_MIN, RULE_SUM
  use arpy_checks, only: check_particles
  use arpy_csr, only: row_builder
  use arpy_store, only: handoff_publish, handoff_size
  use arpy_brute, only: brute_cross
  implicit none
  integer, intent(in) :: d, m, n, rule
  real(dp), intent(in) :: xq(d, m), rcq(m), xr(d, n), rcr(n)
  integer, intent(out) :: lh
  integer(i8), intent(out) :: nnz
  integer, intent(out) :: info, bad
  type(row_builder) :: rb
  nnz = -1
  lh = 0
  bad = 0
  info = ARPY_OK
  if (rule < RULE_MIN .or. rule > RULE_SUM) info = ARPY_ERR_METHOD
  if (info /= ARPY_OK) return
  call check_particles(d, n, xr, rcr, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  call check_particles(d, m, xq, rcq, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  call brute_cross(d, m, xq, rcq, n, xr, rcr, rb, info, rule)
  if (info /= ARPY_OK) return
  call handoff_publish(rb, .false., lh, info)
  if (info /= ARPY_OK) return
  call handoff_size(lh, nnz)
end subroutine arpy_cross_brute

!> The rows of the first n of the m particles against all of them under the min rule (no skin),
!> each ascending, with itself = 1 each particle itself: arpy_csr.own_rows of the symmetric list
!> that arpy_search.half_list builds with method.  Handed off like a search's list.
subroutine arpy_source_rows(d, m, x, rc, n, method, itself, lh, nnz, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_SIZE
  use arpy_checks, only: check_particles
  use arpy_csr, only: row_builder, own_rows
  use arpy_store, only: handoff_publish, handoff_size
  use arpy_search, only: half_list
  implicit none
  integer, intent(in) :: d, m, n, method, itself
  real(dp), intent(in) :: x(d, m), rc(m)
  integer, intent(out) :: lh
  integer(i8), intent(out) :: nnz
  integer, intent(out) :: info, bad
  type(row_builder) :: rb, rows
  integer, allocatable :: perm(:)
  nnz = -1
  lh = 0
  call check_particles(d, m, x, rc, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  if (n < 0 .or. n > m .or. itself < 0 .or. itself > 1) then
     info = ARPY_ERR_SIZE
     return
  end if
  call half_list(d, m, x, rc, 0.0_dp, method, rb, perm, info, bad)
  if (info /= ARPY_OK) return
  if (allocated(perm)) then
     call own_rows(n, m, rb%off, rb%idx, itself == 1, rows, info, perm)
  else
     call own_rows(n, m, rb%off, rb%idx, itself == 1, rows, info)
  end if
  if (info /= ARPY_OK) return
  call handoff_publish(rows, .false., lh, info)
  if (info /= ARPY_OK) return
  call handoff_size(lh, nnz)
end subroutine arpy_source_rows

!> The entries of a cross list (queries xq, cutoffs rq; sources xs, cutoffs rs) still within the min
!> rule at these positions (arpy_search.filter_rows): off_out(m + 1), idx_out (the first
!> off_out(m + 1) entries).
subroutine arpy_filter_rows(d, m, xq, rq, ns, xs, rs, nnz, off, idx, off_out, idx_out, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK
  use arpy_checks, only: check_csr
  use arpy_search, only: filter_rows
  implicit none
  integer, intent(in) :: d, m, ns
  real(dp), intent(in) :: xq(d, m), rq(m), xs(d, ns), rs(ns)
  integer(i8), intent(in) :: nnz, off(m + 1)
  integer, intent(in) :: idx(nnz)
  integer(i8), intent(out) :: off_out(m + 1)
  integer, intent(out) :: idx_out(nnz), info, bad
  call check_csr(m, ns, nnz, off, idx, info, bad)
  if (info /= ARPY_OK) return
  call filter_rows(d, m, xq, rq, ns, xs, rs, nnz, off, idx, off_out, idx_out)
end subroutine arpy_filter_rows

!> Each row's entries sorted by the position of their index (pos: one int64 per column index).
subroutine arpy_sort_rows(n, nnz, off, idx, nr, pos, info, bad)
  use arpy_kinds, only: i8, ARPY_OK
  use arpy_checks, only: check_csr
  use arpy_csr, only: sort_rows
  implicit none
  integer, intent(in) :: n, nr
  integer(i8), intent(in) :: nnz, off(n + 1), pos(nr)
  integer, intent(inout) :: idx(nnz)
  integer, intent(out) :: info, bad
  call check_csr(n, nr, nnz, off, idx, info, bad)
  if (info /= ARPY_OK) return
  call sort_rows(n, nnz, off, idx, nr, pos)
end subroutine arpy_sort_rows

!> sorted = 1 if each row's entries are already in increasing order of pos (the order arpy_sort_rows
!> gives them), else 0.
subroutine arpy_rows_sorted(n, nnz, off, idx, nr, pos, sorted, info, bad)
  use arpy_kinds, only: i8, ARPY_OK
  use arpy_checks, only: check_csr
  use arpy_csr, only: rows_sorted
  implicit none
  integer, intent(in) :: n, nr
  integer(i8), intent(in) :: nnz, off(n + 1), pos(nr)
  integer, intent(in) :: idx(nnz)
  integer, intent(out) :: sorted, info, bad
  sorted = 0
  call check_csr(n, nr, nnz, off, idx, info, bad)
  if (info /= ARPY_OK) return
  if (rows_sorted(n, nnz, off, idx, nr, pos)) sorted = 1
end subroutine arpy_rows_sorted

!> The k points of x nearest to each point of y by the minimum image along the axes with
!> period(l) > 0 (arpy_knn.knn_query): distances dist(k, m) and 0-based indices idx(k, m), nearest
!> first, equal distances by index.  info = ARPY_ERR_SIZE unless 1 <= k <= n.
subroutine arpy_knn(d, n, x, m, y, k, period, dist, idx, info)
  use arpy_kinds, only: dp
  use arpy_knn, only: knn_query
  implicit none
  integer, intent(in) :: d, n, m, k
  real(dp), intent(in) :: x(d, n), y(d, m), period(d)
  real(dp), intent(out) :: dist(k, m)
  integer, intent(out) :: idx(k, m), info
  call knn_query(d, n, x, m, y, k, period, dist, idx, info)
end subroutine arpy_knn

!> The least distance between two of the points x (n >= 2) by the minimum image along the axes with
!> period(l) > 0 (arpy_knn.min_distance).  info = ARPY_ERR_SIZE for fewer than two points.
subroutine arpy_min_distance(d, n, x, period, dmin, info)
  use arpy_kinds, only: dp
  use arpy_knn, only: min_distance
  implicit none
  integer, intent(in) :: d, n
  real(dp), intent(in) :: x(d, n), period(d)
  real(dp), intent(out) :: dmin
  integer, intent(out) :: info
  call min_distance(d, n, x, period, dmin, info)
end subroutine arpy_min_distance

!> Cache order: perm (0-based) sorts the points along the Morton curve of cells 1/s wide from lo
!> (arpy_order); x must be finite (checked by the caller).
subroutine arpy_cache_order(d, n, x, lo, s, perm, info)
  use arpy_kinds, only: dp
  use arpy_order, only: morton_order
  implicit none
  integer, intent(in) :: d, n
  real(dp), intent(in) :: x(d, n), lo(d), s
  integer, intent(out) :: perm(n), info
  call morton_order(d, n, x, lo, s, perm, info)
end subroutine arpy_cache_order

!> Benchmark hook: build the search structure of a method (METHOD_CELL: the
!> uniform cell grid, METHOD_AR: the AR tree) and discard it, so build and list
!> times can be separated.
subroutine arpy_build_only(d, n, x, rc, method, info, bad)
  use arpy_kinds, only: dp, ARPY_OK, ARPY_ERR_METHOD, METHOD_CELL, METHOD_AR
  use arpy_checks, only: check_particles
  use arpy_celllist, only: cell_grid, grid_build
  use arpy_artree, only: ar_tree
  use arpy_arbuild, only: ar_build
  implicit none
  integer, intent(in) :: d, n, method
  real(dp), intent(in) :: x(d, n), rc(n)
  integer, intent(out) :: info, bad
  type(cell_grid) :: g
  type(ar_tree) :: t
  real(dp) :: nodomain(d)
  call check_particles(d, n, x, rc, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  nodomain = 0.0_dp
  select case (method)
  case (METHOD_CELL)
     call grid_build(d, n, x, rc, 0.0_dp, g, info)
  case (METHOD_AR)
     call ar_build(d, n, x, rc, 0.0_dp, .false., nodomain, nodomain, t, info, bad, for_lists=.true.)
  case default
     info = ARPY_ERR_METHOD
  end select
end subroutine arpy_build_only

!> How crowded the sampled particles x(:, 1), x(:, 1 + step), ... of x(d, n) are on a grid of cells of
!> edge g from lo, nc(a) along axis a (arpy_crowding.crowding_counts): block(j), of the j-th of them,
!> the others in the 3**d cells around its own; ns = (n - 1) / step + 1.
subroutine arpy_crowding_counts(d, n, x, step, lo, g, nc, ns, block, info)
  use arpy_kinds, only: dp, i8
  use arpy_crowding, only: crowding_counts
  implicit none
  integer, intent(in) :: d, n, step, nc(d), ns
  real(dp), intent(in) :: x(d, n), lo(d), g
  integer(i8), intent(out) :: block(ns)
  integer, intent(out) :: info
  call crowding_counts(d, n, x, step, lo, g, nc, ns, block, info)
end subroutine arpy_crowding_counts

!> The statistics auto_work's model weighs (arpy_crowding.auto_terms).
subroutine arpy_auto_terms(d, n, x, rc, skin, knob, rule, w, info)
  use arpy_kinds, only: dp
  use arpy_crowding, only: auto_terms, NKNOB
  implicit none
  integer, intent(in) :: d, n, rule
  real(dp), intent(in) :: x(d, n), rc(n), skin, knob(NKNOB)
  real(dp), intent(out) :: w(6)
  integer, intent(out) :: info
  call auto_terms(d, n, x, rc, skin, knob, rule, w, info)
end subroutine arpy_auto_terms
