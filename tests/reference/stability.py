"""References for groomtool.stability that only the tests use.

* :func:`contact_load_hessians_reference`: ``stability.contact_load_hessians`` as it was before the analytic
  Super-Helix Hessian (superhelix.point_load_hessian_parts): central differences of the exact generalized
  force contact.jacobian.point_forces_generalized, 2n perturbed copies of each strand, symmetrised; about
  1e-10 relative error.  The package keeps them for Super Space Clothoids
  (``stability.finite_difference_load_hessians``), so they are not copied here.
"""

from __future__ import annotations

from groomtool.stability import finite_difference_load_hessians as contact_load_hessians_reference

__all__ = ["contact_load_hessians_reference"]
