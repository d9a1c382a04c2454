"""References and helpers for groomtool.rods that only the tests use.

* :func:`clothoid_gravity_force_jacobian_full`: ``rods.clothoid.gravity_force_jacobian`` by the complex
  step with every element recomputed per column (the fast one recomputes only a node's two elements).
* :func:`clothoid_gravity_hessian_factors`: the factors of the separable far blocks of the clothoid's gravity
  Hessian (the analytic dF/dq in progress), checked against ``gravity_force_jacobian``.
* :func:`kinematics_reference`: ``rods.superhelix.kinematics`` with vectorised numpy (the compiled one
  evaluates each element's closed forms in one pass).
* :func:`gravity_force_jacobian_reference`: ``rods.superhelix.gravity_force_jacobian`` assembled with dense
  batched matmuls, its diagonal blocks by :func:`psi_form_hessian` (the vectorised form of the compiled
  ``superhelix._form_hessian_add``).
* :func:`transport`, :func:`rotate_about`: frames moved along a discrete rod (tests of the DER rest data).
* :func:`f_table`: the functions f_n(x) = c_n(1, x) and their derivatives, through ``rods.series.c_table``.
"""

from __future__ import annotations

import numpy as np

from groomtool.rods import clothoid as cl
from groomtool.rods import discrete as dr
from groomtool.rods import superhelix as sh
from groomtool.rods.series import c_table


def f_table(x: np.ndarray):
    """f_n(x), f_n'(x), f_n''(x) for n = 0..4, each with a leading axis of size 5 (x >= 0, any shape):
    ``c_table`` at t = 1 (c_n(1, z) = f_n(z)), the package's series and closed forms."""
    x = np.asarray(x, dtype=np.float64)
    return c_table(np.ones_like(x), x, order=2)


def clothoid_gravity_force_jacobian_full(clothoid: cl.SuperClothoid, linear_density: float, gravity,
                                          chunk: int = 1024):
    """The complex step with every element recomputed per column (reference for the tests)."""
    S, N = clothoid.lengths.shape
    n = 3 * (N + 1)
    out = np.zeros((S, n, n))
    sid_all, col_all = np.nonzero(np.arange(n)[None, :] // 3 <= clothoid.n_elements[:, None])
    for start in range(0, len(sid_all), chunk):
        sid = sid_all[start:start + chunk]
        col = col_all[start:start + chunk]
        q = clothoid.curvatures[sid].astype(np.complex128).reshape(len(sid), n)
        q[np.arange(len(sid)), col] += 1j * cl.COMPLEX_STEP
        sub = cl.SuperClothoid(clothoid.root_positions[sid], clothoid.root_frames[sid], clothoid.lengths[sid],
                               q.reshape(len(sid), N + 1, 3), clothoid.n_elements[sid])
        F = cl.gravity_force(sub, linear_density, gravity)
        out[sid, :, col] = F.reshape(len(sid), n).imag / cl.COMPLEX_STEP
    return out


def clothoid_gravity_hessian_factors(clothoid: cl.SuperClothoid, kin: cl.Kinematics | None = None):
    """Per node (S, N + 1, 3, 3): A_i = int N_i R^T [Y]x ds and Theta_i = int N_i R ds.  Towards an analytic dF/dq:
    for j <= i - 2 (disjoint hat supports, psi_j constant = Theta_j over the support of N_i, and by the Jacobi
    identity d(R^T (Y x g)) = R^T [Y]x [g]x psi) the blocks are separable,

        dF_i/dq_j = rhoS A_i [g]x Theta_j      (and dF_j/dq_i its transpose);

    the blocks with |i - j| <= 1 need nested in-element integrals and are not derived yet (tests: the formula
    against the complex step). Work towards an analytic clothoid gravity Hessian (docs/clothoid.md, 'Not done'):
    only the tests use it so far."""
    kin = cl._with_moments(clothoid, kin)
    l = clothoid.lengths
    S, N = l.shape
    A0, A1 = cl._gravity_element_moments(kin)
    inv = np.where(l > 0, 1.0 / np.where(l > 0, l, 1.0), 0.0)[..., None, None]
    RkT = np.swapaxes(kin.R[:, :-1], -1, -2)
    A = np.zeros((S, N + 1, 3, 3), dtype=A0.dtype)
    A[:, :-1] -= np.swapaxes(A0 - A1 * inv, -1, -2) @ RkT
    A[:, 1:] -= np.swapaxes(A1 * inv, -1, -2) @ RkT
    Ts, Te, _, _ = cl.node_jacobian_terms(kin)
    Theta = np.zeros_like(A)
    Theta[:, :-1] += Ts
    Theta[:, 1:] += Te
    return A, Theta


def transport(v: np.ndarray, t_old: np.ndarray, t_new: np.ndarray) -> np.ndarray:
    """Parallel transport of vectors v (N, 3) from unit tangents t_old to t_new (the minimal rotation):
    P v = c v + b x v + b (b . v) / (1 + c), b = t_old x t_new, c = t_old . t_new."""
    b = dr.cross(t_old, t_new)
    c = dr.dot(t_old, t_new)
    return c[:, None] * v + dr.cross(b, v) + b * (dr.dot(b, v) / (1.0 + c))[:, None]


def rotate_about(v: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate v (N, 3), normal to the unit ``axis`` (N, 3), by ``angle`` (N,): v cos + (axis x v) sin."""
    return np.cos(angle)[:, None] * v + np.sin(angle)[:, None] * dr.cross(axis, v)


# ------------------------------------------------------- Super-Helix: vectorised numpy twins
def psi_form_hessian(beta, dbeta, ddbeta, gamma, dgamma, ddgamma, omega, z, u, v):
    """Hessian in omega of h = u . (alpha I + beta(z) W + gamma(z) W^2) v; (..., 3, 3).

    h = alpha c0 + beta (w . c1) + gamma (P - z c0), c0 = u.v, c1 = v x u, P = (u.w)(v.w).
    """
    c0 = np.einsum("...i,...i->...", u, v)
    c1 = np.cross(v, u)
    uw = np.einsum("...i,...i->...", u, omega)
    vw = np.einsum("...i,...i->...", v, omega)
    wc1 = np.einsum("...i,...i->...", omega, c1)
    P = uw * vw
    grad_p = u * vw[..., None] + v * uw[..., None]
    g = grad_p - 2.0 * c0[..., None] * omega
    eye = np.eye(3)
    ww = omega[..., :, None] * omega[..., None, :]

    def s(a):
        return a[..., None, None]

    hess = s(4.0 * ddbeta * wc1) * ww
    hess += s(2.0 * dbeta) * (omega[..., :, None] * c1[..., None, :] + c1[..., :, None] * omega[..., None, :])
    hess += s(2.0 * dbeta * wc1) * eye
    hess += s(4.0 * ddgamma * (P - z * c0)) * ww
    hess += s(2.0 * dgamma) * (omega[..., :, None] * g[..., None, :] + g[..., :, None] * omega[..., None, :])
    hess += s(2.0 * dgamma * (P - z * c0)) * eye
    hess += s(gamma) * (u[..., :, None] * v[..., None, :] + v[..., :, None] * u[..., None, :] - 2.0 * s(c0) * eye)
    return hess


def kinematics_reference(helix: sh.SuperHelix) -> sh.Kinematics:
    """The quantities of :func:`groomtool.rods.superhelix.kinematics` with vectorised numpy."""
    l = helix.lengths
    w = helix.curvatures
    S, N = l.shape
    z = np.einsum("snk,snk->sn", w, w)
    c, dc, _ = c_table(l, z, order=1)
    W = sh.skew(w)
    Q = np.eye(3) + c[1][..., None, None] * W + c[2][..., None, None] * (W @ W)
    psi1 = l[..., None, None] * np.eye(3) + c[2][..., None, None] * W + c[3][..., None, None] * (W @ W)
    e0 = np.broadcast_to(sh.E0, w.shape)
    p = psi1[..., :, 0]
    P = sh._psi_apply(0.5 * l * l, c[3], c[4], w, z, e0)
    D = sh._psi_apply_jacobian(c[2], dc[2], c[3], dc[3], w, z, e0)
    DP = sh._psi_apply_jacobian(c[3], dc[3], c[4], dc[4], w, z, e0)

    C = np.empty((S, N + 1, 3))
    R = np.empty((S, N + 1, 3, 3))
    sh._chain(np.ascontiguousarray(helix.root_positions), np.ascontiguousarray(helix.root_frames),
              np.ascontiguousarray(Q), np.ascontiguousarray(p), C, R, np.ascontiguousarray(helix.lengths, dtype=np.float64))
    Theta = R[:, :-1] @ psi1
    return sh.Kinematics(helix, C, R, Q, p, P, D, DP, Theta, c, dc, z)


def integrated_jacobians(helix: sh.SuperHelix, kin: sh.Kinematics):
    """G_k = int_0^L dC/domega_k ds = R_k DP_k + m_{k+1} R_k D_k - [X_{k+1}]x Theta_k (S, N, 3, 3), plus m and X (batched
    numpy; superhelix.gravity_force's kernel computes rhoS G_k^T g without forming G)."""
    m, X, _ = sh._downstream_moments(helix, kin)
    Rk = kin.R[:, :-1]
    G = Rk @ kin.DP + m[..., None, None] * (Rk @ kin.D) - sh.skew(X) @ kin.Theta
    return G, m, X


def gravity_force_reference(helix: sh.SuperHelix, linear_density: float, gravity, kin: sh.Kinematics | None = None):
    """F = rhoS G^T g from the batched integrated Jacobians (the original ``superhelix.gravity_force``)."""
    kin = kin if kin is not None else sh.kinematics(helix)
    G, _, _ = integrated_jacobians(helix, kin)
    return linear_density * np.einsum("snab,a->snb", G, np.asarray(gravity, dtype=np.float64))


def gravity_force_jacobian_reference(helix: sh.SuperHelix, linear_density: float, gravity,
                                     kin: sh.Kinematics | None = None):
    """dF/dq assembled with dense batched matmuls (the original ``superhelix.gravity_force_jacobian``)."""
    kin = kin if kin is not None else sh.kinematics(helix)
    g = np.asarray(gravity, dtype=np.float64)
    S, N = helix.lengths.shape
    G, m, X = integrated_jacobians(helix, kin)
    gx = sh.skew(g)
    # off-diagonal blocks, j < k: -rhoS Theta_j^T [g]x G_k, all (j, k) at once as one batched matmul
    left = np.einsum("sjba,bc->sjac", kin.Theta, gx).reshape(S, 3 * N, 3)  # rows (j, a): Theta_j^T [g]x
    right = G.transpose(0, 2, 1, 3).reshape(S, 3, 3 * N)  # columns (k, d): G_k
    block_row = np.repeat(np.arange(N), 3)
    upper = block_row[:, None] < block_row[None, :]
    full = (-linear_density * (left @ right)) * upper
    full += np.swapaxes(full, 1, 2)  # the lower blocks by symmetry
    # diagonal blocks
    w = helix.curvatures
    z = kin.z
    c, dc, ddc = c_table(helix.lengths, z, order=2)
    u = np.einsum("snba,b->sna", kin.R[:, :-1], g)  # R_j^T g
    Y = np.einsum("snba,snb->sna", kin.R[:, 1:], X)  # R_{j+1}^T X_{j+1}
    e0 = np.broadcast_to(sh.E0, w.shape)
    diag = psi_form_hessian(c[3], dc[3], ddc[3], c[4], dc[4], ddc[4], w, z, u, e0)
    diag += m[..., None, None] * psi_form_hessian(c[2], dc[2], ddc[2], c[3], dc[3], ddc[3], w, z, u, e0)
    diag += psi_form_hessian(c[1], dc[1], ddc[1], c[2], dc[2], ddc[2], w, z, u, Y)
    view = full.reshape(S, N, 3, N, 3)
    idx = np.arange(N)
    view[:, idx, :, idx, :] = linear_density * diag.transpose(1, 0, 2, 3)
    return full
