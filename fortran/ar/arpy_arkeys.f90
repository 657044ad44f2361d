!> Cells and cell keys of the adaptive-resolution (AR) tree (Awile,
!> Buyukkececi, Reboux, Sbalzarini, CPC 2012): levels, cell coordinates,
!> Morton codes and the level-order index J.
!>
!> Domain and levels.  The domain [lo, hi] (default: the particles' bounding
!> box) is made cubic with edge D_m = max(hi - lo) anchored at lo (footnote 1);
!> if all particles coincide, D_m = max(rc).  Geometry uses the normalised
!> coordinates u = (x - lo) / D_m clipped to [0, 1], in which every cell corner
!> and midpoint is an exact dyadic number.  Level k (root = 0, cell edge
!> D_m / 2**k) holds the particles with D_m/2**k > rc >= D_m/2**(k+1); cutoffs
!> >= D_m/2 go to level 0.  The level-k cell of u has integer coordinates
!> c_i = min(floor(u_i 2**k), 2**k - 1).
!>
!> Level-order index J (the hash key).  Root J = 1; children of J are
!> J 2**d + l - 2**d + 2 (l = 0 .. 2**d - 1, axis 1 the most significant bit
!> of l, the split order of Algorithm 2); parent (J + 2**d - 2) / 2**d.  In
!> closed form J = F(k) + M_k(c) with F(k) = (2**(dk) - 1)/(2**d - 1) + 1 and
!> M_k the Morton (Z-order) code of c with axis 1 most significant.  J fits
!> int64 up to level 30 in 2D and 20 in 3D; deeper trees are refused
!> (ARPY_ERR_DEPTH).
module arpy_arkeys
  use arpy_kinds, only: dp, i8
  implicit none
  private

  !> deepest level whose J still fits int64, for d = 2 and d = 3
  integer, parameter, public :: AR_MAXLEVEL(2:3) = [30, 20]

  ! Morton codes by bit spreading: table SPREAD2 puts the low 31 bits of a
  ! coordinate on the even bit positions, SPREAD3 the low 21 bits on every
  ! third one; GATHER2 and GATHER3 collect them back (see morton_bits).
  integer, parameter :: SPREAD2 = 1, SPREAD3 = 2, GATHER2 = 3, GATHER3 = 4
  integer, parameter :: MORTON_SHIFT(5, 4) = reshape([ &
       16, 8, 4, 2, 1, &
       32, 16, 8, 4, 2, &
       -1, -2, -4, -8, -16, &
       -2, -4, -8, -16, -32], [5, 4])
  integer(i8), parameter :: MORTON_MASK(0:5, 4) = reshape([ &
       2147483647_i8, 281470681808895_i8, 71777214294589695_i8, &
       1085102592571150095_i8, 3689348814741910323_i8, 6148914691236517205_i8, &
       2097151_i8, 8725724278095871_i8, 8725728556220671_i8, &
       1157144660301377551_i8, 1207822528635744451_i8, 1317624576693539401_i8, &
       6148914691236517205_i8, 3689348814741910323_i8, 1085102592571150095_i8, &
       71777214294589695_i8, 281470681808895_i8, 4294967295_i8, &
       1317624576693539401_i8, 1207822528635744451_i8, 1157144660301377551_i8, &
       8725728556220671_i8, 8725724278095871_i8, 2097151_i8], [6, 4])

  public :: ar_first_index, ar_morton, morton_coords, ar_decode, stencil_morton
  public :: ar_level_of, pow2, axis_cell

contains

  !> First level-order index on level k: F(k) = (2**(d k) - 1)/(2**d - 1) + 1.
  pure function ar_first_index(d, k) result(f)
    integer, intent(in) :: d, k
    integer(i8) :: f
    ! constant divisors, so no integer division instruction is emitted
    if (d == 2) then
       f = (ishft(1_i8, 2 * k) - 1_i8) / 3_i8 + 1_i8
    else
       f = (ishft(1_i8, 3 * k) - 1_i8) / 7_i8 + 1_i8
    end if
  end function ar_first_index

  !> The bits of v spread or gathered by table j (SPREAD2, SPREAD3, GATHER2,
  !> GATHER3): v masked by MORTON_MASK(0, j), then for each step i the bits
  !> shifted by MORTON_SHIFT(i, j) joined in and masked by MORTON_MASK(i, j).
  pure function morton_bits(v, j) result(r)
    integer(i8), intent(in) :: v
    integer, intent(in) :: j
    integer(i8) :: r
    integer :: i
    r = iand(v, MORTON_MASK(0, j))
    do i = 1, 5
       r = iand(ior(r, ishft(r, MORTON_SHIFT(i, j))), MORTON_MASK(i, j))
    end do
  end function morton_bits

  !> Morton code of integer cell coordinates c(1:d), axis 1 most significant.
  pure function ar_morton(d, c) result(m)
    integer, intent(in) :: d
    integer(i8), intent(in) :: c(3)
    integer(i8) :: m
    if (d == 2) then
       m = ior(ishft(morton_bits(c(1), SPREAD2), 1), morton_bits(c(2), SPREAD2))
    else
       m = ior(ior(ishft(morton_bits(c(1), SPREAD3), 2), ishft(morton_bits(c(2), SPREAD3), 1)), &
            morton_bits(c(3), SPREAD3))
    end if
  end function ar_morton

  !> Cell coordinates from a Morton code (inverse of ar_morton).
  pure subroutine morton_coords(d, m, c)
    integer, intent(in) :: d
    integer(i8), intent(in) :: m
    integer(i8), intent(out) :: c(3)
    c = 0
    if (d == 2) then
       c(1) = morton_bits(ishft(m, -1), GATHER2)
       c(2) = morton_bits(m, GATHER2)
    else
       c(1) = morton_bits(ishft(m, -2), GATHER3)
       c(2) = morton_bits(ishft(m, -1), GATHER3)
       c(3) = morton_bits(m, GATHER3)
    end if
  end subroutine morton_coords

  !> The Morton parts of the coordinates around cell c on a level with m cells
  !> per axis: sx(o), sy(o), sz(o) for c + o along axes 1, 2, 3 (o = -1, 0, 1;
  !> sz = 0 in 2D), -1 where c + o lies outside [0, m).  The Morton code of
  !> cell c + (ox, oy, oz) is ior(ior(sx(ox), sy(oy)), sz(oz)).
  pure subroutine stencil_morton(d, c, m, sx, sy, sz)
    integer, intent(in) :: d
    integer(i8), intent(in) :: c(3), m
    integer(i8), intent(out) :: sx(-1:1), sy(-1:1), sz(-1:1)
    integer :: o
    do o = -1, 1
       if (d == 2) then
          sx(o) = ishft(morton_bits(c(1) + o, SPREAD2), 1)
          sy(o) = morton_bits(c(2) + o, SPREAD2)
          sz(o) = 0
       else
          sx(o) = ishft(morton_bits(c(1) + o, SPREAD3), 2)
          sy(o) = ishft(morton_bits(c(2) + o, SPREAD3), 1)
          sz(o) = morton_bits(c(3) + o, SPREAD3)
       end if
       if (c(1) + o < 0 .or. c(1) + o >= m) sx(o) = -1
       if (c(2) + o < 0 .or. c(2) + o >= m) sy(o) = -1
       if (d == 3 .and. (c(3) + o < 0 .or. c(3) + o >= m)) sz(o) = -1
    end do
  end subroutine stencil_morton

  !> Level and integer coordinates of cell J (inverse of F(k) + Morton).
  pure subroutine ar_decode(d, key, k, c)
    integer, intent(in) :: d
    integer(i8), intent(in) :: key
    integer, intent(out) :: k
    integer(i8), intent(out) :: c(3)
    k = 0
    do while (k < AR_MAXLEVEL(d))
       if (ar_first_index(d, k + 1) > key) exit
       k = k + 1
    end do
    call morton_coords(d, key - ar_first_index(d, k), c)
  end subroutine ar_decode

  !> Level of a cutoff: the k >= 0 with D_m/2**k > rc >= D_m/2**(k+1) (exact:
  !> products with powers of two).  Levels beyond 62 are reported as 63.
  pure function ar_level_of(rc, dm) result(k)
    real(dp), intent(in) :: rc, dm
    integer :: k
    if (rc * 2.0_dp >= dm) then
       k = 0
       return
    end if
    ! estimate from the binary exponents, then make it exact
    k = int(iand(ishft(transfer(dm, 0_i8), -52), 2047_i8) &
         - iand(ishft(transfer(rc, 0_i8), -52), 2047_i8)) - 2
    k = min(max(k, 0), 62)
    do while (rc * pow2(k + 1) < dm)
       k = k + 1
       if (k == 63) return
    end do
    do while (k > 0)
       if (rc * pow2(k) < dm) exit
       k = k - 1
    end do
  end function ar_level_of

  !> 2**k as a real (exact), 0 <= k <= 63.
  elemental function pow2(k) result(p)
    integer, intent(in) :: k
    real(dp) :: p
    p = real(ishft(1_i8, min(k, 62)), dp) * merge(2.0_dp, 1.0_dp, k == 63)
  end function pow2

  !> Integer cell coordinate on a level with 2**k cells per axis (p2 = 2**k,
  !> top = 2**k - 1) of a coordinate y along an axis starting at lo.
  elemental function axis_cell(y, lo, dm, p2, top) result(c)
    real(dp), intent(in) :: y, lo, dm, p2
    integer(i8), intent(in) :: top
    integer(i8) :: c
    c = min(int(min(max((y - lo) / dm, 0.0_dp), 1.0_dp) * p2, i8), top)
  end function axis_cell

end module arpy_arkeys
