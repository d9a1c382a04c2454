"""groomtool: rest curvatures that make a groom a stable equilibrium under gravity and frictional contact."""

from .groom import Groom, GroomError
from .material import Material

__version__ = "0.1.0"

__all__ = ["Groom", "GroomError", "Material", "__version__"]
