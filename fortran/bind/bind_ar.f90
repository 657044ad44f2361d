!> The f2py boundary of the arpy core, AR trees kept between calls under a handle (arpy.ARCellList):
!> build, tables, Verlet and cross lists (handed off as in bind_lists.f90, collected by
!> arpy_result_take), the cell operations Op1-Op5, release.
!>
!> Flat external (non-module) routines with explicit-shape arguments and an `info` status code, as
!> f2py calls them; their signatures are declared for f2py in _core.pyf (the contract with
!> Python): keep the two in step.

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
  use arpy_csr, only: row_builder, rb_drop_ghost_pairs
  use arpy_store, only: handoff_publish, handoff_size
  use arpy_artree, only: ar_tree
  use arpy_arlists, only: ar_half_list
  use arpy_arquery, only: ar_full_list
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
  use arpy_csr, only: row_builder
  use arpy_store, only: handoff_publish, handoff_size
  use arpy_artree, only: ar_tree
  use arpy_arquery, only: ar_cross_list
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

!> Release a kept tree.
subroutine arpy_ar_free(handle)
  use arpy_registry, only: registry_free
  implicit none
  integer, intent(in) :: handle
  call registry_free(handle)
end subroutine arpy_ar_free
