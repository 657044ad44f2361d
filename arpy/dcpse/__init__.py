"""DC-PSE operators: the kernel, the operators in a domain with their repair, the paper's displacement
rule, boundary conditions, and the operators a simulation applies by name.

* :mod:`~arpy.dcpse.kernel`: :class:`~arpy.dcpse.kernel.DCPSE` (free space, Appendix A of Reboux et
  al. 2012) and :class:`~arpy.dcpse.kernel.DegenerateStencilError`;
* :mod:`~arpy.dcpse.domain`: :class:`~arpy.dcpse.domain.DomainDCPSE` (ghost sources at the boundary)
  and the repair policy :data:`~arpy.dcpse.domain.REPAIR` with its checks of wild rows;
* :mod:`~arpy.dcpse.rows`: the rows' absolute sums (Lebesgue constants, Gershgorin radii, the
  weight scales of rows at the particles) and products limited row by row;
* :mod:`~arpy.dcpse.displace`: the paper's rule, :func:`~arpy.dcpse.displace.displace_until_valid`;
* :mod:`~arpy.dcpse.boundary`: boundary conditions of a field on the walls of a box;
* :mod:`~arpy.dcpse.operators`: :class:`~arpy.dcpse.operators.Operators`, the operators of a stage
  applied to the fields by name;
* :mod:`~arpy.dcpse.scattered`: :func:`~arpy.dcpse.scattered.core_sizes`, core sizes for scattered data
  from the local spacing.
"""

from .boundary import Conditions, Dirichlet, Neumann, conditions, face_names
from .displace import (DISPLACE_ROUNDS, STENCIL_RULES, Displaced, check_stencil_rule, displace_until_valid,
                       repair_for)
from .domain import (LEBESGUE_MAX, MAX_GATHER, MILD_GATHER, MILD_LEBESGUE, NO_REPAIR, REPAIR, WIDE_GATHER, WIDEN,
                     DomainDCPSE, Repair, bounded_apply, lebesgue_constants)
from .kernel import (DCPSE, DEFAULT_C, DEFAULT_MAX_COND, MAX_ORDER, DegenerateStencilError, gradient_indices,
                     n_unknowns)
from .operators import Operators
from .scattered import CORE_FACTOR, CORE_NEIGHBOURS, core_sizes

__all__ = ["CORE_FACTOR", "CORE_NEIGHBOURS", "Conditions", "DCPSE", "DEFAULT_C", "DEFAULT_MAX_COND", "DISPLACE_ROUNDS", "DegenerateStencilError",
           "Dirichlet", "Displaced", "DomainDCPSE", "LEBESGUE_MAX", "MAX_GATHER", "MAX_ORDER", "MILD_GATHER",
           "MILD_LEBESGUE", "NO_REPAIR", "Neumann", "Operators", "REPAIR", "Repair", "STENCIL_RULES", "WIDEN",
           "WIDE_GATHER", "bounded_apply", "check_stencil_rule", "conditions", "core_sizes", "displace_until_valid", "face_names",
           "gradient_indices", "lebesgue_constants", "n_unknowns", "repair_for"]
