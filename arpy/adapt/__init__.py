"""Adaptation of a particle set to a target resolution (Reboux et al. 2012, §2.3).

* :mod:`~arpy.adapt.resolution`: the target resolution: monitors (Eq. 2.8, Eq. B.13), Eq. 2.9, r*, N*,
  and :class:`~arpy.adapt.resolution.SampledResolution` / :func:`~arpy.adapt.resolution.field_resolution`
  (D_p given on an old particle set);
* :mod:`~arpy.adapt.forces`: the pseudo-force potentials and the energy W with its gradient;
* :mod:`~arpy.adapt.organize`: :func:`~arpy.adapt.organize.self_organize` (one process or ranks),
  which returns a :class:`arpy.particles.Particles`;
* :mod:`~arpy.adapt.adaptation`: the adaptation loop (fusion, insertion, gradient descent with line
  search);
* :mod:`~arpy.adapt.view`: the particles as the loop sees them on a rank (one process: P = 1).
"""

from .organize import self_organize
from .resolution import SampledResolution, field_resolution

__all__ = ["SampledResolution", "field_resolution", "self_organize"]
