!> The f2py boundary of the arpy core: flat routines with explicit-shape
!> arguments and an `info` status code.  Signatures are declared for f2py in
!> _core.pyf; keep the two in step.
!>
!> Lists of unknown length are built inside the core and kept in a hand-off
!> store; the build returns their final size and Python collects them into
!> exactly sized arrays (arpy_result_take).

!> Neighbour list of n particles in d dimensions (x(d, n), cutoffs rc(n)),
!> rule |x_p - x_q| <= min(rc_p, rc_q) + skin.
!> method: 0 = brute force, 1 = uniform cell list.
!> symmetric: 1 = each unordered pair once (row min(p, q) is not guaranteed),
!> 0 = both directions.  bad: 1-based index of an offending particle.
subroutine arpy_neighbors(d, n, x, rc, skin, method, symmetric, nnz, info, bad)
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_METHOD, ARPY_ERR_ALLOC
  use arpy_checks, only: check_particles
  use arpy_csr, only: row_builder, handoff_publish, handoff_size, handoff_clear
  use arpy_brute, only: brute_half
  use arpy_celllist, only: cell_grid, grid_build, grid_half_list
  implicit none
  integer, intent(in) :: d, n, method, symmetric
  real(dp), intent(in) :: x(d, n), rc(n), skin
  integer(i8), intent(out) :: nnz
  integer, intent(out) :: info, bad
  type(row_builder) :: rb
  type(cell_grid) :: g
  integer, allocatable :: perm(:)
  integer :: p, stat

  nnz = -1
  call handoff_clear()
  call check_particles(d, n, x, rc, skin, info, bad)
  if (info /= ARPY_OK) return
  select case (method)
  case (0)
     call brute_half(d, n, x, rc, skin, rb, info)
     if (info /= ARPY_OK) return
     allocate(perm(n), stat=stat)
     if (stat /= 0) then
        info = ARPY_ERR_ALLOC
        return
     end if
     perm = [(p, p = 1, n)]
  case (1)
     call grid_build(d, n, x, rc, skin, g, info)
     if (info /= ARPY_OK) return
     call grid_half_list(g, rb, info)
     if (info /= ARPY_OK) return
     call move_alloc(g%perm, perm)
  case default
     info = ARPY_ERR_METHOD
     return
  end select
  call handoff_publish(rb, perm, symmetric == 0)
  call handoff_size(nnz)
end subroutine arpy_neighbors

!> Collect the list published by the last build into offsets(n+1), indices(nnz).
subroutine arpy_result_take(n, nnz, offsets, indices, info)
  use arpy_kinds, only: i8
  use arpy_csr, only: handoff_take
  implicit none
  integer, intent(in) :: n
  integer(i8), intent(in) :: nnz
  integer(i8), intent(out) :: offsets(n + 1)
  integer, intent(out) :: indices(nnz)
  integer, intent(out) :: info
  call handoff_take(n, nnz, offsets, indices, info)
end subroutine arpy_result_take
