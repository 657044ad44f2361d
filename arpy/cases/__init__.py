"""The test cases of §4 of Reboux et al. (2012), one module per section, and their registry.

* :mod:`~arpy.cases.convergence` -- §4.1: :func:`consistency`, interpolation and Laplacian
  errors on the tanh front (Eq. 4.1), or on the blob of §4.2 (Eq. 4.3), while D0 shrinks by a
  factor per adaptation;
* :mod:`~arpy.cases.reversing_vortex` -- §4.2: :func:`advection`, a blob (Eq. 4.3) advected by
  the reversing vortex (Eq. 4.4) in the periodic unit square, RK4, error Eq. 4.5 at T; the blob's
  field and exact derivatives, :func:`advection_exact`;
* :mod:`~arpy.cases.pulse` -- §4.3: :func:`gaussian_pulse`, a Gaussian pulse (Eq. 4.6) rotated
  and diffused (Eq. 4.7) in 2D or 3D, L-infinity error against Eq. 4.8, the relative mass loss
  (Eq. 4.9) over time; :func:`remeshed_pulse`, the remeshed-particle baseline;
* :mod:`~arpy.cases.burgers2d` -- §4.4: :func:`burgers`, the 2D Burgers equation (Eq. 4.10),
  u = (f, f), doubly periodic, against a pseudo-spectral reference; :func:`remeshed_burgers`,
  the remeshed baseline in conservative form (Eq. 4.11);
* :mod:`~arpy.cases.buckley_leverett` -- §4.5: :func:`five_spot`, the viscous Buckley-Leverett
  equation in the five-spot velocity field;
* :mod:`~arpy.cases.bud` -- §4.6: :func:`bud_surface`, particles self-organized in a narrow band
  around a budding-cell surface, resolution from its curvature (Eq. 4.14);
* :mod:`~arpy.cases.reaction_diffusion` -- :func:`manufactured`, a reaction-diffusion system with a
  compressible flow and Dirichlet and Neumann walls against its exact solution: how to write a
  right-hand side of your own;
* :mod:`~arpy.cases.analysis` -- what several share: :func:`slope`, :func:`equal_error_ratio`;
* :mod:`~arpy.cases.registry` -- :class:`~arpy.cases.registry.Case` and
  :class:`~arpy.cases.registry.Param`: each section module declares its case (parameters with
  defaults, units and checks, and its runner) as ``CASE``; :data:`CASES` collects them and the
  command line ``arpy run <case> [options]`` is built from it.

The modules are not named after the case functions (``advection``, ``burgers``, ...) so that
``arpy.cases.advection`` is always the function.
"""

from __future__ import annotations

from . import (analysis, bud, buckley_leverett, burgers2d, convergence, pulse, reaction_diffusion, registry,
               reversing_vortex)
from .analysis import equal_error_ratio, slope
from .buckley_leverett import (FIVE_SPOT_WELLS, buckley_leverett_flux, buckley_leverett_speed, five_spot,
                               five_spot_velocity)
from .bud import BUD_DMIN, BUD_MAX_PARTICLES, BUD_PAPER_N, ball_inside, bud_surface
from .burgers2d import (burgers, burgers_initial, burgers_initial_gradient, burgers_reference, burgers_velocity,
                        remeshed_burgers)
from .convergence import CONSISTENCY_FACTOR, CONSISTENCY_START, consistency, consistency_levels, consistency_start
from .pulse import PULSE_D0, PULSE_PE, gaussian_pulse, pulse_d0, pulse_exact, pulse_pe, pulse_setup, remeshed_pulse
from .reaction_diffusion import manufactured, manufactured_exact
from .registry import Case, Param
from .reversing_vortex import (ADVECTION_D0, BLOB_MAX_SLOPE, C1, C2, X0, advection, advection_d0, advection_exact,
                               blob, blob_fourth_derivatives, blob_gradient, blob_laplacian, blob_monitor, vortex)

#: The cases of ``arpy run``, by name, in the order ``arpy run --help`` lists them; the first is the default.
CASES: dict[str, Case] = {c.name: c for c in (pulse.CASE, reversing_vortex.CASE, burgers2d.CASE,
                                              buckley_leverett.CASE, convergence.CASE, bud.CASE,
                                              reaction_diffusion.CASE)}

__all__ = ["ADVECTION_D0", "BLOB_MAX_SLOPE", "BUD_DMIN", "BUD_MAX_PARTICLES", "BUD_PAPER_N", "C1", "C2", "CASES",
           "CONSISTENCY_FACTOR", "CONSISTENCY_START", "FIVE_SPOT_WELLS", "PULSE_D0", "PULSE_PE", "X0", "Case",
           "Param", "advection", "advection_d0", "advection_exact", "ball_inside", "blob", "blob_fourth_derivatives",
           "blob_gradient", "blob_laplacian", "blob_monitor", "buckley_leverett_flux", "buckley_leverett_speed",
           "bud_surface", "burgers", "burgers_initial", "burgers_initial_gradient", "burgers_reference",
           "burgers_velocity", "consistency", "consistency_levels", "consistency_start", "equal_error_ratio",
           "five_spot", "five_spot_velocity", "gaussian_pulse", "manufactured", "manufactured_exact", "pulse_d0",
           "pulse_exact", "pulse_pe", "pulse_setup", "remeshed_burgers", "remeshed_pulse", "slope", "vortex"]
