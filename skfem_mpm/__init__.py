"""skfem-mpm: the Material Point Method with B-spline bases, as a scikit-fem plugin."""
__version__ = "0.1.0"

# numba's customizations (kernels.wrappers, kernels.cache_files) before any
# module of the package defines a compiled function
from . import kernels  # noqa: F401, I001
from .effects import BodyForce, Damping, Fixed, Footing, Gravity, Prescribed, Traction, Wall
from .errors import SimulationError
from .geostatic import geostatic_stress
from .lagrange import LagrangeGrid
from .materials import BBar, DruckerPrager, LinearElastic, MohrCoulomb, NeoHookean, VonMises
from .particles import Particles
from .quadrature import ParticleBasis, transfer_matrices
from .scene import Body, Scene
from .solve import Method, fem, simulate
from .spline import (ElementHexBSpline, ElementLineBSpline, ElementQuadBSpline,
                     MappingRectangular, SplineGrid)

__all__ = [
    "__version__",
    "Body",
    "BodyForce",
    "Damping",
    "Wall",
    "Footing",
    "geostatic_stress",
    "Fixed",
    "Gravity",
    "LinearElastic",
    "MohrCoulomb",
    "DruckerPrager",
    "VonMises",
    "BBar",
    "Method",
    "NeoHookean",
    "Prescribed",
    "Scene",
    "SimulationError",
    "Traction",
    "fem",
    "simulate",
    "ElementHexBSpline",
    "ElementLineBSpline",
    "ElementQuadBSpline",
    "MappingRectangular",
    "LagrangeGrid",
    "ParticleBasis",
    "Particles",
    "SplineGrid",
    "transfer_matrices",
]
