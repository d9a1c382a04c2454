"""Floating tangents: polylines -> G1 piecewise helices, the Super-Helix state of a groom."""

from .fitter import FitResult, FixedFit, effective_tolerance, fit_groom, fit_polyline_fixed
from .helix import HelixSolution, helix_residuals, solve_helix
from .cohelicity import relax_points

__all__ = ["FitResult", "FixedFit", "HelixSolution", "effective_tolerance", "fit_groom",
           "fit_polyline_fixed", "helix_residuals", "relax_points", "solve_helix"]
