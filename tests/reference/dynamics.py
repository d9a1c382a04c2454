"""The Super-Helix inertia as first written, vectorised numpy over every Gauss point: the reference
for the compiled kernel of groomtool.rods.dynamics (mass_matrix, velocity_terms), and the per-point
motion the tests check against finite differences.  Only tests use it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from groomtool.rods.dynamics import Inertia
from groomtool.rods.series import c_table
from groomtool.rods.superhelix import E0, Kinematics, SuperHelix, _psi_apply_jacobian, kinematics, skew

@dataclass
class ElementPoints:
    """Gauss points of every element: weights w (S, N, Q) (including l_j), positions x relative to the
    root (S, N, Q, 3), frames R (S, N, Q, 3, 3), own-element Jacobians J_own = R_j D(t) and
    Jw_own = R_j Psi_1(t) (S, N, Q, 3, 3), local p(t), D(t), Psi_1(t), and the c_n tables."""

    t: np.ndarray
    w: np.ndarray
    x: np.ndarray
    R: np.ndarray
    J_own: np.ndarray
    Jw_own: np.ndarray
    p: np.ndarray
    D: np.ndarray
    psi1: np.ndarray
    c: np.ndarray
    dc: np.ndarray
    ddc: np.ndarray


def element_points(helix: SuperHelix, kin: Kinematics, order: int = 4) -> ElementPoints:
    """Gauss-Legendre points of ``order`` per element with every per-point quantity the inertia needs."""
    xg, wg = np.polynomial.legendre.leggauss(order)
    l = helix.lengths[..., None]
    t = 0.5 * (xg + 1.0) * l
    w = 0.5 * wg * l
    omega = np.broadcast_to(helix.curvatures[:, :, None, :], t.shape + (3,))
    z = np.broadcast_to(kin.z[..., None], t.shape)
    c, dc, ddc = c_table(t, z)
    W = skew(omega)
    W2 = W @ W
    eye = np.eye(3)
    psi0 = eye + c[1][..., None, None] * W + c[2][..., None, None] * W2
    psi1 = t[..., None, None] * eye + c[2][..., None, None] * W + c[3][..., None, None] * W2
    p = psi1[..., :, 0]
    D = _psi_apply_jacobian(c[2], dc[2], c[3], dc[3], omega, z, np.broadcast_to(E0, omega.shape))
    Rj = kin.R[:, :-1, None]
    x = (kin.C[:, :-1, None] - kin.C[:, :1, None]) + np.einsum("snqab,snqb->snqa", Rj, p)
    return ElementPoints(t=t, w=w, x=x, R=Rj @ psi0, J_own=Rj @ D, Jw_own=Rj @ psi1, p=p, D=D, psi1=psi1,
                         c=c, dc=dc, ddc=ddc)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (broadcasting), without np.cross's per-call overhead."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


@dataclass
class NodeMotion:
    """World velocity V, angular velocity Omega (S, N+1, 3) at the nodes, and their accelerations at
    qddot = 0: a, alpha (S, N+1, 3)."""

    V: np.ndarray
    Omega: np.ndarray
    a: np.ndarray
    alpha: np.ndarray


def _second_directional(c, dc, ddc, omega, z, u):
    """p''[u, u] for p = t e0 + c2 omega x e0 + c3 (omega (omega.e0) - z e0), and dPsi_1[u] u.

    For a coefficient c(z) times a vector u_(eps), (c u_)'' = (c'' z'^2 + c' z'') u_ + 2 c' z' u_' + c u_'',
    with z' = 2 omega.u, z'' = 2 u.u.
    """
    e0 = np.broadcast_to(E0, omega.shape)
    dz = 2.0 * np.einsum("...i,...i->...", omega, u)
    ddz = 2.0 * np.einsum("...i,...i->...", u, u)
    we = omega[..., 0]
    ue = u[..., 0]
    v1 = cross(omega, e0)
    v1p = cross(u, e0)
    v2 = omega * we[..., None] - z[..., None] * e0
    v2p = u * we[..., None] + omega * ue[..., None] - dz[..., None] * e0
    v2pp = 2.0 * u * ue[..., None] - ddz[..., None] * e0

    def s(a):
        return a[..., None]

    p2 = (s(ddc[2] * dz * dz + dc[2] * ddz) * v1 + s(2.0 * dc[2] * dz) * v1p
          + s(ddc[3] * dz * dz + dc[3] * ddz) * v2 + s(2.0 * dc[3] * dz) * v2p + s(c[3]) * v2pp)
    wu = cross(omega, u)
    dpsi = s(dz) * (s(dc[2]) * wu + s(dc[3]) * cross(omega, wu)) + s(c[3]) * cross(u, wu)
    return p2, dpsi


def node_motion(helix: SuperHelix, rates: np.ndarray, kin: Kinematics | None = None,
                root_velocity=None, root_angular_velocity=None,
                root_acceleration=None, root_angular_acceleration=None) -> NodeMotion:
    """Node velocities and accelerations at qddot = 0 by the forward recursion (module docstring).

    ``rates`` (S, N, 3) = qdot; the root's rigid motion (S, 3) or (3,) each, default at rest.
    """
    kin = kin if kin is not None else kinematics(helix)
    S, N = helix.lengths.shape
    u = np.asarray(rates, dtype=np.float64).reshape(S, N, 3)
    omega = helix.curvatures
    c, dc, ddc = c_table(helix.lengths, kin.z)
    p2, dpsi = _second_directional(c, dc, ddc, omega, kin.z, u)
    Rj = kin.R[:, :-1]
    y = np.einsum("snab,snb->sna", Rj, kin.p)
    lin = np.einsum("snab,snb->sna", Rj @ kin.D, u)
    ang = np.einsum("snab,snb->sna", kin.Theta, u)
    p2w = np.einsum("snab,snb->sna", Rj, p2)
    dpsiw = np.einsum("snab,snb->sna", Rj, dpsi)

    def init(value):
        return np.broadcast_to(np.zeros(3) if value is None else np.asarray(value, dtype=np.float64), (S, 3))

    V = np.empty((S, N + 1, 3))
    Om = np.empty((S, N + 1, 3))
    a = np.empty((S, N + 1, 3))
    al = np.empty((S, N + 1, 3))
    V[:, 0], Om[:, 0] = init(root_velocity), init(root_angular_velocity)
    a[:, 0], al[:, 0] = init(root_acceleration), init(root_angular_acceleration)
    for j in range(N):
        o = Om[:, j]
        V[:, j + 1] = V[:, j] + cross(o, y[:, j]) + lin[:, j]
        Om[:, j + 1] = o + ang[:, j]
        a[:, j + 1] = (a[:, j] + cross(al[:, j], y[:, j]) + cross(o, cross(o, y[:, j]))
                       + 2.0 * cross(o, lin[:, j]) + p2w[:, j])
        al[:, j + 1] = al[:, j] + cross(o, ang[:, j]) + dpsiw[:, j]
    return NodeMotion(V=V, Omega=Om, a=a, alpha=al)



def _suffix_beyond(per_element: np.ndarray) -> np.ndarray:
    """Sum over elements k > j for each j along axis 1 (elements beyond node j+1)."""
    total = np.cumsum(per_element[:, ::-1], axis=1)[:, ::-1]
    return np.concatenate([total[:, 1:], np.zeros_like(total[:, :1])], axis=1)


def _upstream_blocks(helix: SuperHelix, kin: Kinematics) -> tuple[np.ndarray, np.ndarray]:
    """B_k = R_k D_k(l_k) + [C_{k+1} - C_0]x Theta_k and Theta_k, (S, N, 3, 3) each."""
    rel = kin.C[:, 1:] - kin.C[:, :1]
    B = kin.R[:, :-1] @ kin.D + skew(rel) @ kin.Theta
    return B, kin.Theta


def world_inertia(points: ElementPoints, inertia: Inertia) -> np.ndarray:
    """II(s) = R diag(rho J, rho I1, rho I2) R^T at every point, (S, N, Q, 3, 3)."""
    rot = np.asarray(inertia.rotational)
    return np.einsum("...ak,k,...bk->...ab", points.R, rot, points.R)




def mass_matrix_numpy(helix: SuperHelix, inertia: Inertia, kin: Kinematics | None = None, order: int = 4,
                points: ElementPoints | None = None) -> np.ndarray:
    """M = int rhoS J^T J + Jw^T II Jw ds per strand, (S, 3N, 3N); rows and columns of padding are 0.

    Blocks j < k: M_jk = [B_j^T | Theta_j^T] right_k with
        right_k = [ rhoS (m0 B_k - [m1]x Theta_k + E_k) ;
                    rhoS ([m1]x B_k + (tr(m2) I - m2) Theta_k + G_k) + IId Theta_k + Gr_k ]
    (m0, m1, m2, IId: mass, first/second moment and rotational inertia beyond node k+1; E_k, G_k,
    Gr_k: int over element k of J_own, [x]x J_own, II Jw_own); M_kk adds element k's own
    int rhoS J_own^T J_own + Jw_own^T II Jw_own.
    """
    kin = kin if kin is not None else kinematics(helix)
    pts = points if points is not None else element_points(helix, kin, order)
    S, N = helix.lengths.shape
    rhoS = inertia.linear
    II = world_inertia(pts, inertia)
    w = pts.w[..., None, None]
    B, Theta = _upstream_blocks(helix, kin)

    m0 = _suffix_beyond(helix.lengths)[..., None, None]
    m1 = _suffix_beyond(np.einsum("snq,snqa->sna", pts.w, pts.x))
    m2 = _suffix_beyond(np.einsum("snq,snqa,snqb->snab", pts.w, pts.x, pts.x))
    IId = _suffix_beyond(np.sum(w * II, axis=2))
    E = np.sum(w * pts.J_own, axis=2)
    G = np.sum(w * (skew(pts.x) @ pts.J_own), axis=2)
    Gr = np.sum(w * (II @ pts.Jw_own), axis=2)
    own = rhoS * np.sum(w * (np.swapaxes(pts.J_own, -1, -2) @ pts.J_own), axis=2)
    own += np.sum(w * (np.swapaxes(pts.Jw_own, -1, -2) @ II @ pts.Jw_own), axis=2)

    m1x = skew(m1)
    tr = np.trace(m2, axis1=-2, axis2=-1)[..., None, None]
    down_top = rhoS * (m0 * B - m1x @ Theta)
    down_bottom = rhoS * (m1x @ B + (tr * np.eye(3) - m2) @ Theta) + IId @ Theta
    left = np.concatenate([np.swapaxes(B, -1, -2), np.swapaxes(Theta, -1, -2)], axis=-1)  # (S, N, 3, 6)
    right = np.concatenate([down_top + rhoS * E, down_bottom + rhoS * G + Gr], axis=-2)  # (S, N, 6, 3)
    right_down = np.concatenate([down_top, down_bottom], axis=-2)

    M = np.zeros((S, 3 * N, 3 * N))
    _assemble_blocks(np.ascontiguousarray(left), np.ascontiguousarray(right), np.ascontiguousarray(right_down),
                     np.ascontiguousarray(own), np.asarray(helix.n_elements, dtype=np.int64), M)
    return M


def _assemble_blocks(left, right, right_down, own, n_elements, M):
    """M_jk = left_j right_k (j < k), M_kj = M_jk^T, M_kk = left_k right_down_k + own_k, over each
    strand's real elements only (padding stays 0)."""
    for s in range(left.shape[0]):
        n = n_elements[s]
        for j in range(n):
            for k in range(j, n):
                for a in range(3):
                    for b in range(3):
                        acc = 0.0
                        if k == j:
                            for c in range(6):
                                acc += left[s, j, a, c] * right_down[s, k, c, b]
                            acc += own[s, k, a, b]
                            M[s, 3 * j + a, 3 * k + b] = acc
                        else:
                            for c in range(6):
                                acc += left[s, j, a, c] * right[s, k, c, b]
                            M[s, 3 * j + a, 3 * k + b] = acc
                            M[s, 3 * k + b, 3 * j + a] = acc




@dataclass
class PointMotion:
    """Velocity, angular velocity and their accelerations at qddot = 0 at every Gauss point, (S, N, Q, 3)."""

    V: np.ndarray
    Omega: np.ndarray
    a: np.ndarray
    alpha: np.ndarray


def point_motion(helix: SuperHelix, rates: np.ndarray, kin: Kinematics, pts: ElementPoints,
                 nodes: NodeMotion) -> PointMotion:
    """The node recursion carried from each element's start node to its Gauss points (t instead of l_j)."""
    u = np.broadcast_to(np.asarray(rates, dtype=np.float64)[:, :, None, :], pts.t.shape + (3,))
    omega = np.broadcast_to(helix.curvatures[:, :, None, :], pts.t.shape + (3,))
    z = np.einsum("...i,...i->...", omega, omega)
    p2, dpsi = _second_directional(pts.c, pts.dc, pts.ddc, omega, z, u)
    Rj = kin.R[:, :-1, None]
    y = pts.x - (kin.C[:, :-1, None] - kin.C[:, :1, None])
    lin = np.einsum("snqab,snqb->snqa", pts.J_own, u)
    ang = np.einsum("snqab,snqb->snqa", pts.Jw_own, u)
    o = np.broadcast_to(nodes.Omega[:, :-1, None], y.shape)
    al = nodes.alpha[:, :-1, None]
    V = nodes.V[:, :-1, None] + cross(o, y) + lin
    Om = o + ang
    acc = (nodes.a[:, :-1, None] + cross(al, y) + cross(o, cross(o, y)) + 2.0 * cross(o, lin)
           + np.einsum("snqab,snqb->snqa", Rj, p2))
    alpha = al + cross(o, ang) + np.einsum("snqab,snqb->snqa", Rj, dpsi)
    return PointMotion(V=V, Omega=Om, a=acc, alpha=alpha)


def velocity_terms_numpy(helix: SuperHelix, rates: np.ndarray, inertia: Inertia, kin: Kinematics | None = None,
                   order: int = 4, points: ElementPoints | None = None, root_motion: dict | None = None
                   ) -> np.ndarray:
    """A(q, qdot) = int rhoS J^T a + Jw^T (II alpha + w x II w) ds, (S, N, 3).

    Exact for a static root (Coriolis and centrifugal terms); with ``root_motion`` (keys of
    :func:`node_motion`: root_velocity, root_angular_velocity, root_acceleration,
    root_angular_acceleration) it also holds the inertial forces of the moving root frame.
    By structure A_k = B_k^T F_k + Theta_k^T (X_k + T_k) + own_k with F, X, T the sums beyond node k+1
    of w f, w x x f and w tau (f = rhoS a, tau = II alpha + w x II w).
    """
    kin = kin if kin is not None else kinematics(helix)
    pts = points if points is not None else element_points(helix, kin, order)
    nodes = node_motion(helix, rates, kin, **(root_motion or {}))
    mo = point_motion(helix, rates, kin, pts, nodes)
    II = world_inertia(pts, inertia)
    f = inertia.linear * mo.a
    tau = np.einsum("...ab,...b->...a", II, mo.alpha) + cross(mo.Omega, np.einsum("...ab,...b->...a", II, mo.Omega))
    w = pts.w[..., None]
    Fd = _suffix_beyond(np.sum(w * f, axis=2))
    Xd = _suffix_beyond(np.sum(w * cross(pts.x, f), axis=2))
    Td = _suffix_beyond(np.sum(w * tau, axis=2))
    own = np.sum(w * (np.einsum("...ba,...b->...a", pts.J_own, f) + np.einsum("...ba,...b->...a", pts.Jw_own, tau)),
                 axis=2)
    B, Theta = _upstream_blocks(helix, kin)
    A = np.einsum("snba,snb->sna", B, Fd) + np.einsum("snba,snb->sna", Theta, Xd + Td) + own
    return A * helix.element_mask[..., None]


