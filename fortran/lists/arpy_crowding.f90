!> How crowded particles are on the uniform cell list's grid: the statistic with which
!> `method="auto"` (arpy.lists.auto.auto_work) sees clustered particles.
module arpy_crowding
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_SIZE, RULE_MIN, RULE_SUM
  use arpy_threads, only: team_size, block_range, MIN_PARALLEL_ROWS
  implicit none
  private

  public :: crowding_counts, level_crowding, finest_near, auto_terms

  !> The particles of one range in auto_terms' larger sample, and their hashes.
  type :: sample_part
     integer :: m = 0, info = 0
     integer, allocatable :: pick(:)
     integer(i8), allocatable :: h(:)
  end type sample_part

  !> The entries of auto_terms' `knob` (arpy.lists.auto.AUTO_SAMPLE and the others).
  integer, parameter, public :: NKNOB = 9

contains

  !> The grid cell of x(:) (0-based per axis), positions outside the grid (and NaN) in its border
  !> cells: cells of edge g from lo, nc(a) along axis a.
  pure subroutine grid_cell(d, x, lo, g, nc, c)
    integer, intent(in) :: d, nc(d)
    real(dp), intent(in) :: x(d), lo(d), g
    integer, intent(out) :: c(3)
    integer :: a
    real(dp) :: t
    c = 0
    do a = 1, d
       t = (x(a) - lo(a)) / g
       if (.not. (t >= 1.0_dp)) then               ! (below the grid's second cell, or NaN)
          c(a) = 0
       else if (t >= real(nc(a) - 1, dp)) then
          c(a) = nc(a) - 1
       else
          c(a) = int(t)
       end if
    end do
  end subroutine grid_cell

  !> cells(1:k): the flat indices (strides s) of the grid cells within 1 of cell c(1:d) along every
  !> axis, inside the grid of nc(1:d) cells.
  pure subroutine block_cells(d, c, nc, s, cells, k)
    integer, intent(in) :: d, c(3), nc(d)
    integer(i8), intent(in) :: s(3)
    integer(i8), intent(out) :: cells(27)
    integer, intent(out) :: k
    integer :: lo3(3), hi3(3), i1, i2, i3
    lo3 = 0
    hi3 = 0
    lo3(1:d) = max(c(1:d) - 1, 0)
    hi3(1:d) = min(c(1:d) + 1, nc - 1)
    k = 0
    do i1 = lo3(1), hi3(1)
       do i2 = lo3(2), hi3(2)
          do i3 = lo3(3), hi3(3)
             k = k + 1
             cells(k) = i1 * s(1) + i2 * s(2) + i3 * s(3)
          end do
       end do
    end do
  end subroutine block_cells

  !> exponent(v) (v = f 2**e, 0.5 <= f < 1) of a normal v > 0, read from its bits: the level of a cutoff
  !> over the levels' base (Fortran's exponent calls the C library's frexp).
  elemental integer function binary_exponent(v)
    real(dp), intent(in) :: v
    binary_exponent = int(ishft(transfer(v, 0_i8), -52)) - 1022
  end function binary_exponent

  !> The row-major strides of a grid of nc(1:d) cells (axis 3 of a 2D grid unused: 0).
  pure function row_strides(d, nc) result(s)
    integer, intent(in) :: d, nc(d)
    integer(i8) :: s(3)
    integer :: a
    s = 0
    s(d) = 1
    do a = d - 1, 1, -1
       s(a) = s(a + 1) * nc(a + 1)
    end do
  end function row_strides

  !> The grid on which n points spread over a box of edges ext are binned with cells of edge c: cells
  !> of edge g = c, or where that grid would have more than `most` cells, of edge
  !> g = (prod(ext) / most)**(1 / d) (at least c); nc(a) cells along axis a.  ok: .false. when an axis
  !> would still have more than `most` cells (edges of very different lengths).
  pure subroutine capped_grid(d, ext, c, most, g, nc, ok)
    integer, intent(in) :: d
    real(dp), intent(in) :: ext(d), c, most
    real(dp), intent(out) :: g
    integer, intent(out) :: nc(d)
    logical, intent(out) :: ok
    g = c
    if (product(up(ext / c)) > most) g = max(c, exp(sum(log(ext)) / d - log(most) / d))
    ok = maxval(ext / g) <= most
    nc = 1
    if (ok) nc = max(1, ceiling(ext / g))
  contains
    !> The ceiling of v > 0 as a real (no integer overflow).
    elemental real(dp) function up(v)
      real(dp), intent(in) :: v
      up = aint(v)
      if (v > up) up = up + 1.0_dp
    end function up
  end subroutine capped_grid

  !> own(j): of the point q(:, j) on level lev(j) (0 .. nlev - 1), the number of the other points of
  !> its level in the 3**d cells of edge c = base * 2**(first + lev(j)) around its own, on a grid over
  !> the bounding box of the level's points (each edge at least c; the points on its border cells).
  !> Where that grid would have more than `most` cells per point of the level, they are binned on
  !> cells of a coarser edge g (capped_grid) and the count is scaled to the block of edge 3 c as if
  !> they were evenly spread within the coarse block (prod over the axes of min(1, 3 c / e) /
  !> min(1, 3 g / e), e the box's edges).  A level whose grid cannot be capped counts 0.  What
  !> arpy.lists.auto.auto_work estimates the AR list's checks on each particle's own level from.
  !> info: ARPY_ERR_SIZE on a bad level, ARPY_ERR_ALLOC.
  subroutine level_crowding(d, m, q, lev, nlev, base, first, most, own, info)
    integer, intent(in) :: d, m, nlev, first, lev(m)
    real(dp), intent(in) :: q(d, m), base, most
    real(dp), intent(out) :: own(m)
    integer, intent(out) :: info
    integer :: byl(m), start(0:nlev), fill(0:nlev), j, k, nk, i
    own = 0.0_dp
    info = ARPY_OK
    if (d < 2 .or. d > 3 .or. nlev < 1 .or. any(lev < 0) .or. any(lev >= nlev) &
        .or. .not. (base > 0.0_dp) .or. .not. (most >= 1.0_dp)) then
       info = ARPY_ERR_SIZE
       return
    end if
    start = 0                                   ! the points by level (a counting sort)
    do j = 1, m
       start(lev(j)) = start(lev(j)) + 1
    end do
    fill(0) = 0
    do k = 1, nlev
       fill(k) = fill(k - 1) + start(k - 1)
    end do
    start = fill
    do j = 1, m
       fill(lev(j)) = fill(lev(j)) + 1
       byl(fill(lev(j))) = j
    end do
    do k = 0, nlev - 1
       nk = start(k + 1) - start(k)
       if (nk < 2) cycle
       call level_block(k, byl(start(k) + 1:start(k) + nk), i)
       if (i /= ARPY_OK) then
          info = i
          return
       end if
    end do

  contains

    !> The counts of the nk points idx(:) of level k.
    subroutine level_block(k, idx, st)
      integer, intent(in) :: k, idx(:)
      integer, intent(out) :: st
      integer, allocatable :: hist(:)
      integer(i8) :: s(3), b, cells(27)
      integer :: nc(d), a, c(3), t, p, nb
      real(dp) :: c_k, g, scale, lo(d), ext(d)
      logical :: ok
      st = ARPY_OK
      c_k = base * 2.0_dp ** (first + k)
      lo = q(:, idx(1))
      ext = lo
      do t = 2, size(idx)
         lo = min(lo, q(:, idx(t)))
         ext = max(ext, q(:, idx(t)))
      end do
      ext = max(ext - lo, c_k)
      if (.not. all(ext <= huge(1.0_dp))) return              ! (positions that are not finite)
      call capped_grid(d, ext, c_k, most * size(idx), g, nc, ok)
      if (.not. ok) return
      allocate(hist(0:product(int(nc, i8)) - 1), stat=a)
      if (a /= 0) then
         st = ARPY_ERR_ALLOC
         return
      end if
      hist = 0
      s = row_strides(d, nc)
      do t = 1, size(idx)
         call grid_cell(d, q(:, idx(t)), lo, g, nc, c)
         b = c(1) * s(1) + c(2) * s(2) + c(3) * s(3)
         hist(b) = hist(b) + 1
      end do
      scale = product(min(1.0_dp, 3.0_dp * c_k / ext) / min(1.0_dp, 3.0_dp * g / ext))
      do t = 1, size(idx)
         p = idx(t)
         call grid_cell(d, q(:, p), lo, g, nc, c)
         call block_cells(d, c, nc, s, cells, nb)
         own(p) = scale * real(sum(hist(cells(1:nb))) - 1, dp)           ! (not itself)
      end do
    end subroutine level_block

  end subroutine level_crowding

  !> near(j): the finest level (smallest) of the particles of x in the 3**d grid cells around the cell
  !> of q(:, j) (cells of edge g from lo, nc(a) along axis a; points
  !> outside the grid in its border cells), a particle of cutoff rc(p) on level
  !> exponent((rc(p) + skin) / base) - first (Fortran's exponent: base * 2**(level + first - 1) <=
  !> rc + skin < base * 2**(level + first)), at least 0; huge(0) where no such particle is (cutoffs that
  !> are not normal numbers > 0 skipped: the search reports them).  What
  !> arpy.lists.auto.auto_work estimates how deep the AR list's coarse particles descend from.
  !> info: ARPY_ERR_SIZE on a bad grid or sample, ARPY_ERR_ALLOC.
  subroutine finest_near(d, n, x, rc, skin, base, first, lo, g, nc, m, q, near, info)
    integer, intent(in) :: d, n, first, nc(d), m
    real(dp), intent(in) :: x(d, n), rc(n), skin, base, lo(d), g, q(d, m)
    integer, intent(out) :: near(m)
    integer, intent(out) :: info
    integer, allocatable :: cmin(:)
    integer(i8) :: ncell, s(3), b
    integer :: p, j, c(3), stat, lv, k
    integer(i8) :: cells(27)
    real(dp) :: v
    near = huge(0)
    info = ARPY_OK
    if (d < 2 .or. d > 3 .or. n < 1 .or. any(nc < 1) .or. .not. (g > 0.0_dp) .or. .not. (base > 0.0_dp)) then
       info = ARPY_ERR_SIZE
       return
    end if
    ncell = product(int(nc, i8))
    allocate(cmin(0:ncell - 1), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    cmin = huge(0)
    s = row_strides(d, nc)
    do p = 1, n
       v = (rc(p) + skin) / base
       if (.not. (v >= tiny(1.0_dp) .and. v <= huge(1.0_dp))) cycle  ! (the search reports these)
       lv = max(0, binary_exponent(v) - first)
       call grid_cell(d, x(:, p), lo, g, nc, c)
       b = c(1) * s(1) + c(2) * s(2) + c(3) * s(3)
       cmin(b) = min(cmin(b), lv)
    end do
    do j = 1, m
       call grid_cell(d, q(:, j), lo, g, nc, c)
       call block_cells(d, c, nc, s, cells, k)
       near(j) = minval(cmin(cells(1:k)))
    end do
  end subroutine finest_near

  !> u(j), j = 1 .. k: an integer in [0, 2**53) given by the bits of the position x(:, j) alone, the
  !> same wherever the particle stands in the input.  z = xor over the axes a of bits(x(a)) * K(a);
  !> z = (z xor z >> 31) * K4; z = z xor z >> 29; u = its top 53 bits (64-bit integers, wrapping; >>
  !> logical).  (One multiplication less left the sample of a lattice in row order visibly short of
  !> close pairs.)  Samples drawn as the particles whose u is below a fraction are random with respect
  !> to where the particles are and do not depend on their order (particles given in lattice order
  !> sampled every (n/m)-th would form a coarser lattice, none of them near another); the samples of
  !> smaller fractions are subsets of those of larger ones.
  pure subroutine position_hashes(d, k, x, u)
    integer, intent(in) :: d, k
    real(dp), intent(in) :: x(d, k)
    integer(i8), intent(out) :: u(k)
    integer(i8), parameter :: K1 = -7046029254386353131_i8, K2 = -4658895280553007687_i8, &
         K3 = -7723592293110705685_i8, K4 = 6364136223846793005_i8
    integer(i8) :: z
    integer :: j
    if (d == 3) then
       do j = 1, k
          z = ieor(ieor(transfer(x(1, j), 0_i8) * K1, transfer(x(2, j), 0_i8) * K2), transfer(x(3, j), 0_i8) * K3)
          z = ieor(z, ishft(z, -31)) * K4
          u(j) = ishft(ieor(z, ishft(z, -29)), -11)
       end do
    else
       do j = 1, k
          z = ieor(transfer(x(1, j), 0_i8) * K1, transfer(x(2, j), 0_i8) * K2)
          z = ieor(z, ishft(z, -31)) * K4
          u(j) = ishft(ieor(z, ishft(z, -29)), -11)
       end do
    end if
  end subroutine position_hashes

  !> Append p (and its hash h) to the sample pick(1:m), u(1:m), grown when full; info: ARPY_ERR_ALLOC.
  subroutine append(pick, u, m, p, h, info)
    integer, allocatable, intent(inout) :: pick(:)
    integer(i8), allocatable, intent(inout) :: u(:)
    integer, intent(inout) :: m, info
    integer, intent(in) :: p
    integer(i8), intent(in) :: h
    integer, allocatable :: tp(:)
    integer(i8), allocatable :: tu(:)
    integer :: stat
    if (m == size(pick)) then                     ! (rare: more than 6 standard deviations above)
       allocate(tp(2 * m + 1), tu(2 * m + 1), stat=stat)
       if (stat /= 0) then
          info = ARPY_ERR_ALLOC
          return
       end if
       tp(1:m) = pick(1:m)
       tu(1:m) = u(1:m)
       call move_alloc(tp, pick)
       call move_alloc(tu, u)
    end if
    m = m + 1
    pick(m) = p
    u(m) = h
  end subroutine append

  !> w = (W_cell, W_own, W_finer, W_look): the statistics of the n particles x with cutoffs rc + skin
  !> from which arpy.lists.auto.auto_work estimates the times of the uniform and of the AR list (that
  !> docstring is their definition; this is its arithmetic, in one call of the core instead of several
  !> passes of NumPy).  knob = (AUTO_SAMPLE, AUTO_SAMPLE_LEAST, AUTO_SAMPLE_SHARE, AUTO_FINE_SAMPLE,
  !> AUTO_FINE_CELLS, AUTO_CROWD_PAIRS, AUTO_CROWD_CELLS, AUTO_LEVEL_CELLS, AUTO_FINE_SHARE); w(5), w(6): W_hash,
  !> W_dense, the AR tree's tables (tree_tables).  rule (RULE_* of arpy_kinds): under RULE_MAX and
  !> RULE_SUM a particle's reach is its level reach (rc + skin, 2 rc + skin) and w(3), w(4) are
  !> W_coarse, W_up, the AR list's checks and stencil cells looked up on coarser levels, from the
  !> number of particles on every level (all of them, not the sample: a few large ones make a level
  !> every particle searches).  w = -1 when the cutoffs are
  !> not all finite and > 0, 0 when a sampled position is not finite (the search reports both).
  !> The samples are drawn by position_hashes.  info: ARPY_ERR_SIZE on bad sizes, ARPY_ERR_ALLOC.
  subroutine auto_terms(d, n, x, rc, skin, knob, rule, w, info)
    integer, intent(in) :: d, n, rule
    real(dp), intent(in) :: x(d, n), rc(n), skin, knob(NKNOB)
    real(dp), intent(out) :: w(6)
    integer, intent(out) :: info
    integer, allocatable :: lev(:), counts(:), near(:), pick(:), fpick(:), sub(:), cand(:)
    integer(i8), allocatable :: block(:), h(:)
    real(dp), allocatable :: q(:, :), own(:), finer(:), u(:)
    integer, parameter :: HASH_BLOCK = 512
    integer(i8) :: t1, t2, ta
    real(dp) :: r_lo, r_hi, low(d), high(d), ext(d), base, occ1, wcell, wfiner, crowd, g, f, sc, frac, ffrac, mult
    real(dp), allocatable :: up(:)
    logical :: bad, coarse
    type(sample_part), allocatable :: part(:)
    integer :: m, j, k, nlev, first, qs, mq, nf, na, nc(d), stat, nt, t
    logical :: ok
    w = -1.0_dp
    info = ARPY_OK
    coarse = rule /= RULE_MIN                   ! (the max and sum rules search from the fine side)
    mult = merge(2.0_dp, 1.0_dp, rule == RULE_SUM)
    if (d < 2 .or. d > 3 .or. n < 1) then
       info = ARPY_ERR_SIZE
       return
    end if
    ! one pass: the cutoffs' extremes, and the particles whose position hash falls below the larger of
    ! the two samples' fractions; in parallel over contiguous ranges, joined in their order.  The
    ! samples are those below each fraction (the smaller one a subset of the larger)
    frac = real(min(n, int(knob(1)), max(int(knob(2)), n / int(knob(3)))), dp) / n
    ffrac = real(min(n, int(knob(4)), max(int(knob(2)), n / int(knob(9)))), dp) / n
    t1 = threshold(frac)
    t2 = threshold(ffrac)
    ta = max(t1, t2)
    nt = 1
    if (n >= MIN_PARALLEL_ROWS) nt = team_size()
    allocate(part(nt), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    r_lo = huge(1.0_dp)
    r_hi = 0.0_dp
    bad = .false.
    !$omp parallel do num_threads(nt) schedule(static, 1) reduction(min: r_lo) reduction(max: r_hi) &
    !$omp& reduction(.or.: bad)
    do t = 1, nt
       call sample_range(t, r_lo, r_hi, bad)
    end do
    !$omp end parallel do
    if (bad) return
    info = maxval(part%info)
    if (info /= ARPY_OK) return
    na = sum(part%m)
    allocate(cand(na), h(na), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    na = 0
    do t = 1, nt
       cand(na + 1:na + part(t)%m) = part(t)%pick(1:part(t)%m)
       h(na + 1:na + part(t)%m) = part(t)%h(1:part(t)%m)
       na = na + part(t)%m
    end do
    deallocate(part)
    if (.not. (r_hi <= huge(1.0_dp))) return
    w = 0.0_dp
    pick = pack(cand, h < t1)
    u = pack(h, h < t1) * 2.0_dp ** (-53)
    fpick = pack(cand, h < t2)
    m = size(pick)
    nf = size(fpick)
    if (m < 2) return
    allocate(q(d, m), lev(m), own(m), near(m), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    q = x(:, pick(1:m))
    if (.not. all(abs(q) <= huge(1.0_dp))) return         ! (not finite: the search reports them)
    low = minval(q, dim=2)
    high = maxval(q, dim=2)
    ext = max(high - low, r_hi)
    if (.not. all(ext <= huge(1.0_dp))) return
    base = nearest(r_lo, 1.0_dp)
    do j = 1, m
       lev(j) = binary_exponent((mult * rc(pick(j)) + skin) / base)      ! c_k = base 2**k > r >= c_k / 2
    end do
    first = minval(lev)
    lev = lev - first
    nlev = maxval(lev) + 1
    allocate(counts(0:nlev - 1), finer(0:nlev - 1), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    counts = 0
    do j = 1, m
       counts(lev(j)) = counts(lev(j)) + 1
    end do
    call tree_tables(maxval(high - low), w(5), w(6))
    if (coarse) then
       ! a particle's checks on the coarser levels that hold particles, evenly spread
       call coarser_levels(finer, up, info)
       if (info /= ARPY_OK) return
    else
       ! a particle's checks on the finer levels held, evenly spread
       finer(0) = 0.0_dp
       do k = 1, nlev - 1
          finer(k) = finer(k - 1)
          if (counts(k - 1) > 0) finer(k) = finer(k) + occ(base * 2.0_dp ** (first + k - 1), counts(k - 1) * real(n, dp) / m)
       end do
    end if
    wcell = 0.5_dp * n * occ(r_hi, real(n, dp))
    wfiner = n * sum(finer(lev)) / m
    crowd = 1.0_dp
    occ1 = occ(r_hi, 1.0_dp)
    if (occ1 > 0.0_dp) then
       ! (the sampled particles whose hash is below 1 / qs of the sample's bound: about
       ! AUTO_CROWD_PAIRS pairs in one another's blocks if even)
       qs = max(1, int(m / sqrt(knob(6) / occ1)))
       sub = pack([(j, j = 1, m)], u(1:m) < frac / qs)
       mq = size(sub)
       call capped_grid(d, ext, r_hi, knob(7) * mq, g, nc, ok)
       if (ok .and. mq >= 1) then
          allocate(block(mq), stat=stat)
          if (stat /= 0) then
             info = ARPY_ERR_ALLOC
             return
          end if
          call crowding_counts(d, mq, q(:, sub), 1, low, g, nc, mq, block, info)
          if (info /= ARPY_OK) return
          sc = product(min(1.0_dp, 3.0_dp * r_hi / ext) / min(1.0_dp, 3.0_dp * g / ext)) &
               * (n - 1) / max(mq - 1, 1) / occ(r_hi, real(n, dp))
          crowd = 0.0_dp
          wfiner = 0.0_dp
          do j = 1, mq
             f = block(j) * sc
             crowd = crowd + f
             wfiner = wfiner + f * finer(lev(sub(j)))
          end do
          crowd = crowd / mq
          wfiner = n * wfiner / mq
       end if
    end if
    w(1) = wcell * crowd
    w(3) = wfiner
    if (coarse) w(4) = real(n, dp) * 3**d * sum(up(lev)) / m        ! (the coarser levels it looks up)
    if (nlev == 1) then
       ! (one level: the AR list tests the particles of 3**d cells of its edge, crowded alike)
       w(2) = 0.5_dp * n * occ(base * 2.0_dp ** first, real(n, dp)) * crowd
       return
    end if
    call level_crowding(d, m, q, lev, nlev, base, first, knob(8), own, info)
    if (info /= ARPY_OK) return
    w(2) = 0.5_dp * n * (real(n, dp) / m) * sum(own) / m
    if (nf < 1 .or. coarse) return
    call capped_grid(d, ext, r_hi, knob(5) * nf, g, nc, ok)
    if (.not. ok) return
    call finest_near(d, nf, x(:, fpick(1:nf)), rc(fpick(1:nf)), skin, base, first, low, g, nc, m, q, near, info)
    if (info /= ARPY_OK) return
    w(4) = real(n, dp) * 3**d * sum(real(lev - min(near, lev), dp)) / m          ! (the levels it descends)

  contains

    !> Range t of nt of the particles: the extremes of its cutoffs (lo, hi; bad: one not > 0), its
    !> particles whose hash is below ta into part(t).
    subroutine sample_range(t, lo, hi, bad)
      integer, intent(in) :: t
      real(dp), intent(inout) :: lo, hi
      logical, intent(inout) :: bad
      integer(i8) :: hu(HASH_BLOCK)
      real(dp) :: r
      integer :: p0, p1, b0, b1, p, st, sel(HASH_BLOCK + 1), ns
      call block_range(n, nt, t, p0, p1)
      associate (pt => part(t))
        pt%info = ARPY_OK
        pt%m = 0
        allocate(pt%pick(guess(ta, p1 - p0 + 1)), pt%h(guess(ta, p1 - p0 + 1)), stat=st)
        if (st /= 0) then
           pt%info = ARPY_ERR_ALLOC
           return
        end if
        do b0 = p0, p1, HASH_BLOCK                      ! (in blocks: the hashes vectorize)
           b1 = min(p1, b0 + HASH_BLOCK - 1)
           do p = b0, b1
              r = mult * rc(p) + skin
              bad = bad .or. .not. (r > 0.0_dp)             ! (<= 0 or NaN)
              lo = min(lo, r)
              hi = max(hi, r)
           end do
           call position_hashes(d, b1 - b0 + 1, x(:, b0:b1), hu)
           ns = 0
           do p = 1, b1 - b0 + 1                        ! (without branches: they mispredict)
              sel(ns + 1) = p
              ns = ns + merge(1, 0, hu(p) < ta)
           end do
           do p = 1, ns
              call append(pt%pick, pt%h, pt%m, b0 - 1 + sel(p), hu(sel(p)), pt%info)
           end do
        end do
      end associate
    end subroutine sample_range

    !> The hash below which a particle is in a sample of fraction fr of them (all for fr >= 1).
    pure integer(i8) function threshold(fr)
      real(dp), intent(in) :: fr
      threshold = huge(0_i8)
      if (fr < 1.0_dp) threshold = int(fr * 2.0_dp ** 53, i8)
    end function threshold

    !> Room for a sample of the particles whose hash is below tr, of k particles (six standard
    !> deviations more than expected).
    pure integer function guess(tr, k)
      integer(i8), intent(in) :: tr
      integer, intent(in) :: k
      real(dp) :: fr
      fr = min(1.0_dp, tr * 2.0_dp ** (-53))
      guess = int(min(real(k, dp), fr * k + 6.0_dp * sqrt(fr * k) + 16.0_dp))
    end function guess

    !> (W_hash, W_dense): the cells of the AR tree's hashed levels that its particles enter, and the cells
    !> of its dense levels, by arpy_arbuild's plan_dense rule applied to the sample.  The tree's root edge
    !> is base 2**K, K the fewest doublings that reach the largest extent e (its level K - k has the cells
    !> of edge c_k of level k here).  From the coarsest level below the root to the finest, a level is dense
    !> when the box of the particles on it or finer has at most 4 cells per such particle (+ 1024) and the
    !> dense levels so far stay within 4 n + 4096 cells (counts scaled from the sample to n, boxes the
    !> sample's); W_dense is their cells (and a sentinel each).  A particle enters a cell of its own level
    !> and of every coarser one (flagged: its region holds finer particles); W_hash is n times the mean
    !> number of hashed levels among those.
    subroutine tree_tables(e, wh, wd)
      real(dp), intent(in) :: e
      real(dp), intent(out) :: wh, wd
      real(dp) :: lo_k(d, 0:nlev - 1), hi_k(d, 0:nlev - 1), c, cells
      integer :: kk, k, top, held(0:nlev - 1), j
      logical :: dense(0:nlev + 64)
      top = 0
      do while (base * 2.0_dp ** top < e .and. top < 64)
         top = top + 1
      end do
      ! the box and number of the sampled particles on each level or finer (one pass, then cumulative)
      lo_k = huge(1.0_dp)
      hi_k = -huge(1.0_dp)
      do j = 1, m
         lo_k(:, lev(j)) = min(lo_k(:, lev(j)), q(:, j))
         hi_k(:, lev(j)) = max(hi_k(:, lev(j)), q(:, j))
      end do
      held(0) = counts(0)
      do k = 1, nlev - 1
         lo_k(:, k) = min(lo_k(:, k), lo_k(:, k - 1))
         hi_k(:, k) = max(hi_k(:, k), hi_k(:, k - 1))
         held(k) = held(k - 1) + counts(k)
      end do
      dense = .true.
      wd = 0.0_dp
      do kk = top - 1 - first, 0, -1                 ! (coarse to fine: tree levels 1 .. K - first)
         k = min(kk, nlev - 1)                       ! (levels above the coarsest held: every particle)
         dense(kk) = .false.
         c = base * 2.0_dp ** (first + kk)
         cells = product(aint((hi_k(:, k) - lo_k(:, k)) / c) + 1.0_dp)
         if (cells > 4.0_dp * (real(n, dp) * held(k) / m) + 1024.0_dp .or. wd + cells > 4.0_dp * n + 4096.0_dp) cycle
         wd = wd + cells + 1.0_dp
         dense(kk) = .true.
      end do
      wh = 0.0_dp
      do j = 1, m
         wh = wh + count(.not. dense(lev(j):max(top - 1 - first, lev(j))))
      end do
      wh = real(n, dp) * wh / m
    end subroutine tree_tables

    !> Under the max and sum rules, for each level k of the sample (k = 0 .. nlev - 1, edge c_k), the
    !> checks a particle of it makes on the coarser levels that hold particles (ch(k): the sum over
    !> those levels j of occ(c_j, n_j)) and the number of those levels (uk(k)); n_j counted over every
    !> particle (its level by the same rule; in parallel, integer sums: the same at any thread count).
    subroutine coarser_levels(ch, uk, info)
      real(dp), intent(out) :: ch(0:nlev - 1)
      real(dp), allocatable, intent(out) :: uk(:)
      integer, intent(out) :: info
      integer(i8), allocatable :: held_all(:)
      integer :: top, p, kk, st
      top = binary_exponent(r_hi / base)
      allocate(held_all(0:top), uk(0:nlev - 1), stat=st)
      if (st /= 0) then
         info = ARPY_ERR_ALLOC
         return
      end if
      info = ARPY_OK
      held_all = 0
      !$omp parallel do num_threads(nt) private(kk) reduction(+: held_all)
      do p = 1, n
         kk = min(top, max(0, binary_exponent((mult * rc(p) + skin) / base)))
         held_all(kk) = held_all(kk) + 1
      end do
      !$omp end parallel do
      ch = 0.0_dp
      uk = 0.0_dp
      do kk = 0, nlev - 1
         do p = first + kk + 1, top
            if (held_all(p) == 0) cycle
            ch(kk) = ch(kk) + occ(base * 2.0_dp ** p, real(held_all(p), dp))
            uk(kk) = uk(kk) + 1.0_dp
         end do
      end do
    end subroutine coarser_levels

    !> Of k particles spread evenly over the box, those in a block of 3**d cells of edge c.
    pure real(dp) function occ(c, k)
      real(dp), intent(in) :: c, k
      occ = k * product(min(1.0_dp, 3.0_dp * c / ext))
    end function occ

  end subroutine auto_terms

  !> block(j): of the sampled particle 1 + (j - 1) * step, the number of the other sampled particles
  !> (1, 1 + step, 1 + 2 step, ...) in the 3**d grid cells around its own (cells of edge g from lo,
  !> nc(a) along axis a; particles outside the grid counted in its border cells).
  !> ns = (n - 1) / step + 1.  info: ARPY_ERR_SIZE on a bad grid or sample, ARPY_ERR_ALLOC.
  subroutine crowding_counts(d, n, x, step, lo, g, nc, ns, block, info)
    integer, intent(in) :: d, n, step, nc(d), ns
    real(dp), intent(in) :: x(d, n), lo(d), g
    integer(i8), intent(out) :: block(ns)
    integer, intent(out) :: info
    integer(i8), allocatable :: hist(:)
    integer(i8) :: ncell, s(3), b
    integer :: p, j, c(3), stat, k
    integer(i8) :: cells(27)
    block = 0
    info = ARPY_OK
    if (d < 2 .or. d > 3 .or. n < 1 .or. step < 1 .or. any(nc < 1) &
        .or. ns /= (n - 1) / step + 1 .or. .not. (g > 0.0_dp)) then
       info = ARPY_ERR_SIZE
       return
    end if
    ncell = product(int(nc, i8))
    allocate(hist(0:ncell - 1), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    hist = 0
    s = row_strides(d, nc)
    do p = 1, n, step
       call grid_cell(d, x(:, p), lo, g, nc, c)
       b = c(1) * s(1) + c(2) * s(2) + c(3) * s(3)
       hist(b) = hist(b) + 1
    end do
    do j = 1, ns
       call grid_cell(d, x(:, 1 + (j - 1) * step), lo, g, nc, c)
       call block_cells(d, c, nc, s, cells, k)
       block(j) = sum(hist(cells(1:k))) - 1                       ! (not itself)
    end do
  end subroutine crowding_counts

end module arpy_crowding
