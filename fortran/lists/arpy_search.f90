!> Neighbour search by any method, and in periodic boxes.
!>
!> half_list: the symmetric list of a particle set by brute force, the uniform cell list or the AR
!> cell list, rows in the method's search order.
!>
!> Periodic boxes go through images: a particle within its own reach r (cutoff + skin) of a
!> periodic face gets a copy shifted by the box edge across it (combined copies at edges and
!> corners); under the min rule a pair across the boundary needs both particles that close to it.
!> periodic_list adds to the particles' own list the pairs of these images queried against the
!> particles: particle r near an image of s gives the pair (r, s) if r < s (the same pair is found
!> again from the image of r near s), as extra rows that the hand-off appends to the rows of the
!> particles (arpy_store).  With cutoffs below half the box a pair lies either within the box or
!> across it, never both.
!>
!> Under the max and sum rules a pair's reach can exceed the smaller particle's own (cutoff +
!> skin), so both particles of a pair across a face lie within the largest reach of a pair of it:
!> every particle within its cutoff + the largest cutoff + skin (slightly widened against rounding)
!> gets images.  The images and the particles then make one set, whose list by the method and
!> rule (half_list) gives the particles' own pairs and those of a particle with an image
!> (union_rows); pairs of two images are dropped.
module arpy_search
  use, intrinsic :: iso_fortran_env, only: int8
  use arpy_kinds, only: dp, i8, ARPY_OK, ARPY_ERR_ALLOC, ARPY_ERR_METHOD, ARPY_ERR_SIZE, METHOD_BRUTE, METHOD_CELL, &
       METHOD_AR, RULE_MIN
  use arpy_csr, only: row_builder
  use arpy_brute, only: brute_half, brute_cross
  use arpy_celllist, only: cell_grid, grid_build, grid_half_list, cell_prefix
  use arpy_artree, only: ar_tree
  use arpy_arbuild, only: ar_build
  use arpy_arlists, only: ar_half_list
  use arpy_arquery, only: ar_cross_list
  use arpy_order, only: radix_sort
  use arpy_threads, only: team_size, block_range, MIN_PARALLEL_POINTS, MIN_PARALLEL_ROWS
  use arpy_checks, only: particle_extremes
  implicit none
  private

  public :: half_list, periodic_list, image_count, image_fill, face_band, filter_rows, image_skin

  !> at most this many parallel blocks of particles in the image passes
  integer, parameter :: MAX_BLOCKS = 256

contains

  !> The symmetric list of n particles by `method` into rb, rows in search order; perm(a) (1-based)
  !> is the particle of row a, left unallocated when rows are in particle order.  With `order`
  !> (n), the list is that of the particles in search order instead: its entries are slots
  !> (0-based) where they would be particle indices, order(a) is the 0-based particle at slot a, and
  !> perm stays unallocated (rows and entries need no hand-off permutation).  ext: the particles'
  !> extremes from check_particles, if the caller has them.  rule: the cutoff rule (RULE_MIN if
  !> absent).
  subroutine half_list(d, n, x, rc, skin, method, rb, perm, info, bad, order, ext, rule)
    integer, intent(in) :: d, n, method
    real(dp), intent(in) :: x(d, n), rc(n), skin
    type(row_builder), intent(inout) :: rb
    integer, allocatable, intent(inout) :: perm(:)
    integer, intent(out) :: info, bad
    integer(i8), intent(out), optional :: order(:)
    type(particle_extremes), intent(in), optional :: ext
    integer, intent(in), optional :: rule
    type(cell_grid) :: g
    type(ar_tree) :: t
    real(dp) :: nodomain(d)
    integer :: a, rl
    bad = 0
    rl = RULE_MIN
    if (present(rule)) rl = rule
    select case (method)
    case (METHOD_BRUTE)
       if (present(order)) order = [(int(a - 1, i8), a = 1, n)]
       call brute_half(d, n, x, rc, skin, rb, info, rl)
    case (METHOD_CELL)
       call grid_build(d, n, x, rc, skin, g, info, known=ext, rule=rl)
       if (info /= ARPY_OK) return
       if (present(order)) call slot_labels(n, g%perm, order)
       call grid_half_list(g, rb, info)
       if (.not. present(order) .and. info == ARPY_OK) call move_alloc(g%perm, perm)
    case (METHOD_AR)
       nodomain = 0.0_dp
       call ar_build(d, n, x, rc, skin, .false., nodomain, nodomain, t, info, bad, for_lists=.true., ext=ext, rule=rl)
       if (info /= ARPY_OK) return
       if (present(order)) call slot_labels(n, t%perm, order)
       call ar_half_list(t, rb, info)
       if (.not. present(order) .and. info == ARPY_OK) call move_alloc(t%perm, perm)
    case default
       info = ARPY_ERR_METHOD
    end select
  end subroutine half_list

  !> The symmetric list of n particles in a periodic box (see the module's notes): rb, their own
  !> list (rows in search order, perm: the particle of each row; unallocated for brute force, rows
  !> in particle order), and the pairs across the faces as extra rows.  The images xg(:, g) of the
  !> particles src(g) (0-based; image_fill) are queried against the particles: by brute force, else
  !> against their AR tree (also for the uniform list whose grid is too coarse to wrap).  Extra row
  !> j: particle xpart(j) (1-based, ascending), entries xidx(xoff(j) + 1 : xoff(j + 1)) (0-based
  !> particles, in the order of the images).  ext: the particles' extremes (check_particles).
  !> rule: the cutoff rule (RULE_MIN if absent; the max and sum rules go through union_rows).
  subroutine periodic_list(d, n, x, rc, skin, method, m, xg, src, ext, rb, perm, xpart, xoff, xidx, info, bad, rule)
    integer, intent(in) :: d, n, m, src(m), method
    real(dp), intent(in) :: x(d, n), rc(n), skin, xg(d, m)
    type(particle_extremes), intent(in) :: ext
    type(row_builder), intent(inout) :: rb
    integer, allocatable, intent(inout) :: perm(:), xpart(:), xidx(:)
    integer(i8), allocatable, intent(inout) :: xoff(:)
    integer, intent(out) :: info, bad
    integer, intent(in), optional :: rule
    type(ar_tree) :: t
    type(row_builder) :: cross
    real(dp), allocatable :: rcg(:)
    real(dp) :: nodomain(d)
    integer :: g, stat
    bad = 0
    if (present(rule)) then
       if (rule /= RULE_MIN) then
          call union_rows(d, n, x, rc, skin, method, rule, m, xg, src, rb, perm, xpart, xoff, xidx, info, bad)
          return
       end if
    end if
    allocate(rcg(max(m, 1)), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    do g = 1, m
       rcg(g) = rc(src(g) + 1) + skin
    end do
    select case (method)
    case (METHOD_BRUTE)
       call brute_half(d, n, x, rc, skin, rb, info)
       if (info /= ARPY_OK) return
       call brute_cross(d, m, xg, rcg(1:m), n, x, rc + skin, cross, info)
    case (METHOD_CELL, METHOD_AR)
       ! the whole tree (not for_lists): the images' queries descend from the root
       nodomain = 0.0_dp
       call ar_build(d, n, x, rc, skin, .false., nodomain, nodomain, t, info, bad, ext=ext)
       if (info /= ARPY_OK) return
       call ar_half_list(t, rb, info)
       if (info /= ARPY_OK) return
       call ar_cross_list(t, m, xg, rcg(1:m), cross, info)
       call move_alloc(t%perm, perm)
    case default
       info = ARPY_ERR_METHOD
    end select
    if (info /= ARPY_OK) return
    call extra_rows(m, src, cross, xpart, xoff, xidx, info)
  end subroutine periodic_list

  !> The extra skin of the images under `rule` (image_count, image_fill: a particle p gets images
  !> within rc_p + image_skin of a face): skin under the min rule (a pair's reach is at most
  !> either particle's rc + skin); else the largest cutoff rhi + skin, widened by 1e-12 of itself so
  !> that no rounding of rc_p + (rhi + skin) against the pair's reach, max(rc_p, rc_q) + skin or
  !> (rc_p + rc_q) + skin, drops an image (an image too many is harmless: its pairs are tested).
  pure real(dp) function image_skin(rule, rhi, skin) result(s)
    integer, intent(in) :: rule
    real(dp), intent(in) :: rhi, skin
    s = skin
    if (rule /= RULE_MIN) s = (rhi + skin) * (1.0_dp + 1.0e-12_dp)
  end function image_skin

  !> The list of n particles in a periodic box under the max or sum rule (see the module's notes):
  !> the list of the particles and their m images xg (sources src, 0-based) as one set by `method`
  !> (half_list), split into rb, the particles' own pairs (rows in search order, perm: the particle
  !> of each row, 1-based), and the pairs of a particle r with an image of s, r < s, as the extra
  !> rows xpart, xoff, xidx of periodic_list.  Pairs of two images are dropped.
  subroutine union_rows(d, n, x, rc, skin, method, rule, m, xg, src, rb, perm, xpart, xoff, xidx, info, bad)
    integer, intent(in) :: d, n, method, rule, m, src(m)
    real(dp), intent(in) :: x(d, n), rc(n), skin, xg(d, m)
    type(row_builder), intent(inout) :: rb
    integer, allocatable, intent(inout) :: perm(:), xpart(:), xidx(:)
    integer(i8), allocatable, intent(inout) :: xoff(:)
    integer, intent(out) :: info, bad
    type(row_builder) :: both, cross
    integer, allocatable :: uperm(:), newperm(:)
    integer(i8), allocatable :: newoff(:)
    real(dp), allocatable :: xu(:, :), ru(:)
    integer(i8) :: e, w, start
    integer :: a, p, q, g, row, stat
    bad = 0
    allocate(xu(d, n + m), ru(n + m), stat=stat)
    if (stat /= 0) goto 90
    xu(:, 1:n) = x
    ru(1:n) = rc
    do g = 1, m
       xu(:, n + g) = xg(:, g)
       ru(n + g) = rc(src(g) + 1)
    end do
    call half_list(d, n + m, xu, ru, skin, method, both, uperm, info, bad, rule=rule)
    if (info /= ARPY_OK) return
    if (bad > n) bad = src(bad - n) + 1
    deallocate(xu, ru)
    if (.not. allocated(uperm)) then
       allocate(uperm(n + m), stat=stat)
       if (stat /= 0) goto 90
       uperm = [(a, a = 1, n + m)]
    end if
    ! the pairs of a particle and an image, counted by image, then each image's row filled
    allocate(cross%off(m + 1), newperm(n), newoff(n + 1), stat=stat)
    if (stat /= 0) goto 90
    cross%n = m
    cross%off = 0
    do a = 1, n + m
       p = uperm(a)
       do e = both%off(a) + 1, both%off(a + 1)
          q = both%idx(e) + 1
          if ((p > n) .eqv. (q > n)) cycle
          g = max(p, q) - n
          cross%off(g + 1) = cross%off(g + 1) + 1
       end do
    end do
    do g = 1, m
       cross%off(g + 1) = cross%off(g + 1) + cross%off(g)
    end do
    allocate(cross%idx(max(cross%off(m + 1), 1_i8)), stat=stat)
    if (stat /= 0) goto 90
    cross%nnz = cross%off(m + 1)
    ! one pass: image entries into their rows (cross%off(g) moves along row g), the particles'
    ! own pairs compacted in place (rows of images dropped)
    w = 0
    row = 0
    start = 0
    newoff(1) = 0
    do a = 1, n + m
       p = uperm(a)
       do e = start + 1, both%off(a + 1)
          q = both%idx(e) + 1
          if (p <= n .and. q <= n) then
             w = w + 1
             both%idx(w) = q - 1
          else if ((p > n) .neqv. (q > n)) then
             g = max(p, q) - n
             cross%off(g) = cross%off(g) + 1
             cross%idx(cross%off(g)) = min(p, q) - 1
          end if
       end do
       start = both%off(a + 1)
       if (p <= n) then
          row = row + 1
          newperm(row) = p
          newoff(row + 1) = w
       end if
    end do
    do g = m, 1, -1                         ! (each row's offset moved to its end: shift back)
       cross%off(g + 1) = cross%off(g)
    end do
    cross%off(1) = 0
    rb%n = n
    rb%nnz = w
    call move_alloc(newoff, rb%off)
    call move_alloc(both%idx, rb%idx)
    call move_alloc(newperm, perm)
    call extra_rows(m, src, cross, xpart, xoff, xidx, info)
    return
90  info = ARPY_ERR_ALLOC
  end subroutine union_rows

  !> The pairs (r, s), r < s, of the rows of images (cross: row g lists the particles r, 0-based,
  !> near the image g of particle src(g)) as extra rows by r (type published in arpy_store): a stable
  !> sort by r, so each row keeps the images' order.
  subroutine extra_rows(m, src, cross, xpart, xoff, xidx, info)
    integer, intent(in) :: m, src(m)
    type(row_builder), intent(in) :: cross
    integer, allocatable, intent(inout) :: xpart(:), xidx(:)
    integer(i8), allocatable, intent(inout) :: xoff(:)
    integer, intent(out) :: info
    integer(i8), allocatable :: key(:)
    integer(i8) :: k, np
    integer :: g, j, stat
    info = ARPY_OK
    np = 0
    do g = 1, m
       np = np + count(cross%idx(cross%off(g) + 1:cross%off(g + 1)) < src(g))
    end do
    allocate(key(max(np, 1_i8)), xidx(max(np, 1_i8)), stat=stat)
    if (stat /= 0) goto 90
    np = 0
    do g = 1, m
       do k = cross%off(g) + 1, cross%off(g + 1)
          if (cross%idx(k) >= src(g)) cycle
          np = np + 1
          key(np) = cross%idx(k)
          xidx(np) = src(g)
       end do
    end do
    call radix_sort(int(np), key, xidx, 31, info)
    if (info /= ARPY_OK) return
    j = 0                                    ! one row per particle r
    if (np > 0) j = 1 + count(key(2:np) /= key(1:np - 1))
    allocate(xpart(j), xoff(j + 1), stat=stat)
    if (stat /= 0) goto 90
    j = 0
    xoff(1) = 0
    do k = 1, np
       if (k > 1) then
          if (key(k) == key(k - 1)) cycle
          xoff(j + 1) = k - 1
       end if
       j = j + 1
       xpart(j) = int(key(k)) + 1
    end do
    xoff(j + 1) = np
    return
90  info = ARPY_ERR_ALLOC
  end subroutine extra_rows

  !> order = a search's slot -> particle map `spread`, 0-based; spread becomes the identity, so the
  !> search writes slots where it wrote particle indices (in parallel for large n).
  subroutine slot_labels(n, spread, order)
    integer, intent(in) :: n
    integer, intent(inout) :: spread(n)
    integer(i8), intent(out) :: order(n)
    integer :: a
    !$omp parallel do num_threads(team_size()) if(n >= MIN_PARALLEL_ROWS) schedule(static)
    do a = 1, n
       order(a) = spread(a) - 1
       spread(a) = a
    end do
    !$omp end parallel do
  end subroutine slot_labels

  !> Shift number t (0 <= t < 3**d) of the images, s(ax) in {-1, 0, 1} with axis 1 the slowest
  !> digit; usable if it moves along some axis and only along periodic ones.
  pure subroutine image_shift(d, t, periodic, s, usable)
    integer, intent(in) :: d, t
    logical, intent(in) :: periodic(d)
    integer, intent(out) :: s(d)
    logical, intent(out) :: usable
    integer :: ax, rest
    rest = t
    do ax = d, 1, -1
       s(ax) = mod(rest, 3) - 1
       rest = rest / 3
    end do
    usable = any(s /= 0) .and. .not. any(s /= 0 .and. .not. periodic)
  end subroutine image_shift

  !> The image shifts t = 0 .. 3**d - 1 of image_shift as bit masks of axes (bit ax - 1): those
  !> shifted by +1 (up(t)) and by -1 (down(t)), and whether t is usable; made once per pass.
  pure subroutine shift_masks(d, periodic, up, down, usable)
    integer, intent(in) :: d
    logical, intent(in) :: periodic(d)
    integer, intent(out) :: up(0:), down(0:)
    logical, intent(out) :: usable(0:)
    integer :: t, ax, s(d)
    do t = 0, 3**d - 1
       call image_shift(d, t, periodic, s, usable(t))
       up(t) = 0
       down(t) = 0
       do ax = 1, d
          if (s(ax) == 1) up(t) = ibset(up(t), ax - 1)
          if (s(ax) == -1) down(t) = ibset(down(t), ax - 1)
       end do
    end do
  end subroutine shift_masks

  !> The faces a particle at xp with reach r lies within r of, as bit masks of axes: the low faces
  !> (near_lo) and the high faces (near_hi).
  pure subroutine face_masks(d, xp, r, lo, hi, near_lo, near_hi)
    integer, intent(in) :: d
    real(dp), intent(in) :: xp(d), r, lo(d), hi(d)
    integer, intent(out) :: near_lo, near_hi
    integer :: ax
    near_lo = 0
    near_hi = 0
    do ax = 1, d
       if (xp(ax) - lo(ax) <= r) near_lo = ibset(near_lo, ax - 1)
       if (hi(ax) - xp(ax) <= r) near_hi = ibset(near_hi, ax - 1)
    end do
  end subroutine face_masks

  !> Whether the particle of face_masks near_lo, near_hi has the image of the usable shift of masks
  !> up, down (shift_masks): it lies within its reach of the low face along every axis shifted by +1
  !> (imaged to the high side) and of the high face along every axis shifted by -1.
  pure logical function has_image(up, down, near_lo, near_hi)
    integer, intent(in) :: up, down, near_lo, near_hi
    has_image = iand(up, not(near_lo)) == 0 .and. iand(down, not(near_hi)) == 0
  end function has_image

  !> Whether a particle at xp with reach r is near a periodic face (has some image).
  pure logical function near_face(d, xp, r, lo, hi, periodic)
    integer, intent(in) :: d
    real(dp), intent(in) :: xp(d), r, lo(d), hi(d)
    logical, intent(in) :: periodic(d)
    integer :: ax
    near_face = .false.
    do ax = 1, d
       if (periodic(ax)) near_face = near_face .or. xp(ax) - lo(ax) <= r .or. hi(ax) - xp(ax) <= r
    end do
  end function near_face

  !> band(1:nband): the particles within r of a periodic face of the box [lo, hi], ascending (in
  !> parallel blocks of particles).
  subroutine face_band(d, n, x, r, lo, hi, periodic, band, nband, info)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), r, lo(d), hi(d)
    logical, intent(in) :: periodic(d)
    integer, allocatable, intent(inout) :: band(:)
    integer, intent(out) :: nband, info
    integer(int8), allocatable :: near(:)
    integer :: p, stat, nb, k, p0, p1, at
    integer :: bcount(MAX_BLOCKS)
    info = ARPY_OK
    allocate(near(n), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    nb = min(team_size(), MAX_BLOCKS)
    if (n < MIN_PARALLEL_ROWS) nb = 1
    ! each block of particles flags and counts its own, then lists them from its first place
    !$omp parallel do num_threads(nb) schedule(static, 1) private(p0, p1, p)
    do k = 1, nb
       call block_range(n, nb, k, p0, p1)
       bcount(k) = 0
       do p = p0, p1
          near(p) = 0
          if (near_face(d, x(:, p), r, lo, hi, periodic)) then
             near(p) = 1
             bcount(k) = bcount(k) + 1
          end if
       end do
    end do
    !$omp end parallel do
    nband = sum(bcount(1:nb))
    allocate(band(max(nband, 1)), stat=stat)
    if (stat /= 0) then
       info = ARPY_ERR_ALLOC
       return
    end if
    !$omp parallel do num_threads(nb) schedule(static, 1) private(p0, p1, p, at)
    do k = 1, nb
       call block_range(n, nb, k, p0, p1)
       at = sum(bcount(1:k - 1))
       do p = p0, p1
          if (near(p) == 1) then
             at = at + 1
             band(at) = p
          end if
       end do
    end do
    !$omp end parallel do
  end subroutine face_band

  !> Number of images of n particles with reaches rc + skin in the box [lo, hi] (periodic axes
  !> only); only the particles of ``subset`` (ascending, 1-based), when given, can have images.
  subroutine image_count(d, n, x, rc, skin, lo, hi, periodic, m, subset)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), rc(n), skin, lo(d), hi(d)
    logical, intent(in) :: periodic(d)
    integer, intent(out) :: m
    integer, intent(in), optional :: subset(:)
    integer :: cnt(0:3**d - 1, MAX_BLOCKS)
    integer :: nb
    call count_images(d, n, x, rc, skin, lo, hi, periodic, nb, cnt, subset)
    m = sum(cnt(:, 1:nb))
  end subroutine image_count

  !> The number of candidates (subset's, or all n particles) and candidate i's particle.
  pure integer function candidates(n, subset)
    integer, intent(in) :: n
    integer, intent(in), optional :: subset(:)
    candidates = n
    if (present(subset)) candidates = size(subset)
  end function candidates

  pure integer function candidate(i, subset)
    integer, intent(in) :: i
    integer, intent(in), optional :: subset(:)
    candidate = i
    if (present(subset)) candidate = subset(i)
  end function candidate

  !> The images of every shift (in the order of image_shift) in every block of candidates
  !> (blocks of block_range, in parallel from MIN_PARALLEL_ROWS candidates): cnt(t, b).
  subroutine count_images(d, n, x, rc, skin, lo, hi, periodic, nb, cnt, subset)
    integer, intent(in) :: d, n
    real(dp), intent(in) :: x(d, n), rc(n), skin, lo(d), hi(d)
    logical, intent(in) :: periodic(d)
    integer, intent(out) :: nb, cnt(0:, :)
    integer, intent(in), optional :: subset(:)
    integer :: b, i, p, p0, p1, t, nc, up(0:3**d - 1), down(0:3**d - 1), near_lo, near_hi
    logical :: usable(0:3**d - 1)
    nc = candidates(n, subset)
    nb = 1
    if (nc >= MIN_PARALLEL_ROWS) nb = min(team_size(), MAX_BLOCKS)
    call shift_masks(d, periodic, up, down, usable)
    !$omp parallel do num_threads(nb) schedule(static, 1) private(i, p, p0, p1, t, near_lo, near_hi)
    do b = 1, nb
       cnt(:, b) = 0
       call block_range(nc, nb, b, p0, p1)
       do i = p0, p1
          p = candidate(i, subset)
          if (.not. near_face(d, x(:, p), rc(p) + skin, lo, hi, periodic)) cycle
          call face_masks(d, x(:, p), rc(p) + skin, lo, hi, near_lo, near_hi)
          do t = 0, 3**d - 1
             if (usable(t)) then
                if (has_image(up(t), down(t), near_lo, near_hi)) cnt(t, b) = cnt(t, b) + 1
             end if
          end do
       end do
    end do
    !$omp end parallel do
  end subroutine count_images

  !> The m images: positions xg(:, k) = x + s (hi - lo) and sources src(k) (0-based), by shift
  !> (in the order of image_shift), then by particle; only the particles of ``subset`` (ascending,
  !> 1-based), when given, can have images.  Blocks of candidates in parallel, each writing its
  !> images of each shift from its own offset: the order of a serial pass.
  subroutine image_fill(d, n, x, rc, skin, lo, hi, periodic, m, xg, src, info, subset)
    integer, intent(in) :: d, n, m
    real(dp), intent(in) :: x(d, n), rc(n), skin, lo(d), hi(d)
    logical, intent(in) :: periodic(d)
    real(dp), intent(out) :: xg(d, m)
    integer, intent(out) :: src(m), info
    integer, intent(in), optional :: subset(:)
    integer :: cnt(0:3**d - 1, MAX_BLOCKS)
    integer :: nb, b, t, i, p, p0, p1, k, total, s(d), up(0:3**d - 1), down(0:3**d - 1), near_lo, near_hi
    logical :: usable(0:3**d - 1), shift_ok
    info = ARPY_OK
    call count_images(d, n, x, rc, skin, lo, hi, periodic, nb, cnt, subset)
    if (sum(cnt(:, 1:nb)) /= m) then
       info = ARPY_ERR_SIZE
       return
    end if
    ! cnt(t, b): the slot before block b's images of shift t (shifts in order, blocks within one)
    call cell_prefix(0_i8, int(3**d - 1, i8), nb, cnt, 0_i8, int(3**d - 1, i8), 0, total)
    call shift_masks(d, periodic, up, down, usable)
    !$omp parallel do num_threads(nb) schedule(static, 1) private(i, p, p0, p1, t, s, shift_ok, k, near_lo, near_hi)
    do b = 1, nb
       call block_range(candidates(n, subset), nb, b, p0, p1)
       do i = p0, p1                           ! one pass; each shift's images in particle order
          p = candidate(i, subset)
          if (.not. near_face(d, x(:, p), rc(p) + skin, lo, hi, periodic)) cycle
          call face_masks(d, x(:, p), rc(p) + skin, lo, hi, near_lo, near_hi)
          do t = 0, 3**d - 1
             if (.not. usable(t)) cycle
             if (.not. has_image(up(t), down(t), near_lo, near_hi)) cycle
             call image_shift(d, t, periodic, s, shift_ok)
             cnt(t, b) = cnt(t, b) + 1
             k = cnt(t, b)
             xg(:, k) = x(:, p) + real(s, dp) * (hi - lo)
             src(k) = p - 1
          end do
       end do
    end do
    !$omp end parallel do
  end subroutine image_fill

  !> Verlet lists reused: the entries q of row p of a cross list (queries xq with cutoffs rq, sources
  !> xs with cutoffs rs; 0-based entries) that lie within min(rq_p, rs_q) of the query now, in their
  !> order, by the test of the list builders (squared distance against the squared smaller cutoff).
  !> Out: off_out(m + 1) and idx_out(1:off_out(m + 1)).  Rows in parallel, each written once.
  subroutine filter_rows(d, m, xq, rq, ns, xs, rs, nnz, off, idx, off_out, idx_out)
    integer, intent(in) :: d, m, ns
    real(dp), intent(in) :: xq(d, m), rq(m), xs(d, ns), rs(ns)
    integer(i8), intent(in) :: nnz, off(m + 1)
    integer, intent(in) :: idx(nnz)
    integer(i8), intent(out) :: off_out(m + 1)
    integer, intent(out) :: idx_out(nnz)
    integer(i8) :: k, at
    integer :: p
    ! pass 1: the kept entries of each row; pass 2: written from the row's offset on
    off_out(1) = 0
    !$omp parallel do num_threads(team_size()) if(m >= MIN_PARALLEL_POINTS) schedule(static) private(k)
    do p = 1, m
       off_out(p + 1) = 0
       do k = off(p) + 1, off(p + 1)
          if (within(p, idx(k) + 1)) off_out(p + 1) = off_out(p + 1) + 1
       end do
    end do
    !$omp end parallel do
    do p = 1, m
       off_out(p + 1) = off_out(p + 1) + off_out(p)
    end do
    !$omp parallel do num_threads(team_size()) if(m >= MIN_PARALLEL_POINTS) schedule(static) private(k, at)
    do p = 1, m
       at = off_out(p)
       do k = off(p) + 1, off(p + 1)
          if (.not. within(p, idx(k) + 1)) cycle
          at = at + 1
          idx_out(at) = idx(k)
       end do
    end do
    !$omp end parallel do

  contains

    !> The builders' test (dx, dy, dz = source - query; dz = 0 in 2D).
    pure logical function within(p, q)
      integer, intent(in) :: p, q
      real(dp) :: dx, dy, dz, rm
      dx = xs(1, q) - xq(1, p)
      dy = xs(2, q) - xq(2, p)
      dz = 0.0_dp
      if (d == 3) dz = xs(3, q) - xq(3, p)
      rm = min(rq(p), rs(q))
      within = dx * dx + dy * dy + dz * dz <= rm * rm
    end function within

  end subroutine filter_rows

end module arpy_search
