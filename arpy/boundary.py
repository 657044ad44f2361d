"""Deprecated path of :mod:`arpy.dcpse.boundary` (boundary conditions of a field on the walls of a box).

Kept only because the example of :class:`arpy.simulation.Simulation` imports from it; import from
:mod:`arpy.dcpse.boundary` instead.  Importing this module warns (DeprecationWarning).
"""

import warnings

from .dcpse.boundary import Condition, Conditions, Dirichlet, Neumann, WallValue, conditions, face_names

__all__ = ["Condition", "Conditions", "Dirichlet", "Neumann", "WallValue", "conditions", "face_names"]

warnings.warn("arpy.boundary is deprecated: import from arpy.dcpse.boundary", DeprecationWarning, stacklevel=2)
