"""References for groomtool.invert and groomtool.stability: the original dense routes that the
chunked, compiled ones replaced, for the tests that compare them (to round-off).

* :func:`equilibrium_residuals_reference`: :func:`groomtool.inverse_problem.equilibrium_residuals` as it was
  (kinematics twice, the second time padded to the longest strand), with the dense point-Jacobian
  H^T r of reference.contact.generalized_contact_force_reference.
* :func:`stiffness_ratios_reference`: :func:`groomtool.stability.stiffness_ratios` by batched
  eigvalsh of the padded dense matrices.
"""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_limits

from groomtool.inverse_problem import gravity_force
from groomtool.material import Material
from groomtool.rods import superhelix as sh
from reference.contact import generalized_contact_force_reference
from reference.rods import gravity_force_jacobian_reference


def equilibrium_residuals_reference(helix: sh.SuperHelix, rest_curvatures, material: Material, gravity,
                                    contacts=None, forces=None) -> np.ndarray:
    """The original :func:`equilibrium_residuals` (kinematics twice, the second time padded to the
    longest strand), with the dense point-Jacobian H^T r."""
    F = gravity_force(helix, material, gravity)
    K = sh.stiffness(helix, material.stiffness_diag)
    res = K * (helix.curvatures - rest_curvatures) - F
    if contacts is not None and forces is not None and len(forces):
        res -= generalized_contact_force_reference(helix, contacts, forces)
    num = np.linalg.norm(res.reshape(helix.n_strands, -1), axis=1)
    den = np.linalg.norm(F.reshape(helix.n_strands, -1), axis=1)
    return num / np.maximum(den, np.finfo(float).tiny)


def stiffness_ratios_reference(helix: sh.SuperHelix, stiffness_diag, linear_density: float, gravity,
                               chunk: int = 256, progress=None) -> np.ndarray:
    """The original dense route: batched eigvalsh of the padded matrices (with chunk > 1 a strand shorter than the longest
    of its chunk gets max(rho, 0), the padding's zeros)."""
    order = np.argsort(helix.n_elements, kind="stable")
    out = np.empty(helix.n_strands)
    with threadpool_limits(1, user_api="blas"):
        for start in range(0, helix.n_strands, chunk):
            ids = order[start:start + chunk]
            out[ids] = _ratios(helix.subset(ids), stiffness_diag, linear_density, gravity)
            if progress is not None:
                progress.update(len(ids))
    return out


def _ratios(helix, stiffness_diag, linear_density, gravity):
    dF = gravity_force_jacobian_reference(helix, linear_density, gravity)
    K = sh.stiffness(helix, stiffness_diag).reshape(helix.n_strands, -1)
    K = np.where(K > 0, K, 1.0)  # padding dofs: dF is zero there, any K works
    scale = 1.0 / np.sqrt(K)
    A = scale[:, :, None] * dF * scale[:, None, :]
    return np.linalg.eigvalsh(A)[:, -1]

