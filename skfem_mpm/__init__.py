"""skfem-mpm: the Material Point Method with B-spline bases, as a scikit-fem plugin."""
__version__ = "0.1.0"

from .lagrange import LagrangeGrid
from .particles import Particles
from .quadrature import ParticleBasis, transfer_matrices
from .spline import (ElementLineBSpline, ElementQuadBSpline, MappingRectangular,
                     SplineGrid)

__all__ = [
    "__version__",
    "ElementLineBSpline",
    "ElementQuadBSpline",
    "MappingRectangular",
    "LagrangeGrid",
    "ParticleBasis",
    "Particles",
    "SplineGrid",
    "transfer_matrices",
]
