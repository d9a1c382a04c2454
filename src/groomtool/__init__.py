"""groomtool: rest curvatures that make a groom a stable equilibrium under gravity and frictional contact."""

from .groom import Groom, GroomError
from .material import Material
from .api import export, inversion_params, invert, load, load_head  # noqa: E402  (after the data classes)
from .version import __version__

__all__ = ["Groom", "GroomError", "Material", "__version__", "export", "inversion_params", "invert", "load",
           "load_head"]
