!> The f2py boundary of the arpy core: flat routines with explicit-shape
!> arguments and an `info` status code.  Signatures are declared for f2py in
!> _core.pyf; keep the two in step.
!>
!> Lists of unknown length are built inside the core and kept in a hand-off
!> store under a handle of their own; the build returns the handle and the
!> final size, and Python collects the list into exactly sized arrays
!> (arpy_result_take) or drops it (arpy_result_free).

!> Neighbour list of n particles in d dimensions (x(d, n), cutoffs rc(n)),
!> rule |x_p - x_q| <= min(rc_p, rc_q) + skin.
!> method: METHOD_BRUTE, METHOD_CELL (uniform cell list) or METHOD_AR (AR
!> cell list, domain = bounding box).
!> symmetric: 1 = each unordered pair once (row min(p, q) is not guaranteed),
!> 0 = both directions.  bad: 1-based index of an offending particle.
!> in_cells: 0 = rows and entries are the particles; 1 = they are the positions of the particles
!> in the search's order, order(a) (0-based) the particle at position a (the list of x(:, order + 1),
!> handed off without a permutation); order is written only then.
!> result: the hand-off handle of the list (0 on error).  order(m): the caller's array, m = n when
!> in_cells = 1 (else ARPY_ERR_SIZE), any m otherwise.
subroutine arpy_neighbors(d, n, x, rc, skin, method, symmetric, in_cells, lh, nnz, m, order, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_SIZE
  use arpy_checks, only: check_particles, particle_extremes
  use arpy_csr, only: row_builder, handoff_publish, handoff_size
  use arpy_search, only: half_list
  implicit none
  integer, intent(in) :: d, n, method, symmetric, in_cells, m
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
  if (info /= ARPY_OK) return
  call check_particles(d, n, x, rc, skin, info, bad, ext)
  if (info /= ARPY_OK) return
  if (in_cells == 1) then
     call half_list(d, n, x, rc, skin, method, rb, perm, info, bad, order, ext)
  else
     call half_list(d, n, x, rc, skin, method, rb, perm, info, bad, ext=ext)
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
!> checked that the particles lie in the box and that max(rc) + skin is below half the smallest
!> periodic edge.
subroutine arpy_periodic_neighbors(d, n, x, rc, skin, method, symmetric, lo, hi, periodic, lh, nnz, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC, METHOD_CELL
  use arpy_checks, only: check_particles, particle_extremes
  use arpy_celllist, only: cell_grid, grid_build, grid_half_list
  use arpy_csr, only: row_builder, handoff_publish, handoff_size
  use arpy_search, only: periodic_list, image_count, image_fill, face_band
  implicit none
  integer, intent(in) :: d, n, method, symmetric, periodic(d)
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

  nnz = -1
  lh = 0
  call check_particles(d, n, x, rc, skin, info, bad, ext)
  if (info /= ARPY_OK) return
  if (method == METHOD_CELL) then
     ! the uniform grid tiles the box and wraps: no images (at least 3 cells per periodic axis)
     call grid_build(d, n, x, rc, skin, g, info, lo, hi, periodic /= 0, ext)
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
  call face_band(d, n, x, ext%rhi + skin, lo, hi, periodic /= 0, band, nband, info)
  if (info /= ARPY_OK) return
  call image_count(d, n, x, rc, skin, lo, hi, periodic /= 0, m, band(1:nband))
  allocate(xg(d, m), src(m), stat=stat)
  if (stat /= 0) then
     info = ARPY_ERR_ALLOC
     return
  end if
  call image_fill(d, n, x, rc, skin, lo, hi, periodic /= 0, m, xg, src, info, band(1:nband))
  if (info /= ARPY_OK) return
  call periodic_list(d, n, x, rc, skin, method, m, xg, src, ext, rb, perm, xpart, xoff, xidx, info, bad)
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
  use arpy_csr, only: handoff_take
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
  use arpy_csr, only: handoff_free
  implicit none
  integer, intent(in) :: lh
  call handoff_free(lh)
end subroutine arpy_result_free

!> Build an AR tree (Algorithms 1-2) and keep it under a handle.
!> has_domain = 1: the domain is [lo, hi] (particles outside: error);
!> 0: the bounding box (lo, hi ignored).  Returns the numbers of leaf cells
!> and of hash entries, the deepest level and the cube edge D_m.
subroutine arpy_ar_create(d, n, x, rc, skin, has_domain, lo, hi, handle, nleaf, nkey, &
     maxlevel, dm, info, bad)
  use arpy_kinds, only: dp, ARPY_OK, ARPY_ERR_RANGE, RANGE_EXP
  use arpy_checks, only: check_particles
  use arpy_artree, only: ar_tree, ar_ncells, ar_nleaves
  use arpy_arbuild, only: ar_build
  use arpy_registry, only: registry_new, registry_get, registry_free
  implicit none
  integer, intent(in) :: d, n, has_domain
  real(dp), intent(in) :: x(d, n), rc(n), skin, lo(d), hi(d)
  integer, intent(out) :: handle, nleaf, nkey, maxlevel, info, bad
  real(dp), intent(out) :: dm
  type(ar_tree), pointer :: t
  handle = 0
  nleaf = 0
  nkey = 0
  maxlevel = -1
  dm = 0.0_dp
  call check_particles(d, n, x, rc, skin, info, bad)
  if (info /= ARPY_OK) return
  if (has_domain /= 0) then
     if (max(maxval(abs(lo)), maxval(abs(hi))) > 2.0_dp**RANGE_EXP) then
        info = ARPY_ERR_RANGE
        return
     end if
  end if
  call registry_new(handle, info)
  if (info /= ARPY_OK) return
  call registry_get(handle, t, info)
  call ar_build(d, n, x, rc, skin, has_domain /= 0, lo, hi, t, info, bad)
  if (info /= ARPY_OK) then
     call registry_free(handle)
     handle = 0
     return
  end if
  nleaf = ar_nleaves(t)
  nkey = ar_ncells(t)
  maxlevel = t%maxlevel
  dm = t%dm
end subroutine arpy_ar_create

!> Copy the tables of an AR tree: per slot the particle (0-based) and its
!> level; per leaf cell its J and slot range [first, last) (0-based); per
!> hash entry its J, own-level slot range [first, last) (empty if none) and
!> finer flag (1 if the cell's region holds particles of a finer level).
subroutine arpy_ar_tables(handle, n, nleaf, nkey, perm, level, leaf_key, leaf_first, &
     leaf_last, keys, first, last, finer, lo, info)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_SIZE
  use arpy_arhash, only: entry_first, entry_last, entry_finer
  use arpy_artree, only: ar_tree, ar_ncells, ar_entries, ar_nleaves, ar_leaves
  use arpy_registry, only: registry_get
  implicit none
  integer, intent(in) :: handle, n, nleaf, nkey
  integer, intent(out) :: perm(n), level(n), leaf_first(nleaf), leaf_last(nleaf)
  integer(i8), intent(out) :: leaf_key(nleaf), keys(nkey)
  integer, intent(out) :: first(nkey), last(nkey), finer(nkey)
  real(dp), intent(out) :: lo(3)
  integer, intent(out) :: info
  type(ar_tree), pointer :: t
  integer(i8) :: vals(nkey)
  integer :: li, leaf_level(nleaf)
  call registry_get(handle, t, info)
  if (info /= ARPY_OK) return
  if (n /= t%n .or. nleaf /= ar_nleaves(t) .or. nkey /= ar_ncells(t)) then
     info = ARPY_ERR_SIZE
     return
  end if
  perm = t%perm - 1
  call ar_leaves(t, leaf_key, leaf_first, leaf_last, leaf_level)
  do li = 1, nleaf                   ! every slot lies in exactly one leaf cell
     level(leaf_first(li):leaf_last(li)) = leaf_level(li)
  end do
  leaf_first = leaf_first - 1
  lo = t%lo
  call ar_entries(t, keys, vals)
  first = entry_first(vals) - 1
  last = max(entry_last(vals), first)
  finer = merge(1, 0, entry_finer(vals))
end subroutine arpy_ar_tables

!> Algorithm 3 on a kept tree: publish its Verlet list (symmetric = 1: each
!> pair once, 0: both directions) under handle `lh` for arpy_result_take.
subroutine arpy_ar_verlet(handle, symmetric, nb, bits, lh, nnz, info)
  use arpy_kinds, only: i8, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_SIZE
  use arpy_csr, only: row_builder, handoff_publish, handoff_size, rb_drop_ghost_pairs
  use arpy_artree, only: ar_tree
  use arpy_arlists, only: ar_half_list, ar_full_list
  use arpy_registry, only: registry_get
  implicit none
  integer, intent(in) :: handle, symmetric       ! 1: symmetric; 0: full, by expansion; 2: full, built directly
  integer, intent(in) :: nb                      ! 0, or n: the halo bit strings (0: a real particle)
  integer, intent(in) :: bits(nb)
  integer, intent(out) :: lh
  integer(i8), intent(out) :: nnz
  integer, intent(out) :: info
  type(ar_tree), pointer :: t
  type(row_builder) :: rb
  integer, allocatable :: perm(:)
  integer :: stat
  nnz = -1
  lh = 0
  call registry_get(handle, t, info)
  if (info /= ARPY_OK) return
  if (nb /= 0 .and. nb /= t%n) then
     info = ARPY_ERR_SIZE
     return
  end if
  if (symmetric == 2) then
     call ar_full_list(t, rb, info)
  else
     call ar_half_list(t, rb, info)
  end if
  if (info /= ARPY_OK) return
  if (nb /= 0) call rb_drop_ghost_pairs(rb, t%perm, bits)
  allocate(perm(t%n), source=t%perm, stat=stat)
  if (stat /= 0) then
     info = ARPY_ERR_ALLOC
     return
  end if
  call handoff_publish(rb, symmetric == 0, lh, info, perm)
  if (info /= ARPY_OK) return
  call handoff_size(lh, nnz)
end subroutine arpy_ar_verlet

!> Cross-set list of m query points against a kept tree (rule
!> min(rcq_i, rc_q)); publishes rows = queries under handle `lh`.
subroutine arpy_ar_cross(handle, d, m, xq, rcq, lh, nnz, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK
  use arpy_checks, only: check_particles
  use arpy_csr, only: row_builder, handoff_publish, handoff_size
  use arpy_artree, only: ar_tree
  use arpy_arlists, only: ar_cross_list
  use arpy_registry, only: registry_get
  implicit none
  integer, intent(in) :: handle, d, m
  real(dp), intent(in) :: xq(d, m), rcq(m)
  integer, intent(out) :: lh
  integer(i8), intent(out) :: nnz
  integer, intent(out) :: info, bad
  type(ar_tree), pointer :: t
  type(row_builder) :: rb
  nnz = -1
  lh = 0
  bad = 0
  call registry_get(handle, t, info, d)
  if (info /= ARPY_OK) return
  call check_particles(d, m, xq, rcq, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  call ar_cross_list(t, m, xq, rcq, rb, info)
  if (info /= ARPY_OK) return
  call handoff_publish(rb, .false., lh, info)
  if (info /= ARPY_OK) return
  call handoff_size(lh, nnz)
end subroutine arpy_ar_cross

!> The cross list of m query points against n reference particles by brute force
!> (arpy_brute.brute_cross: rows ascending, the cell lists' test), handed off like a search's
!> list.  bad: the first invalid reference particle, else the first invalid query (info says which
!> check failed; the caller names them).
subroutine arpy_cross_brute(d, m, xq, rcq, n, xr, rcr, lh, nnz, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK
  use arpy_checks, only: check_particles
  use arpy_csr, only: row_builder, handoff_publish, handoff_size
  use arpy_brute, only: brute_cross
  implicit none
  integer, intent(in) :: d, m, n
  real(dp), intent(in) :: xq(d, m), rcq(m), xr(d, n), rcr(n)
  integer, intent(out) :: lh
  integer(i8), intent(out) :: nnz
  integer, intent(out) :: info, bad
  type(row_builder) :: rb
  nnz = -1
  lh = 0
  call check_particles(d, n, xr, rcr, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  call check_particles(d, m, xq, rcq, 0.0_dp, info, bad)
  if (info /= ARPY_OK) return
  call brute_cross(d, m, xq, rcq, n, xr, rcr, rb, info)
  if (info /= ARPY_OK) return
  call handoff_publish(rb, .false., lh, info)
  if (info /= ARPY_OK) return
  call handoff_size(lh, nnz)
end subroutine arpy_cross_brute

!> Release a kept tree.
subroutine arpy_ar_free(handle)
  use arpy_registry, only: registry_free
  implicit none
  integer, intent(in) :: handle
  call registry_free(handle)
end subroutine arpy_ar_free

!> Op1-Op5 on a kept tree, for m cells or points at once.
!> op = AR_OP_FIND_CELL (Op1): keys(i) = J of the level-k cell containing
!>      pts(:, i) (-1 outside)
!> op = AR_OP_LOOKUP (Op2): for J = keys(i): out(1:3, i) = own-level slot range
!>      [first, last) (0-based, empty if none) and finer flag; out(4, i) = 1 if
!>      the cell exists (holds particles on its level or below)
!> op = AR_OP_CHILDREN (Op3): nbr(1:2**d, i) = children of keys(i)
!> op = AR_OP_PARENT (Op4): nbr(1, i) = parent of keys(i) (0 for the root)
!> op = AR_OP_NEIGHBORS (Op5): nbr(1:cnt(i), i) = neighbours of keys(i) inside
!>      the domain
subroutine arpy_ar_ops(handle, op, d, m, pts, k, keys, out, nbr, cnt, info)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_METHOD
  use arpy_artree, only: ar_tree
  use arpy_arops, only: ar_find_cell, ar_lookup, ar_children, ar_parent, ar_neighbor_cells, &
       AR_OP_FIND_CELL, AR_OP_LOOKUP, AR_OP_CHILDREN, AR_OP_PARENT, AR_OP_NEIGHBORS
  use arpy_registry, only: registry_get
  implicit none
  integer, intent(in) :: handle, op, d, m, k
  real(dp), intent(in) :: pts(d, m)
  integer(i8), intent(inout) :: keys(m)
  integer, intent(out) :: out(4, m), cnt(m)
  integer(i8), intent(out) :: nbr(26, m)
  integer, intent(out) :: info
  type(ar_tree), pointer :: t
  integer :: i, first, last
  logical :: found, finer
  out = 0
  nbr = 0
  cnt = 0
  call registry_get(handle, t, info, d)
  if (info /= ARPY_OK) return
  do i = 1, m
     select case (op)
     case (AR_OP_FIND_CELL)
        keys(i) = ar_find_cell(t, pts(:, i), k)
     case (AR_OP_LOOKUP)
        call ar_lookup(t, keys(i), found, first, last, finer)
        out(1, i) = first - 1
        out(2, i) = max(last, first - 1)
        out(3, i) = merge(1, 0, finer)
        out(4, i) = merge(1, 0, found)
     case (AR_OP_CHILDREN)
        call ar_children(d, keys(i), nbr(:, i))
        cnt(i) = 2**d
     case (AR_OP_PARENT)
        nbr(1, i) = ar_parent(d, keys(i))
        cnt(i) = 1
     case (AR_OP_NEIGHBORS)
        call ar_neighbor_cells(d, keys(i), nbr(:, i), cnt(i))
     case default
        info = ARPY_ERR_METHOD
        return
     end select
  end do
end subroutine arpy_ar_ops

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

!> Threads of the core's parallel loops: n > 0 threads, n <= 0 OpenMP's default.
subroutine arpy_set_threads(n)
  use arpy_threads, only: set_threads
  implicit none
  integer, intent(in) :: n
  call set_threads(n)
end subroutine arpy_set_threads

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

!> Huge-page advice for the core's large arrays: on /= 0 on, 0 off; was: the setting before.
subroutine arpy_set_huge_pages(on, was)
  use arpy_memory, only: set_huge_pages, huge_pages_on
  implicit none
  integer, intent(in) :: on
  integer, intent(out) :: was
  was = merge(1, 0, huge_pages_on())
  call set_huge_pages(on /= 0)
end subroutine arpy_set_huge_pages

!> The threads the next parallel loop of this thread will use, and the processors OpenMP sees.
subroutine arpy_get_threads(n, max_threads)
  use arpy_threads, only: team_size, core_count
  implicit none
  integer, intent(out) :: n, max_threads
  n = team_size()
  max_threads = core_count()
end subroutine arpy_get_threads

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

!> The rows of the first n of the m particles against all of them under the min rule (no skin),
!> each ascending, with itself = 1 each particle itself: arpy_csr.own_rows of the symmetric list
!> that arpy_search.half_list builds with method.  Handed off like a search's list.
subroutine arpy_source_rows(d, m, x, rc, n, method, itself, lh, nnz, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_SIZE
  use arpy_checks, only: check_particles
  use arpy_csr, only: row_builder, own_rows, handoff_publish, handoff_size
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
