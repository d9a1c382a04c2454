"""Inertia of Super-Helices: the mass matrix with cross-section rotation, and the velocity terms A.

Kinetic energy of a strand (translation of the centreline plus rotation of the cross-sections):

    T = 1/2 int rhoS |C'|^2 ds + 1/2 int w(s)^T II(s) w(s) ds,   II(s) = R(s) diag(rho J, rho I1, rho I2) R(s)^T

(w the world angular velocity of the material frame, J = I1 + I2 the polar moment: the twist axis n0
comes first).  With C' = J(s) qdot and w = Jw(s) qdot,

    M = int rhoS J^T J + Jw^T II Jw ds,
    A = int rhoS J^T a(s) + Jw^T (II alpha(s) + w x II w) ds                (Lagrange / d'Alembert)

where a(s) = Jdot qdot and alpha(s) = Jwdot qdot are the accelerations at qddot = 0 (velocity-quadratic,
plus the prescribed acceleration of a moving root).  The equations of motion are M qddot + A = forces.

Structure used (docs/maths.md section 2, superhelix.py): for a point x in element e,
    J_k(x)  = B_k - [x]x Theta_k,   Jw_k = Theta_k            (k < e)
    J_e(x)  = R_e D_e(t),           Jw_e = R_e Psi_1(t)        (own element)
so every block M_jk (j < k) is left_j @ right_k with left_j = [B_j^T | Theta_j^T] (3 x 6) and right_k
built from the moments (mass, first and second moment, rotational inertia) of everything beyond
node k+1 plus element k's own integrals.  The whole matrix costs O(N^2) 3x3 products per strand, no
quadrature point loops over the upstream elements.  Positions are taken relative to the root (J is
translation invariant) to keep the [x]x products well conditioned.

Node motion (angular velocity Omega_j, velocity V_j, and their accelerations at qddot = 0), with
y_j = R_j p_j the chord of element j and u_j its rate vector:
    Omega_{j+1} = Omega_j + R_j Psi_1 u_j
    V_{j+1}     = V_j + Omega_j x y_j + R_j D_j u_j
    alpha_{j+1} = alpha_j + Omega_j x (R_j Psi_1 u_j) + R_j (dPsi_1[u_j] u_j)
    a_{j+1}     = a_j + alpha_j x y_j + Omega_j x (Omega_j x y_j) + 2 Omega_j x (R_j D_j u_j) + R_j p''[u_j, u_j]
(the same formulas with t instead of l_j give every point inside an element).

M and A are computed together in one compiled pass per strand (:func:`inertia_terms`); the vectorised
numpy version over every Gauss point is the tests' reference (tests/reference/dynamics.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from . import clothoid as cl
from .series import _f_point
from .superhelix import Kinematics, SuperHelix, _e0_jacobian, kinematics


@dataclass(frozen=True)
class Inertia:
    """Inertia per unit length: ``linear`` = rho S (kg/m) and ``rotational`` = rho (J, I1, I2) (kg m)
    about the material axes (n0 twist, n1, n2)."""

    linear: float
    rotational: tuple

    @classmethod
    def from_material(cls, material, rotational_scale: float = 1.0) -> "Inertia":
        """rhoS and rho (2I, I, I) of a circular fibre, the rotational part times ``rotational_scale``
        (1 = physical; larger values slow down the twist and bending-rate modes, see docs/simulation.md)."""
        rot = material.density * material.second_moment * np.array([2.0, 1.0, 1.0]) * rotational_scale
        return cls(float(material.linear_density), tuple(float(x) for x in rot))


# --------------------------------------------------------------------------- node speeds
def strand_node_speeds(helix: SuperHelix, rates: np.ndarray, kin: Kinematics | None = None) -> np.ndarray:
    """(S,) per strand the max over its nodes of |V_j| (root at rest), by the recursion
    V_{j+1} = V_j + Omega_j x y_j + R_j D_j u_j, Omega_{j+1} = Omega_j + Theta_j u_j (module docstring)."""
    kin = kin if kin is not None else kinematics(helix)
    S, N = helix.lengths.shape
    u = np.ascontiguousarray(np.asarray(rates, dtype=np.float64).reshape(S, N, 3))
    return _node_speeds_kernel(kin.R, kin.p, kin.D, kin.Theta, u, np.asarray(helix.n_elements, dtype=np.int64))


@njit(cache=True)
def _node_speeds_kernel(R, p, D, Theta, u, n_elements):
    out = np.zeros(R.shape[0])
    V = np.empty(3)
    om = np.empty(3)
    y = np.empty(3)
    lin = np.empty(3)
    for s in range(R.shape[0]):
        V[:] = 0.0
        om[:] = 0.0
        best = 0.0
        for j in range(n_elements[s]):
            Rj = R[s, j]
            for a in range(3):
                y[a] = Rj[a, 0] * p[s, j, 0] + Rj[a, 1] * p[s, j, 1] + Rj[a, 2] * p[s, j, 2]
            lin[:] = 0.0
            for a in range(3):
                for b in range(3):
                    acc = 0.0
                    for c in range(3):
                        acc += Rj[a, c] * D[s, j, c, b]
                    lin[a] += acc * u[s, j, b]
            V[0] += om[1] * y[2] - om[2] * y[1] + lin[0]
            V[1] += om[2] * y[0] - om[0] * y[2] + lin[1]
            V[2] += om[0] * y[1] - om[1] * y[0] + lin[2]
            for a in range(3):
                om[a] += (Theta[s, j, a, 0] * u[s, j, 0] + Theta[s, j, a, 1] * u[s, j, 1]
                          + Theta[s, j, a, 2] * u[s, j, 2])
            speed = np.sqrt(V[0] * V[0] + V[1] * V[1] + V[2] * V[2])
            if speed > best:
                best = speed
        out[s] = best
    return out


def _root_motion_arrays(S: int, root_motion: dict | None, a: int, b: int):
    """The root's angular velocity, acceleration and angular acceleration of strands a..b-1, (b - a, 3) each
    (zero without ``root_motion``; its values (S, 3) or (3,))."""
    def init(key):
        value = None if root_motion is None else root_motion.get(key)
        vector = np.zeros(3) if value is None else np.asarray(value, dtype=np.float64)
        return np.ascontiguousarray(np.broadcast_to(vector, (S, 3))[a:b])

    return init("root_angular_velocity"), init("root_acceleration"), init("root_angular_acceleration")


@dataclass(frozen=True)
class MassGenerators:
    """The mass matrix of each strand as 3 x 3 blocks of a symmetric block-semiseparable matrix (groomtool.semiseparable):

        M_jj = diag_j,   M_kj = later_k^T earlier_j  (k > j),   M_jk = M_kj^T,

    earlier_j = [B_j ; Theta_j] (6 x 3: the rigid velocity of everything beyond element j, cf. :func:`mass_matrix`)
    and later_k = right_k (6 x 3).  diag (S, N, 3, 3), later and earlier (S, N, 6, 3); zero on padding elements."""

    diag: np.ndarray
    later: np.ndarray
    earlier: np.ndarray

    def dense(self, n_elements) -> np.ndarray:
        """The dense M (S, 3N, 3N), zero rows and columns of padding."""
        S, N = self.diag.shape[:2]
        M = np.zeros((S, 3 * N, 3 * N))
        _dense_from_generators(self.diag, self.later, self.earlier, np.asarray(n_elements, dtype=np.int64), M)
        return M


def inertia_generators(helix: SuperHelix, inertia: Inertia, kin: Kinematics | None = None, rates=None,
                       order: int = 4, root_motion: dict | None = None, mass: bool = True,
                       strands: tuple[int, int] | None = None):
    """(MassGenerators or None, A or None): the mass matrix's generators (O(N) per strand; None unless ``mass``) and
    the velocity terms (S, N, 3; None without ``rates``) of one configuration, in one compiled pass over
    Gauss-Legendre points of ``order`` per element (:func:`mass_matrix`, :func:`velocity_terms` for the formulas).

    ``strands`` = (first, stop): only those strands, N then their largest element count (the simulator walks a
    large groom in chunks)."""
    kin = kin if kin is not None else kinematics(helix)
    a, b = (0, helix.n_strands) if strands is None else (int(strands[0]), int(strands[1]))
    n_el = np.asarray(helix.n_elements[a:b], dtype=np.int64)
    S = b - a
    N = helix.max_elements if strands is None else max(int(n_el.max(initial=1)), 1)

    def part(x, nodes=0):
        return np.ascontiguousarray(x[a:b, :N + nodes], dtype=np.float64)

    xg, wg = np.polynomial.legendre.leggauss(order)
    want_A = rates is not None
    u = (part(np.asarray(rates, dtype=np.float64).reshape(helix.curvatures.shape)) if want_A
         else np.zeros((S, N, 3)))
    om0, acc0, al0 = _root_motion_arrays(helix.n_strands, root_motion, a, b)
    shape = (S, N) if mass else (1, 1)
    gens = MassGenerators(np.zeros(shape + (3, 3)), np.zeros(shape + (6, 3)), np.zeros(shape + (6, 3)))
    A = np.zeros((S, N, 3))
    _inertia_kernel(part(helix.lengths), part(helix.curvatures), part(kin.z), part(kin.C, 1), part(kin.R, 1),
                    part(kin.D), part(kin.Theta), n_el, xg, wg, float(inertia.linear),
                    np.asarray(inertia.rotational, dtype=np.float64), u, om0, acc0, al0, mass, want_A,
                    gens.diag, gens.later, gens.earlier, A)
    return (gens if mass else None), (A if want_A else None)


def inertia_terms(helix: SuperHelix, inertia: Inertia, kin: Kinematics | None = None, rates=None, order: int = 4,
                  root_motion: dict | None = None, mass: bool = True, strands: tuple[int, int] | None = None):
    """(M, A): :func:`inertia_generators` with the mass matrix dense (S, 3N, 3N; None unless ``mass``): O(N^2) per
    strand from the O(N) generators."""
    gens, A = inertia_generators(helix, inertia, kin, rates, order, root_motion, mass, strands)
    n_el = helix.n_elements if strands is None else helix.n_elements[int(strands[0]):int(strands[1])]
    return (gens.dense(n_el) if mass else None), A


def mass_matrix(helix: SuperHelix, inertia: Inertia, kin: Kinematics | None = None, order: int = 4) -> np.ndarray:
    """M = int rhoS J^T J + Jw^T II Jw ds per strand, (S, 3N, 3N); rows and columns of padding are 0.

    Blocks j < k: M_jk = [B_j^T | Theta_j^T] right_k with
        right_k = [ rhoS (m0 B_k - [m1]x Theta_k + E_k) ;
                    rhoS ([m1]x B_k + (tr(m2) I - m2) Theta_k + G_k) + IId Theta_k + Gr_k ]
    (B_k = R_k D_k(l_k) + [C_{k+1} - C_0]x Theta_k; m0, m1, m2, IId: mass, first/second moment and
    rotational inertia beyond node k+1; E_k, G_k, Gr_k: int over element k of J_own, [x]x J_own,
    II Jw_own); M_kk = [B_k^T | Theta_k^T] right'_k (right_k without element k's own E_k, G_k, Gr_k) plus
    element k's own int rhoS J_own^T J_own + Jw_own^T II Jw_own.  The generators (:class:`MassGenerators`:
    earlier_j = [B_j; Theta_j], later_k = right_k, O(N) per strand) come from one compiled pass
    (:func:`_inertia_kernel`), the dense blocks from them (O(N^2)).
    """
    return inertia_terms(helix, inertia, kin, order=order)[0]


def velocity_terms(helix: SuperHelix, rates: np.ndarray, inertia: Inertia, kin: Kinematics | None = None,
                   order: int = 4, root_motion: dict | None = None) -> np.ndarray:
    """A(q, qdot) = int rhoS J^T a + Jw^T (II alpha + w x II w) ds, (S, N, 3).

    Exact for a static root (Coriolis and centrifugal terms); with ``root_motion`` (keys of
    the root motion of a moving head: root_velocity, root_angular_velocity, root_acceleration,
    root_angular_acceleration) it also holds the inertial forces of the moving root frame.
    By structure A_k = B_k^T F_k + Theta_k^T (X_k + T_k) + own_k with F, X, T the sums beyond node k+1
    of w f, w x x f and w tau (f = rhoS a, tau = II alpha + w x II w), the point accelerations a, alpha
    carried from each element's start node by the node recursion (module docstring).  O(N) per strand.
    """
    return inertia_terms(helix, inertia, kin, rates=rates, order=order, root_motion=root_motion, mass=False)[1]


def kinetic_energy(mass: np.ndarray, rates: np.ndarray) -> np.ndarray:
    """T = 1/2 qdot^T M qdot per strand, (S,) (static root)."""
    v = np.asarray(rates).reshape(mass.shape[0], -1)
    return 0.5 * np.einsum("si,sij,sj->s", v, mass, v)


# --------------------------------------------------------------------------- compiled inertia (M and A in one pass)
@njit(cache=True)
def _mat3(A, B, out):
    """out = A B (3 x 3)."""
    for a in range(3):
        for b in range(3):
            out[a, b] = A[a, 0] * B[0, b] + A[a, 1] * B[1, b] + A[a, 2] * B[2, b]


@njit(cache=True)
def _cross_add(a, b, scale, out):
    """out += scale (a x b)."""
    out[0] += scale * (a[1] * b[2] - a[2] * b[1])
    out[1] += scale * (a[2] * b[0] - a[0] * b[2])
    out[2] += scale * (a[0] * b[1] - a[1] * b[0])


@njit(cache=True)
def _local_frame(t, w, z, buf, psi0, psi1, Dt, p2, dpsi, u, want_motion):
    """At t along an element of curvature w (z = |w|^2): Psi_0(t), Psi_1(t), D(t) = dp/dw and, with
    ``want_motion``, p''[u, u] and dPsi_1[u] u (the formulas of _second_directional in
    tests/reference/dynamics.py)."""
    t2 = t * t
    _f_point(z * t2, 2, buf)
    c1 = t * buf[0, 1]
    c2 = t2 * buf[0, 2]
    c3 = t2 * t * buf[0, 3]
    dc2 = t2 * t2 * buf[1, 2]
    dc3 = t2 * t2 * t * buf[1, 3]
    w0, w1, w2 = w[0], w[1], w[2]
    # W = [w]x, W^2 = w w^T - z I
    W = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    for a in range(3):
        for b in range(3):
            eye = 1.0 if a == b else 0.0
            w2ab = w[a] * w[b] - z * eye
            psi0[a, b] = eye + c1 * W[a][b] + c2 * w2ab
            psi1[a, b] = t * eye + c2 * W[a][b] + c3 * w2ab
    _e0_jacobian(c2, dc2, c3, dc3, w0, w1, w2, z, Dt)
    if not want_motion:
        return
    ddc2 = t2 * t2 * t2 * buf[2, 2]
    ddc3 = t2 * t2 * t2 * t * buf[2, 3]
    u0, u1, u2 = u[0], u[1], u[2]
    dz = 2.0 * (w0 * u0 + w1 * u1 + w2 * u2)
    ddz = 2.0 * (u0 * u0 + u1 * u1 + u2 * u2)
    v1 = (0.0, w2, -w1)  # w x e0
    v1p = (0.0, u2, -u1)  # u x e0
    v2 = (w0 * w0 - z, w1 * w0, w2 * w0)  # w w0 - z e0
    v2p = (u0 * w0 + w0 * u0 - dz, u1 * w0 + w1 * u0, u2 * w0 + w2 * u0)
    v2pp = (2.0 * u0 * u0 - ddz, 2.0 * u1 * u0, 2.0 * u2 * u0)
    k1 = ddc2 * dz * dz + dc2 * ddz
    k2 = 2.0 * dc2 * dz
    k3 = ddc3 * dz * dz + dc3 * ddz
    k4 = 2.0 * dc3 * dz
    for a in range(3):
        p2[a] = k1 * v1[a] + k2 * v1p[a] + k3 * v2[a] + k4 * v2p[a] + c3 * v2pp[a]
    wu = (w1 * u2 - w2 * u1, w2 * u0 - w0 * u2, w0 * u1 - w1 * u0)
    wwu = (w1 * wu[2] - w2 * wu[1], w2 * wu[0] - w0 * wu[2], w0 * wu[1] - w1 * wu[0])
    uwu = (u1 * wu[2] - u2 * wu[1], u2 * wu[0] - u0 * wu[2], u0 * wu[1] - u1 * wu[0])
    for a in range(3):
        dpsi[a] = dz * (dc2 * wu[a] + dc3 * wwu[a]) + c3 * uwu[a]


@njit(cache=True)
def _inertia_kernel(l, w, z, C, R, Dl, Theta, n_elements, xg, wg, rhoS, rot, u, root_om, root_acc, root_alpha,
                    want_mass, want_A, Md, Ml, Me, A):
    """The mass matrix's generators (MassGenerators: Md (S, N, 3, 3), Ml = right_k and Me = [B_j; Theta_j]
    (S, N, 6, 3), written only with ``want_mass``) and A (S, N, 3, with ``want_A``) of mass_matrix and velocity_terms
    in one pass per strand: per Gauss point the own-element Jacobians, world inertia and (for A) the point
    accelerations; per element the moments; suffix sums beyond each node (module docstring)."""
    S, N = l.shape
    Q = xg.shape[0]
    buf = np.empty((3, 5))
    psi0 = np.empty((3, 3))
    psi1 = np.empty((3, 3))
    Dt = np.empty((3, 3))
    Rp = np.empty((3, 3))
    Jo = np.empty((3, 3))
    Jw = np.empty((3, 3))
    II = np.empty((3, 3))
    T1 = np.empty((3, 3))
    p2 = np.empty(3)
    dpsi = np.empty(3)
    x = np.empty(3)
    y = np.empty(3)
    lin = np.empty(3)
    ang = np.empty(3)
    acc = np.empty(3)
    alq = np.empty(3)
    omq = np.empty(3)
    f = np.empty(3)
    tau = np.empty(3)
    IIo = np.empty(3)
    om = np.empty(3)
    a_n = np.empty(3)
    al_n = np.empty(3)
    # per element: m1, m2, IIsum, E, G, Gr, own (mass); F, X, T, ownA (velocity terms)
    m1e = np.empty((N, 3))
    m2e = np.empty((N, 3, 3))
    IIe = np.empty((N, 3, 3))
    Ee = np.empty((N, 3, 3))
    Ge = np.empty((N, 3, 3))
    Gre = np.empty((N, 3, 3))
    owne = np.empty((N, 3, 3))
    Fe = np.empty((N, 3))
    Xe = np.empty((N, 3))
    Te = np.empty((N, 3))
    ownA = np.empty((N, 3))
    B = np.empty((N, 3, 3))
    dtop = np.empty((N, 3, 3))
    dbottom = np.empty((N, 3, 3))
    for s in range(S):
        n = n_elements[s]
        for a in range(3):
            om[a] = root_om[s, a]
            a_n[a] = root_acc[s, a]
            al_n[a] = root_alpha[s, a]
        for j in range(n):
            lj = l[s, j]
            wj = w[s, j]
            zj = z[s, j]
            uj = u[s, j]
            Rj = R[s, j]
            m1e[j] = 0.0
            m2e[j] = 0.0
            IIe[j] = 0.0
            Ee[j] = 0.0
            Ge[j] = 0.0
            Gre[j] = 0.0
            owne[j] = 0.0
            Fe[j] = 0.0
            Xe[j] = 0.0
            Te[j] = 0.0
            ownA[j] = 0.0
            for q in range(Q + 1):
                last = q == Q  # the element's end: advances the node motion
                if last and not want_A:
                    break
                t = lj if last else 0.5 * (xg[q] + 1.0) * lj
                wq = 0.5 * wg[q] * lj if not last else 0.0
                _local_frame(t, wj, zj, buf, psi0, psi1, Dt, p2, dpsi, uj, want_A)
                for a in range(3):
                    y[a] = Rj[a, 0] * psi1[0, 0] + Rj[a, 1] * psi1[1, 0] + Rj[a, 2] * psi1[2, 0]
                    x[a] = C[s, j, a] - C[s, 0, a] + y[a]
                _mat3(Rj, Dt, Jo)
                _mat3(Rj, psi1, Jw)
                if want_A:
                    for a in range(3):
                        lin[a] = Jo[a, 0] * uj[0] + Jo[a, 1] * uj[1] + Jo[a, 2] * uj[2]
                        ang[a] = Jw[a, 0] * uj[0] + Jw[a, 1] * uj[1] + Jw[a, 2] * uj[2]
                        acc[a] = a_n[a] + Rj[a, 0] * p2[0] + Rj[a, 1] * p2[1] + Rj[a, 2] * p2[2]
                        alq[a] = al_n[a] + Rj[a, 0] * dpsi[0] + Rj[a, 1] * dpsi[1] + Rj[a, 2] * dpsi[2]
                        omq[a] = om[a] + ang[a]
                    # a = a_j + al_j x y + Om_j x (Om_j x y) + 2 Om_j x lin + R p''; al = al_j + Om_j x ang + R dPsi
                    oy = (om[1] * y[2] - om[2] * y[1], om[2] * y[0] - om[0] * y[2], om[0] * y[1] - om[1] * y[0])
                    _cross_add(al_n, y, 1.0, acc)
                    acc[0] += om[1] * oy[2] - om[2] * oy[1]
                    acc[1] += om[2] * oy[0] - om[0] * oy[2]
                    acc[2] += om[0] * oy[1] - om[1] * oy[0]
                    _cross_add(om, lin, 2.0, acc)
                    _cross_add(om, ang, 1.0, alq)
                    if last:
                        for a in range(3):
                            a_n[a] = acc[a]
                            al_n[a] = alq[a]
                            om[a] = omq[a]
                        break
                if wq == 0.0:
                    continue
                # world inertia II = (R Psi_0) diag(rot) (R Psi_0)^T
                _mat3(Rj, psi0, Rp)
                for a in range(3):
                    for b in range(a, 3):
                        v = rot[0] * Rp[a, 0] * Rp[b, 0] + rot[1] * Rp[a, 1] * Rp[b, 1] + rot[2] * Rp[a, 2] * Rp[b, 2]
                        II[a, b] = v
                        II[b, a] = v
                if want_mass:
                    for a in range(3):
                        m1e[j, a] += wq * x[a]
                        for b in range(3):
                            m2e[j, a, b] += wq * x[a] * x[b]
                            IIe[j, a, b] += wq * II[a, b]
                            Ee[j, a, b] += wq * Jo[a, b]
                    # G += w [x]x Jo ; Gr += w II Jw
                    for b in range(3):
                        Ge[j, 0, b] += wq * (x[1] * Jo[2, b] - x[2] * Jo[1, b])
                        Ge[j, 1, b] += wq * (x[2] * Jo[0, b] - x[0] * Jo[2, b])
                        Ge[j, 2, b] += wq * (x[0] * Jo[1, b] - x[1] * Jo[0, b])
                    _mat3(II, Jw, T1)
                    for a in range(3):
                        for b in range(3):
                            Gre[j, a, b] += wq * T1[a, b]
                    # own += w (rhoS Jo^T Jo + Jw^T II Jw)
                    for a in range(3):
                        for b in range(3):
                            jj = Jo[0, a] * Jo[0, b] + Jo[1, a] * Jo[1, b] + Jo[2, a] * Jo[2, b]
                            owne[j, a, b] += wq * (rhoS * jj + Jw[0, a] * T1[0, b] + Jw[1, a] * T1[1, b]
                                                   + Jw[2, a] * T1[2, b])
                if want_A:
                    for a in range(3):
                        f[a] = rhoS * acc[a]
                        IIo[a] = II[a, 0] * omq[0] + II[a, 1] * omq[1] + II[a, 2] * omq[2]
                        tau[a] = II[a, 0] * alq[0] + II[a, 1] * alq[1] + II[a, 2] * alq[2]
                    _cross_add(omq, IIo, 1.0, tau)
                    for a in range(3):
                        Fe[j, a] += wq * f[a]
                        Te[j, a] += wq * tau[a]
                        ownA[j, a] += wq * (Jo[0, a] * f[0] + Jo[1, a] * f[1] + Jo[2, a] * f[2]
                                            + Jw[0, a] * tau[0] + Jw[1, a] * tau[1] + Jw[2, a] * tau[2])
                    _cross_add(x, f, wq, Xe[j])
        # B_k = R_k D_k(l_k) + [C_{k+1} - C_0]x Theta_k
        for k in range(n):
            _mat3(R[s, k], Dl[s, k], T1)
            r0 = C[s, k + 1, 0] - C[s, 0, 0]
            r1 = C[s, k + 1, 1] - C[s, 0, 1]
            r2 = C[s, k + 1, 2] - C[s, 0, 2]
            Th = Theta[s, k]
            for b in range(3):
                B[k, 0, b] = T1[0, b] + r1 * Th[2, b] - r2 * Th[1, b]
                B[k, 1, b] = T1[1, b] + r2 * Th[0, b] - r0 * Th[2, b]
                B[k, 2, b] = T1[2, b] + r0 * Th[1, b] - r1 * Th[0, b]
        # suffix sums beyond node k+1, walking back from the tip
        m0 = 0.0
        m1 = np.zeros(3)
        m2 = np.zeros((3, 3))
        IId = np.zeros((3, 3))
        Fd = np.zeros(3)
        Xd = np.zeros(3)
        Td = np.zeros(3)
        for k in range(n - 1, -1, -1):
            Bk = B[k]
            Th = Theta[s, k]
            if want_A:
                for a in range(3):
                    A[s, k, a] = (Bk[0, a] * Fd[0] + Bk[1, a] * Fd[1] + Bk[2, a] * Fd[2]
                                  + Th[0, a] * (Xd[0] + Td[0]) + Th[1, a] * (Xd[1] + Td[1])
                                  + Th[2, a] * (Xd[2] + Td[2]) + ownA[k, a])
                for a in range(3):
                    Fd[a] += Fe[k, a]
                    Xd[a] += Xe[k, a]
                    Td[a] += Te[k, a]
            if want_mass:
                tr = m2[0, 0] + m2[1, 1] + m2[2, 2]
                for b in range(3):
                    # [m1]x B and [m1]x Theta, column b
                    mB0 = m1[1] * Bk[2, b] - m1[2] * Bk[1, b]
                    mB1 = m1[2] * Bk[0, b] - m1[0] * Bk[2, b]
                    mB2 = m1[0] * Bk[1, b] - m1[1] * Bk[0, b]
                    mT0 = m1[1] * Th[2, b] - m1[2] * Th[1, b]
                    mT1 = m1[2] * Th[0, b] - m1[0] * Th[2, b]
                    mT2 = m1[0] * Th[1, b] - m1[1] * Th[0, b]
                    mB = (mB0, mB1, mB2)
                    mT = (mT0, mT1, mT2)
                    for a in range(3):
                        dt_ = rhoS * (m0 * Bk[a, b] - mT[a])
                        db = rhoS * mB[a] + IId[a, 0] * Th[0, b] + IId[a, 1] * Th[1, b] + IId[a, 2] * Th[2, b]
                        db += rhoS * (tr * Th[a, b] - m2[a, 0] * Th[0, b] - m2[a, 1] * Th[1, b] - m2[a, 2] * Th[2, b])
                        dtop[k, a, b] = dt_
                        dbottom[k, a, b] = db
                        Ml[s, k, a, b] = dt_ + rhoS * Ee[k, a, b]
                        Ml[s, k, 3 + a, b] = db + rhoS * Ge[k, a, b] + Gre[k, a, b]
                m0 += l[s, k]
                for a in range(3):
                    m1[a] += m1e[k, a]
                    for b in range(3):
                        m2[a, b] += m2e[k, a, b]
                        IId[a, b] += IIe[k, a, b]
        if not want_mass:
            continue
        # earlier_k = [B_k; Theta_k]; M_kk = [B_k^T | Theta_k^T] right'_k + own_k
        for k in range(n):
            Bk = B[k]
            Tk = Theta[s, k]
            for a in range(3):
                for b in range(3):
                    Me[s, k, a, b] = Bk[a, b]
                    Me[s, k, 3 + a, b] = Tk[a, b]
                    Md[s, k, a, b] = (Bk[0, a] * dtop[k, 0, b] + Bk[1, a] * dtop[k, 1, b] + Bk[2, a] * dtop[k, 2, b]
                                      + Tk[0, a] * dbottom[k, 0, b] + Tk[1, a] * dbottom[k, 1, b]
                                      + Tk[2, a] * dbottom[k, 2, b]) + owne[k, a, b]


@njit(cache=True)
def _dense_from_generators(diag, later, earlier, n_elements, M):
    """M[s] (3N, 3N) with blocks M_jj = diag_j, M_jk = earlier_j^T later_k = M_kj^T (j < k) (MassGenerators)."""
    r = later.shape[2]
    for s in range(diag.shape[0]):
        n = n_elements[s]
        for j in range(n):
            for a in range(3):
                for b in range(3):
                    M[s, 3 * j + a, 3 * j + b] = diag[s, j, a, b]
            for k in range(j + 1, n):
                for a in range(3):
                    for b in range(3):
                        v = 0.0
                        for c in range(r):
                            v += earlier[s, j, c, a] * later[s, k, c, b]
                        M[s, 3 * j + a, 3 * k + b] = v
                        M[s, 3 * k + b, 3 * j + a] = v


# --------------------------------------------------------------------------- Super Space Clothoids (the simulator's)
def clothoid_mass_matrix(clothoid, inertia: Inertia, kin=None, order: int = 4) -> np.ndarray:
    """M = int rhoS J^T J + Jw^T II Jw ds of Super Space Clothoids (rods/clothoid.py), (S, 3(N + 1), 3(N + 1)) on
    the nodal dofs, with the cross-section rotation as for the helix (II = R diag(rho J, rho I, rho I) R^T; without it
    the twist of a straight piece would have no inertia).  Gauss-Legendre with ``order`` points per element (the
    integrand is smooth, not polynomial: a quadrature), J and Jw from
    :func:`groomtool.rods.clothoid.point_jacobians_rotation`, one batched product per quadrature node.  Rows and
    columns of padding nodes are 0.  O(N^2) per strand and point: dense, for the simulator's small strands."""
    kin = kin if kin is not None else cl.kinematics(clothoid)
    S, N = clothoid.lengths.shape
    n = 3 * (N + 1)
    xg, wg = np.polynomial.legendre.leggauss(order)
    xg = 0.5 * (xg + 1.0)
    wg = 0.5 * wg
    starts = clothoid.element_starts[:, :-1]
    strand = np.repeat(np.arange(S), N)
    rot = np.asarray(inertia.rotational, dtype=np.float64)
    M = np.zeros((S, n, n))
    for xq, wq in zip(xg, wg):
        s = (starts + xq * clothoid.lengths).ravel()
        J, Jw, R, _ = cl.point_jacobians_rotation(clothoid, strand, s, kin)
        w = (wq * clothoid.lengths).reshape(S * N, 1, 1)
        lin = (np.sqrt(inertia.linear * w) * J.transpose(0, 2, 1, 3).reshape(S * N, 3, n)).reshape(S, N * 3, n)
        # material-frame angular Jacobian R^T Jw, scaled by sqrt(w rho (J, I, I)) per axis
        Jm = np.einsum("pba,pbc->pac", R, Jw.transpose(0, 2, 1, 3).reshape(S * N, 3, n))
        Jm = (np.sqrt(w * rot[None, :, None]) * Jm).reshape(S, N * 3, n)
        M += np.swapaxes(lin, 1, 2) @ lin + np.swapaxes(Jm, 1, 2) @ Jm
    return 0.5 * (M + np.swapaxes(M, 1, 2))


def clothoid_node_speeds(clothoid, rates: np.ndarray, kin=None) -> np.ndarray:
    """(S,) per strand the max over its nodes of |Cdot| (root at rest;
    :func:`groomtool.rods.clothoid.node_velocities`)."""
    return np.linalg.norm(cl.node_velocities(clothoid, rates, kin), axis=-1).max(axis=1)


CLOTHOID_COMPLEX_STEP = 1e-30  # the clothoid's velocity terms: derivatives by the complex step (exact to round-off)


def _clothoid_point_motion(clothoid, kin, rates, order: int):
    """Per Gauss point (``order`` per element, all strands): weight w (S, N), the centreline velocity Cdot and the
    material angular velocity R^T w of the rates (S * N per quadrature node, lists over the nodes) and the J, Jw, R
    used (complex-safe: no conjugation anywhere)."""
    S, N = clothoid.lengths.shape
    xg, wg = np.polynomial.legendre.leggauss(order)
    starts = clothoid.element_starts[:, :-1]
    strand = np.repeat(np.arange(S), N)
    v = np.asarray(rates).reshape(S, N + 1, 3)[strand]
    out = []
    for xq, wq in zip(0.5 * (xg + 1.0), 0.5 * wg):
        s = (starts + xq * clothoid.lengths).ravel()
        J, Jw, R, _ = cl.point_jacobians_rotation(clothoid, strand, s, kin)
        cdot = np.einsum("pnac,pnc->pa", J, v)
        om = np.einsum("pba,pnbc,pnc->pa", R, Jw, v)
        out.append(((wq * clothoid.lengths).ravel(), cdot, om, J, Jw, R))
    return out


def clothoid_kinetic_energy(clothoid, inertia: Inertia, rates, kin=None, order: int = 4) -> np.ndarray:
    """T = 1/2 int rhoS |Cdot|^2 + (R^T w)^T diag(rho J, rho I, rho I) (R^T w) ds per strand (S,), from the point
    velocities at Gauss points (equal to 1/2 v^T M v with :func:`clothoid_mass_matrix` of the same order);
    analytic in q and the rates (complex-step safe)."""
    kin = kin if kin is not None else cl.kinematics(clothoid)
    S, N = clothoid.lengths.shape
    rot = np.asarray(inertia.rotational, dtype=np.float64)
    T = 0.0
    for w, cdot, om, *_ in _clothoid_point_motion(clothoid, kin, rates, order):
        T = T + 0.5 * w * (inertia.linear * np.sum(cdot * cdot, axis=1) + (om * om) @ rot)
    return np.sum(np.reshape(T, (S, N)), axis=1)


def clothoid_momentum(clothoid, inertia: Inertia, rates, kin=None, order: int = 4) -> np.ndarray:
    """dT/dv = M v, (S, N + 1, 3), from the point velocities (O(N) per point, no M): sum over the Gauss points of
    w (rhoS J^T Cdot + Jw^T R diag(rot) R^T w)."""
    kin = kin if kin is not None else cl.kinematics(clothoid)
    S, N = clothoid.lengths.shape
    rot = np.asarray(inertia.rotational, dtype=np.float64)
    out = 0.0
    for w, cdot, om, J, Jw, R in _clothoid_point_motion(clothoid, kin, rates, order):
        tau = np.einsum("pab,pb->pa", R, om * rot)  # world angular momentum density
        part = (np.einsum("pnac,pa->pnc", J, inertia.linear * cdot) + np.einsum("pnac,pa->pnc", Jw, tau))
        out = out + (w[:, None, None] * part).reshape(S, N, N + 1, 3).sum(axis=1)
    return out


def clothoid_velocity_terms(clothoid, inertia: Inertia, rates, kin=None, order: int = 4) -> np.ndarray:
    """A(q, qd) = Mdot qd - dT/dq of Super Space Clothoids (static root), (S, N + 1, 3), from Lagrange's equations
    (M qdd + A = forces with T = 1/2 qd^T M(q) qd):

        Mdot qd = d/de [M(q + e qd) qd]    (one complex step of :func:`clothoid_momentum` along qd),
        dT/dq_j                            (one complex step of the kinetic energy per dof, batched over copies of
                                            each strand: :func:`_clothoid_energy_gradient`, O(N) per copy).

    Same Gauss points as :func:`clothoid_mass_matrix`, so A is exactly the velocity term of that M.  O(N^2) per
    strand; zero at rest."""
    kin = kin if kin is not None else cl.kinematics(clothoid)
    S, N = clothoid.lengths.shape
    eps = CLOTHOID_COMPLEX_STEP
    v = np.asarray(rates, dtype=np.float64).reshape(S, N + 1, 3) * clothoid.node_mask[..., None]
    moved = clothoid.with_curvatures(clothoid.curvatures + 1j * eps * v)
    mdot = clothoid_momentum(moved, inertia, v, cl.kinematics(moved), order).imag / eps
    # dT/dq by copies of each strand, one per real dof
    sid, col = np.nonzero(np.arange(3 * (N + 1))[None, :] // 3 <= clothoid.n_elements[:, None])
    q = clothoid.curvatures[sid].astype(np.complex128).reshape(len(sid), -1)
    q[np.arange(len(sid)), col] += 1j * eps
    copies = cl.SuperClothoid(clothoid.root_positions[sid], clothoid.root_frames[sid], clothoid.lengths[sid],
                              q.reshape(len(sid), N + 1, 3), clothoid.n_elements[sid])
    energy = _clothoid_energy_gradient(clothoid, inertia, v, kin, sid, col, copies,
                                       _copies_kinematics(copies, kin, sid, col // 3), order)
    grad = np.zeros((S, 3 * (N + 1)))
    grad[sid, col] = energy.imag / eps
    return (mdot - grad.reshape(S, N + 1, 3)) * clothoid.node_mask[..., None]


def _copies_kinematics(copies, kin, sid, node):
    """Kinematics of copies of strands ``sid`` whose node ``node`` was perturbed (complex step): only the two
    elements touching the node are propagated again (as clothoid.gravity_force_jacobian does), the others copied
    from the real ``kin``, then the chain."""
    m = len(sid)
    N = copies.max_elements
    a, b = copies.starts_and_slopes()
    arrays = [np.ascontiguousarray(getattr(kin, name)[sid], dtype=np.complex128)
              for name in ("Q", "p", "P", "Mphi", "MX", "MZ")]
    rows = np.repeat(np.arange(m, dtype=np.int64), 2)
    elems = np.stack([node - 1, node], axis=1).ravel().astype(np.int64)
    cl._element_subset_kernel(np.ascontiguousarray(copies.lengths), a, b, rows, elems, *arrays,
                              *cl._scratch(np.complex128))
    Q, p, P, Mphi, MX, MZ = arrays
    C = np.empty((m, N + 1, 3), dtype=np.complex128)
    R = np.empty((m, N + 1, 3, 3), dtype=np.complex128)
    cl._chain(np.ascontiguousarray(copies.root_positions, dtype=np.complex128),
              np.ascontiguousarray(copies.root_frames, dtype=np.complex128), Q, p, C, R)
    return cl.Kinematics(copies, C, R, Q, p, P, Mphi, MX, MZ, a, b, None)


def _clothoid_energy_gradient(clothoid, inertia: Inertia, v, kin, sid, col, copies, ckin, order: int):
    """dT/dq by the complex step on copies (strand sid, dof col perturbed), O(N) per copy: the in-element partial
    series at each Gauss point depend only on their own element, so they are taken from the real configuration
    except in the two elements beside the perturbed node (recomputed in complex arithmetic); the upstream part of
    every point velocity is a prefix sum over the copy's elements (node_jacobian_terms).  Returns T per copy."""
    S, N = clothoid.lengths.shape
    m = len(sid)
    node = col // 3
    xg, wg = np.polynomial.legendre.leggauss(order)
    rot = np.asarray(inertia.rotational, dtype=np.float64)
    vc = v[sid]  # (m, N + 1, 3)
    Ts, Te, Bs, Be = cl.node_jacobian_terms(ckin)  # (m, N, 3, 3) complex
    beta = np.einsum("cnab,cnb->cna", Bs, vc[:, :-1]) + np.einsum("cnab,cnb->cna", Be, vc[:, 1:])
    omega = np.einsum("cnab,cnb->cna", Ts, vc[:, :-1]) + np.einsum("cnab,cnb->cna", Te, vc[:, 1:])
    mask = clothoid.element_mask[sid][..., None]
    Bsum = np.cumsum(beta * mask, axis=1) - beta * mask  # sum over k < e
    Wsum = np.cumsum(omega * mask, axis=1) - omega * mask
    lengths = clothoid.lengths[sid]  # (m, N)
    strand_all = np.repeat(np.arange(S), N)
    elem_all = np.tile(np.arange(N), S)
    T = np.zeros(m, dtype=np.complex128)
    rows = np.repeat(np.arange(m), 2)
    near = np.stack([node - 1, node], axis=1).ravel()
    ok = (near >= 0) & (near < clothoid.n_elements[sid][rows])
    rows, near = rows[ok], near[ok]
    for xq, wq in zip(0.5 * (xg + 1.0), 0.5 * wg):
        t_all = xq * clothoid.lengths.ravel()
        Phi, p, Mphi, MX = (x.reshape((S, N) + x.shape[1:])[sid].astype(np.complex128)
                            for x in cl._partial(clothoid, kin, strand_all, elem_all, t_all))
        if len(rows):
            Phi_c, p_c, Mphi_c, MX_c = cl._partial(copies, ckin, rows, near, xq * lengths[rows, near])
            Phi[rows, near], p[rows, near], Mphi[rows, near], MX[rows, near] = Phi_c, p_c, Mphi_c, MX_c
        As, Ae = cl._hat_split(Mphi, lengths)
        Ys, Ye = cl._hat_split(MX[:, :, :2], lengths)
        Re = ckin.R[:, :-1]
        x = ckin.C[:, :-1] + np.einsum("cnab,cnb->cna", Re, p)
        ang = np.einsum("cnab,cnb->cna", As, vc[:, :-1]) + np.einsum("cnab,cnb->cna", Ae, vc[:, 1:])
        lin = np.einsum("cnab,cnb->cna", Ys, vc[:, :-1]) + np.einsum("cnab,cnb->cna", Ye, vc[:, 1:]) - np.cross(p, ang)
        cdot = Bsum - np.cross(x, Wsum) + np.einsum("cnab,cnb->cna", Re, lin)
        om = Wsum + np.einsum("cnab,cnb->cna", Re, ang)
        om_mat = np.einsum("cnba,cnb->cna", Re @ Phi, om)
        dens = inertia.linear * np.sum(cdot * cdot, axis=-1) + (om_mat * om_mat) @ rot
        T = T + 0.5 * np.sum(wq * lengths * dens * mask[..., 0], axis=1)
    return T
