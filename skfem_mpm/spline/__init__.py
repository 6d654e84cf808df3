"""B-spline spaces on scikit-fem meshes (Bezier extraction)."""
from .bernstein import bernstein, bernstein_derivative
from .dofs import SplineDofs
from .element import ElementHexBSpline, ElementLineBSpline, ElementQuadBSpline
from .grid import SplineGrid
from .knots import extraction_operators, open_knot_vector
from .mapping import MappingRectangular

__all__ = [
    "ElementHexBSpline",
    "ElementLineBSpline",
    "ElementQuadBSpline",
    "MappingRectangular",
    "SplineDofs",
    "SplineGrid",
    "bernstein",
    "bernstein_derivative",
    "extraction_operators",
    "open_knot_vector",
]
