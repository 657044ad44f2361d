!> The scan of Eq. 2.9 (Reboux et al. 2012, implicit reading): for each particle p,
!>
!>   D_p = min( D~_p, min over sources q of max(D~_q, |x_p - x_q| / r*) ),
!>
!> the largest resolution no source within p's own reach r* D_p asks to be finer
!> (arpy/resolution.py, graded_resolution, derives it).
!>
!> Sources are binned on a uniform grid (cell edge r* times the smallest source D~, coarser
!> if that would make more than CELLS_PER_SOURCE cells per source) and each particle scans the
!> cells ring by ring around its own: after ring r every unvisited source lies at least r h
!> away, and a source at distance s >= r* D cannot lower D (max(D~_q, s / r*) >= D), so the scan
!> stops once r h >= r* D.  A particle whose reach spans more than RINGS rings (a coarse one where
!> D~ grades from fine to coarse: its disc holds thousands of cells) goes on by blocks of BLOCK_CELLS^d
!> cells, ring by ring of blocks, each block with the box of its sources and their smallest D~: a
!> block is skipped when max(smallest D~, distance to its box / r*) is at least the current D_p (no
!> source in it can lower D_p), so the coarse sources around it (D~ too large) and the far fine ones
!> drop out a block at a time.  The box bound is computed like a source's distance (each axis's gap no
!> larger than the difference to any source in the box, in rounding too, squared and summed in the
!> same order), so a skipped block never held a lower value.  The minimum over q is exact whatever the
!> visiting order (a source seen twice changes nothing); distances are
!> sqrt(((0 + dx1**2) + dx2**2) + dx3**2), the sum order of scipy's cKDTree, so the result is
!> bitwise that of a k-nearest-neighbour scan.  Each D_p is written by one iteration of a
!> parallel loop: bitwise the same for any number of threads.
module arpy_grade
  use arpy_kinds, only: dp, i8
  use arpy_threads, only: team_size, MIN_PARALLEL_POINTS
  use arpy_csr, only: sort_run
  implicit none
  private

  public :: grade_scan, shepard_rows

  !> at most this many grid cells per source (plus a few), so memory stays O(m)
  integer, parameter :: CELLS_PER_SOURCE = 4
  !> rings of cells a particle scans before it goes on by blocks
  integer, parameter :: RINGS = 2
  !> cells per axis of a block
  integer, parameter :: BLOCK_CELLS = 8

contains

  !> D(p) for the particles x(:, 1:n) with targets target(1:n) over the sources src(:, 1:m)
  !> with targets st(1:m) (every value > 0 and finite, d in 1..3, m >= 1 when n >= 1).
  subroutine grade_scan(d, n, x, target, m, src, st, rstar, dout)
    integer, intent(in) :: d, n, m
    real(dp), intent(in) :: x(d, n), target(n), src(d, m), st(m), rstar
    real(dp), intent(out) :: dout(n)
    real(dp) :: lo(3), hi(3), h, vol, tol, xp(3), dp_
    real(dp), allocatable :: sx(:, :), sst(:), blo(:, :), bhi(:, :), bmin(:)
    integer :: nc(3), nb(3), c(3), p, q, a, r, i, j, jl, jh, kl, kh, t, ncell, b
    integer, allocatable :: start(:), cell(:)

    if (n == 0) return
    lo = 0.0_dp
    hi = 0.0_dp
    lo(1:d) = min(minval(src, dim=2), minval(x, dim=2))
    hi(1:d) = max(maxval(src, dim=2), maxval(x, dim=2))
    ! cell edge: the finest reach, unless that makes too many cells
    h = rstar * minval(st)
    vol = 1.0_dp
    do a = 1, d
       vol = vol * max(hi(a) - lo(a), h)
    end do
    if (vol / h**d > real(CELLS_PER_SOURCE, dp) * m + 64.0_dp) &
         h = (vol / (real(CELLS_PER_SOURCE, dp) * m + 64.0_dp))**(1.0_dp / d)
    nc = 1
    do a = 1, d
       nc(a) = int(min((hi(a) - lo(a)) / h, real(CELLS_PER_SOURCE * m + 64, dp))) + 1
    end do
    ncell = nc(1) * nc(2) * nc(3)
    ! rounding slack of the cell bounds (a coordinate's cell is found to a few ulps of |x|)
    tol = 1.0e-12_dp * (maxval(abs(lo)) + maxval(abs(hi)) + h)

    ! counting sort of the sources by cell (cell id: k fastest, so a range of k is contiguous)
    allocate(start(ncell + 1), cell(m), sx(3, m), sst(m))
    start = 0
    do q = 1, m
       c = cell_of(d, src(:, q), lo, h, nc)
       cell(q) = id(c(1), c(2), c(3))
       start(cell(q) + 1) = start(cell(q) + 1) + 1
    end do
    start(1) = 1
    do i = 2, ncell + 1
       start(i) = start(i) + start(i - 1)
    end do
    sx = 0.0_dp
    do q = 1, m
       t = start(cell(q))
       sx(1:d, t) = src(:, q)
       sst(t) = st(q)
       start(cell(q)) = t + 1
    end do
    do i = ncell + 1, 2, -1
       start(i) = start(i - 1)
    end do
    start(1) = 1
    ! the blocks: the box of their sources and the smallest target (empty: smallest target huge)
    nb = (nc + BLOCK_CELLS - 1) / BLOCK_CELLS
    allocate(blo(3, nb(1) * nb(2) * nb(3)), bhi(3, nb(1) * nb(2) * nb(3)), bmin(nb(1) * nb(2) * nb(3)))
    blo = huge(1.0_dp)
    bhi = -huge(1.0_dp)
    bmin = huge(1.0_dp)
    do q = 1, m                                        ! (cell(q) - 1 = (i nc(2) + j) nc(3) + k)
       t = cell(q) - 1
       b = bid(t / (nc(2) * nc(3)) / BLOCK_CELLS, mod(t / nc(3), nc(2)) / BLOCK_CELLS, mod(t, nc(3)) / BLOCK_CELLS)
       do a = 1, d
          blo(a, b) = min(blo(a, b), src(a, q))
          bhi(a, b) = max(bhi(a, b), src(a, q))
       end do
       bmin(b) = min(bmin(b), st(q))
    end do

    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_POINTS) schedule(dynamic, 128) &
    !$omp private(p, xp, c, dp_, r, i, j, jl, jh, kl, kh)
    do p = 1, n
       xp = 0.0_dp
       xp(1:d) = x(:, p)
       c = cell_of(d, x(:, p), lo, h, nc)
       dp_ = target(p)
       r = 0
       do
          kl = max(c(3) - r, 0)
          kh = min(c(3) + r, nc(3) - 1)
          do i = max(c(1) - r, 0), min(c(1) + r, nc(1) - 1)
             if (abs(i - c(1)) == r) then                  ! a face of the ring: every cell
                jl = max(c(2) - r, 0)
                jh = min(c(2) + r, nc(2) - 1)
                if (kl == 0 .and. kh == nc(3) - 1) then    ! whole columns: one run of cells
                   call visit(d, xp, sx, sst, start(id(i, jl, kl)), start(id(i, jh, kh) + 1) - 1, rstar, dp_)
                else
                   do j = jl, jh
                      call visit(d, xp, sx, sst, start(id(i, j, kl)), start(id(i, j, kh) + 1) - 1, rstar, dp_)
                   end do
                end if
             else                                          ! the faces j = c2 -+ r, then k = c3 -+ r
                if (c(2) - r >= 0) &
                     call visit(d, xp, sx, sst, start(id(i, c(2) - r, kl)), start(id(i, c(2) - r, kh) + 1) - 1, &
                     rstar, dp_)
                if (c(2) + r <= nc(2) - 1) &
                     call visit(d, xp, sx, sst, start(id(i, c(2) + r, kl)), start(id(i, c(2) + r, kh) + 1) - 1, &
                     rstar, dp_)
                if (c(3) - r >= 0 .or. c(3) + r <= nc(3) - 1) then
                   do j = max(c(2) - r + 1, 0), min(c(2) + r - 1, nc(2) - 1)
                      if (c(3) - r >= 0) call visit(d, xp, sx, sst, start(id(i, j, c(3) - r)), &
                           start(id(i, j, c(3) - r) + 1) - 1, rstar, dp_)
                      if (c(3) + r <= nc(3) - 1) call visit(d, xp, sx, sst, start(id(i, j, c(3) + r)), &
                           start(id(i, j, c(3) + r) + 1) - 1, rstar, dp_)
                   end do
                end if
             end if
          end do
          ! every source beyond ring r lies at least r h away
          if (all(c - r <= 0 .and. c + r >= nc - 1)) exit
          if (r * h - tol >= rstar * dp_) exit
          if (r == RINGS) then                          ! a wide reach: the rest by blocks
             call by_blocks(xp, c / BLOCK_CELLS, dp_)
             exit
          end if
          r = r + 1
       end do
       dout(p) = dp_
    end do
    !$omp end parallel do

  contains

    !> the 1-based id of cell (i, j, k)
    pure integer function id(i, j, k)
      integer, intent(in) :: i, j, k
      id = (i * nc(2) + j) * nc(3) + k + 1
    end function id

    !> the 1-based id of block (i, j, k)
    pure integer function bid(i, j, k)
      integer, intent(in) :: i, j, k
      bid = (i * nb(2) + j) * nb(3) + k + 1
    end function bid

    !> Lower dp_ (particle at xp, in block bc) by the sources of the blocks, ring by ring of blocks
    !> around bc, skipping a block that cannot lower it; after ring R every unvisited source lies at
    !> least R BLOCK_CELLS h away.
    subroutine by_blocks(xp, bc, dp_)
      real(dp), intent(in) :: xp(3)
      integer, intent(in) :: bc(3)
      real(dp), intent(inout) :: dp_
      integer :: rr, u, v, w
      rr = 0
      do
         do u = max(bc(1) - rr, 0), min(bc(1) + rr, nb(1) - 1)
            do v = max(bc(2) - rr, 0), min(bc(2) + rr, nb(2) - 1)
               if (max(abs(u - bc(1)), abs(v - bc(2))) == rr) then      ! a face of the ring: every block
                  do w = max(bc(3) - rr, 0), min(bc(3) + rr, nb(3) - 1)
                     call visit_block(xp, u, v, w, dp_)
                  end do
               else                                                      ! else its two faces along axis 3
                  if (bc(3) - rr >= 0) call visit_block(xp, u, v, bc(3) - rr, dp_)
                  if (bc(3) + rr <= nb(3) - 1) call visit_block(xp, u, v, bc(3) + rr, dp_)
               end if
            end do
         end do
         if (all(bc - rr <= 0 .and. bc + rr >= nb - 1)) exit
         if (rr * BLOCK_CELLS * h - tol >= rstar * dp_) exit
         rr = rr + 1
      end do
    end subroutine by_blocks

    !> Visit the cells of block (u, v, w) unless it cannot lower dp_ (particle at xp).
    subroutine visit_block(xp, u, v, w, dp_)
      real(dp), intent(in) :: xp(3)
      integer, intent(in) :: u, v, w
      real(dp), intent(inout) :: dp_
      integer :: b, ci, cj, k0, k1
      b = bid(u, v, w)
      if (bmin(b) >= dp_) return
      if (sqrt(box_gap2(d, xp, blo(:, b), bhi(:, b))) / rstar >= dp_) return
      k0 = w * BLOCK_CELLS
      k1 = min(k0 + BLOCK_CELLS, nc(3)) - 1
      do ci = u * BLOCK_CELLS, min(u * BLOCK_CELLS + BLOCK_CELLS, nc(1)) - 1
         do cj = v * BLOCK_CELLS, min(v * BLOCK_CELLS + BLOCK_CELLS, nc(2)) - 1
            call visit(d, xp, sx, sst, start(id(ci, cj, k0)), start(id(ci, cj, k1) + 1) - 1, rstar, dp_)
         end do
      end do
    end subroutine visit_block

  end subroutine grade_scan

  !> The squared distance from xp to the box [lo, hi], summed over the axes in the order of a
  !> source's (visit).  Each axis's gap is at most the difference to any point of the box, in
  !> rounding too (rounding is monotone), so the sum is at most any of its sources' squared distances.
  pure real(dp) function box_gap2(d, xp, lo, hi) result(g2)
    integer, intent(in) :: d
    real(dp), intent(in) :: xp(3), lo(3), hi(3)
    real(dp) :: gap
    integer :: b
    g2 = 0.0_dp
    do b = 1, d
       gap = max(lo(b) - xp(b), xp(b) - hi(b), 0.0_dp)
       g2 = g2 + gap * gap
    end do
  end function box_gap2

  !> the cell of a point, 0-based, clipped to the grid
  pure function cell_of(d, y, lo, h, nc) result(cc)
    integer, intent(in) :: d, nc(3)
    real(dp), intent(in) :: y(d), lo(3), h
    integer :: cc(3)
    integer :: b
    cc = 0
    do b = 1, d
       cc(b) = int(min(max((y(b) - lo(b)) / h, 0.0_dp), real(nc(b) - 1, dp)))
    end do
  end function cell_of

  !> Lower dp_ by the sources first .. last: max(D~_q, |x_p - x_q| / r*).
  pure subroutine visit(d, xp, sx, sst, first, last, rstar, dp_)
    integer, intent(in) :: d, first, last
    real(dp), intent(in) :: xp(3), sx(:, :), sst(:), rstar
    real(dp), intent(inout) :: dp_
    integer :: u, b
    real(dp) :: s2, diff, v
    do u = first, last
       if (sst(u) >= dp_) cycle                            ! max(D~_q, .) >= D: cannot lower it
       s2 = 0.0_dp
       do b = 1, d
          diff = xp(b) - sx(b, u)
          s2 = s2 + diff * diff
       end do
       v = max(sst(u), sqrt(s2) / rstar)
       if (v < dp_) dp_ = v
    end do
  end subroutine visit

  !> The Shepard interpolation of D (Sec. 3.2.2 step 4(e)iv) at the points y(:, 1:m) from the sources
  !> xs(:, 1:ns) with cutoffs rcs and values ds, over the cross list off / idx (row p: the sources that
  !> reach y_p, 0-based, in any order): out(p) = sum_q w_q ds_q / sum_q w_q with
  !> w_q = max(1 - |y_p - x_q|^2 / rcs_q^2, 0)^2, both sums taken over the row in ascending source
  !> order, so that no list layout shows in them (the arithmetic of arpy.resolution's NumPy form:
  !> squared differences summed over the axes in order).  ok(p) = 0 where no weight is positive
  !> (out(p) = 0 there).  Rows in parallel, each written by one iteration.
  subroutine shepard_rows(d, m, y, ns, xs, rcs, ds, off, idx, out, ok, failed)
    integer, intent(in) :: d, m, ns
    real(dp), intent(in) :: y(d, m), xs(d, ns), rcs(ns), ds(ns)
    integer(i8), intent(in) :: off(m + 1)
    integer, intent(in) :: idx(*)
    real(dp), intent(out) :: out(m)
    integer, intent(out) :: ok(m), failed           !< failed = 1: no workspace
    integer, allocatable :: row(:)
    integer :: p, kmax, length, i, q, b, stat
    real(dp) :: num, den, s2, diff, w
    kmax = 1
    do p = 1, m
       kmax = max(kmax, int(off(p + 1) - off(p)))
    end do
    failed = 0
    !$omp parallel num_threads(team_size()) if(m >= MIN_PARALLEL_POINTS) default(shared) &
    !$omp private(row, p, length, i, q, b, num, den, s2, diff, w, stat) reduction(max: failed)
    allocate(row(kmax), stat=stat)
    if (stat /= 0) failed = 1
    !$omp do schedule(static)
    do p = 1, m
       out(p) = 0.0_dp
       ok(p) = 0
       if (stat /= 0) cycle
       length = int(off(p + 1) - off(p))
       row(1:length) = idx(off(p) + 1:off(p + 1))
       call sort_run(row, 1_i8, int(length, i8))          ! the row in ascending order
       num = 0.0_dp
       den = 0.0_dp
       do i = 1, length
          q = row(i) + 1
          s2 = 0.0_dp
          do b = 1, d
             diff = y(b, p) - xs(b, q)
             s2 = s2 + diff * diff
          end do
          w = max(1.0_dp - s2 / (rcs(q) * rcs(q)), 0.0_dp)
          w = w * w
          num = num + w * ds(q)
          den = den + w
       end do
       if (den > 0.0_dp) then
          ok(p) = 1
          out(p) = num / den
       end if
    end do
    !$omp end do
    if (stat == 0) deallocate(row)
    !$omp end parallel
  end subroutine shepard_rows

end module arpy_grade
