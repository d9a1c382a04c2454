"""Forward simulation of Super-Helices under gravity and Coulomb frictional contact (MATH.md 1, 4, 5).

Equations of motion per strand (rods/dynamics.py for M and A):

    M(q) qdd + K (q - q0) + A(q, qd) = F(q) + H^T r

Semi-implicit Euler, elastic forces (and gravity, linearised) implicit, contact impulses r (N s):

    Mhat v' = M v + h (F(q) - K (q - q0) - A(q, v)) + H^T r,   q' = q + h v'
    Mhat    = M + h^2 (K - dF/dq) + h (alpha M + beta K)

(alpha = mass damping + air drag / rhoS, beta = stiffness damping).  Where gravity makes a mode of
a strand unstable enough that the implicit step would amplify it without bound (a strand standing
up beyond its buckling length), that strand's Mhat is modified mode by mode (factor_step_matrix).
The root follows a static or moving head transform (its inertial forces enter through A).

Contacts, each step: sample the helices, detect strand/strand and strand/head contacts on the current
geometry, H from contact/jacobian.py, and solve the velocity-level Coulomb problem

    u = H v' + w = W r + b,   W = H Mhat^-1 H^T,   b = H Mhat^-1 rhs + w - ubar e_N

with the solvers package (De Saxce's change of variable, block Gauss-Seidel).  ubar is the normal
velocity a contact must at least have (docs/simulation.md): -gap/h for a contact detected ahead of
touching (speculative margin), 0 for a contact within the contact thickness (no push: a groom at
rest stays at rest), and a gentle push min(push_rate * excess / h, max_push_speed) only for the part
of a penetration deeper than both the allowance and the contact's own depth at the start.
Contacts that carried load in the previous step stay in the problem while within reach (re-evaluated
at their arc lengths), so a strand draped over a surface keeps several supports.

At an equilibrium the inversion produced (K (q - q0) = F + H^T r_inv, r_inv in the cones), v = 0 and
r = h r_inv solve the first step exactly: u = W (h r_inv) + b = H Mhat^-1 h (F - K (q - q0) + H^T r_inv) = 0.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from numba import njit

from .material import Material
from .rods import dynamics as dyn
from .rods import superhelix as sh

CONTACT_MODES = ("none", "head", "all")


# --------------------------------------------------------------------------- parameters
@dataclass
class SimulationParams:
    """Everything that decides a simulation besides the strands, the material and gravity.

    dt (s); contacts none | head | all; contact_radius (m, None: the contact module's default, the
    one the inversion used); penetration_allowance (m, None: half the contact radius) is the depth
    tolerated without push; push_rate (per step) and max_push_speed (m/s) bound the push;
    head_margin and strand_margin (m, None: 100 and 2 contact radii) bound how far ahead of touching
    strand/head and strand/strand contacts are detected (1.5 h |v|max, speculative);
    mass_damping alpha (1/s), stiffness_damping beta (s), air_drag (kg/(m s), a force -c v per unit
    length, approximated as alpha += c / rhoS); rotational_inertia_scale multiplies the cross-section
    rotational inertia; velocity_terms: compute A(q, qd) (else dropped); implicit_gravity: include
    -h^2 dF/dq in Mhat; max_rotation_per_step (rad, None: off) is a safeguard against violent
    unresolved motion: a strand whose element would turn by more than this in one step has its rates
    scaled down (counted in the result's stats).
    """

    dt: float = 1.0 / 240.0
    contacts: str = "all"
    contact_radius: float | None = None
    samples_per_element: int = 8
    friction: float | None = None
    penetration_allowance: float | None = None
    push_rate: float = 0.2
    max_push_speed: float = 0.02
    head_margin: float | None = None
    strand_margin: float | None = None
    mass_damping: float = 0.0
    stiffness_damping: float = 0.0
    air_drag: float = 0.0
    rotational_inertia_scale: float = 1.0
    velocity_terms: bool = True
    implicit_gravity: bool = True
    quadrature_order: int = 4
    max_rotation_per_step: float | None = 0.25
    solver: str = "auto"
    solver_tolerance: float = 1e-8
    max_iterations: int = 2000

    def __post_init__(self):
        if self.contacts not in CONTACT_MODES:
            raise ValueError(f"contacts must be one of {CONTACT_MODES}, got {self.contacts!r}")
        if not (self.dt > 0 and np.isfinite(self.dt)):
            raise ValueError(f"dt must be > 0, got {self.dt}")
        for name in ("mass_damping", "stiffness_damping", "air_drag", "push_rate", "max_push_speed"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not (self.rotational_inertia_scale > 0):
            raise ValueError("rotational_inertia_scale must be > 0")


# --------------------------------------------------------------------------- head motion
def _rigid_motion(head_motion, t: float, eps: float = 1e-4):
    """Transform (R, T) of the head at t, its velocity (V, Omega) and acceleration (a, alpha) by
    central differences; x_world = R x_rest + T, v(x) = V + Omega x (x - T)."""
    R, T = (np.asarray(a, dtype=np.float64) for a in head_motion(t))
    Rm, Tm = (np.asarray(a, dtype=np.float64) for a in head_motion(t - eps))
    Rp, Tp = (np.asarray(a, dtype=np.float64) for a in head_motion(t + eps))
    V = (Tp - Tm) / (2 * eps)
    acc = (Tp - 2 * T + Tm) / eps**2

    def axial(S):
        return 0.5 * np.array([S[2, 1] - S[1, 2], S[0, 2] - S[2, 0], S[1, 0] - S[0, 1]])

    Om = axial((Rp - Rm) / (2 * eps) @ R.T)
    Om_p = axial((Rp - R) / eps @ R.T)
    Om_m = axial((R - Rm) / eps @ Rm.T)
    alpha = (Om_p - Om_m) / eps
    return R, T, V, Om, acc, alpha


# --------------------------------------------------------------------------- contact bookkeeping
def contact_gaps(contacts, radius: float) -> np.ndarray:
    """gap = axis distance - 2 r_c (strand/strand) or signed axis-to-surface distance - r_c (head);
    negative inside the contact thickness."""
    head = np.asarray(contacts.strand_b) < 0
    return np.asarray(contacts.distance) - np.where(head, radius, 2.0 * radius)


def match_contacts(old, new, arc_tolerance: float) -> np.ndarray:
    """For every contact of ``new`` the index of the same contact in ``old`` (same strands, arc lengths
    within ``arc_tolerance`` in |ds_a| + |ds_b|, the closest), or -1."""
    m_new = len(new.strand_a)
    out = np.full(m_new, -1, dtype=np.int64)
    if old is None or len(old.strand_a) == 0 or m_new == 0:
        return out
    K = int(max(np.max(old.strand_a), np.max(new.strand_a), np.max(old.strand_b), np.max(new.strand_b))) + 2
    key_old = np.asarray(old.strand_a, np.int64) * K + np.asarray(old.strand_b, np.int64) + 1
    key_new = np.asarray(new.strand_a, np.int64) * K + np.asarray(new.strand_b, np.int64) + 1
    order = np.argsort(key_old, kind="stable")
    sorted_keys = key_old[order]
    lo = np.searchsorted(sorted_keys, key_new, "left")
    hi = np.searchsorted(sorted_keys, key_new, "right")
    sb_old = np.nan_to_num(np.asarray(old.s_b, dtype=np.float64))
    sb_new = np.nan_to_num(np.asarray(new.s_b, dtype=np.float64))
    best = np.full(m_new, np.inf)
    for k in range(int(np.max(hi - lo, initial=0))):
        idx = lo + k
        valid = idx < hi
        j = order[np.minimum(idx, len(order) - 1)]
        d = np.abs(new.s_a - old.s_a[j]) + np.abs(sb_new - sb_old[j])
        better = valid & (d <= arc_tolerance) & (d < best)
        best[better] = d[better]
        out[better] = j[better]
    return out


def normal_velocity_targets(gap, allowed, dt: float, push_rate: float, max_push_speed: float) -> np.ndarray:
    """ubar per contact: -gap/h ahead of touching, 0 within the allowed depth, a bounded push beyond."""
    gap = np.asarray(gap, dtype=np.float64)
    excess = -gap - allowed
    push = np.minimum(push_rate * np.maximum(excess, 0.0) / dt, max_push_speed)
    return np.where(gap > 0.0, -gap / dt, np.where(excess > 0.0, push, 0.0))


# --------------------------------------------------------------------------- state and results
@dataclass
class State:
    """Time (s), curvatures q and rates v = qdot, (S, N, 3) padded like the helix."""

    time: float
    curvatures: np.ndarray
    rates: np.ndarray


@dataclass
class StepSystem:
    """One step up to the contact problem (exposed for tests): the Cholesky factors of Mhat (S, 3N, 3N),
    the free rates v_free (S, N, 3), contacts, H, the solver-scaled ContactProblem (r = r_scale r~,
    u = u_scale u~), and the geometry it was built on."""

    helix: sh.SuperHelix
    kin: sh.Kinematics
    chol: np.ndarray
    v_free: np.ndarray
    mass: np.ndarray
    contacts: object = None
    H: object = None
    problem: object = None
    r_scale: float = 1.0
    u_scale: float = 1.0
    r0: np.ndarray | None = None
    stats: dict = field(default_factory=dict)


@dataclass
class SimulationResult:
    """Frames (F, V, 3) of the sampled strands at ``times`` (F,), ``offsets`` (S + 1,) into each frame;
    tips (steps + 1, S, 3); the final state; timings (s: per stage summed, ``per_step`` the mean step
    after the first, ``first_step``); per-step stats."""

    times: np.ndarray
    frames: np.ndarray
    offsets: np.ndarray
    tips: np.ndarray
    final: State
    helix: sh.SuperHelix
    timings: dict
    stats: dict


# --------------------------------------------------------------------------- the simulator
class Simulator:
    """Steps Super-Helices forward in time (module docstring).

    helix: the initial configuration (q and root); rest_curvatures q0 (S, N, 3); material; gravity (3,);
    head: a trimesh.Trimesh or None; head_motion: None (static) or t -> (R (3,3), T (3,)) mapping the
    initial pose to the pose at time t (roots and head follow it); initial_rates (S, N, 3) or None;
    stiffness: K (S, N, 3) instead of the material's; warm_start: (contacts, forces (m, 3) in N) known
    at the start, e.g. the inversion's: the first contact solve starts from r = h * forces on the
    contacts that match (an inverted groom's first step is then solved before any sweep).
    """

    def __init__(self, helix: sh.SuperHelix, rest_curvatures, material: Material, gravity, head=None,
                 params: SimulationParams | None = None, head_motion: Callable | None = None,
                 initial_rates=None, stiffness=None, warm_start=None):
        self.params = params or SimulationParams()
        self.material = material
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.head = head
        self.head_motion = head_motion
        self.rest = np.asarray(rest_curvatures, dtype=np.float64).reshape(helix.curvatures.shape)
        self.base_roots = helix.root_positions.copy()
        self.base_frames = helix.root_frames.copy()
        self.lengths = helix.lengths
        self.n_elements = helix.n_elements
        self.inertia = dyn.Inertia.from_material(material, self.params.rotational_inertia_scale)
        self.K = sh.stiffness(helix, material.stiffness_diag) if stiffness is None else np.asarray(stiffness, float)
        self.mask = helix.element_mask
        rates = np.zeros_like(helix.curvatures) if initial_rates is None else np.asarray(initial_rates, float)
        self.state = State(0.0, helix.curvatures.copy(), rates * self.mask[..., None])
        self.friction = material.friction if self.params.friction is None else self.params.friction
        self.timings: dict[str, float] = {}
        self.modified_strands = 0  # strand-steps whose step matrix was modified (factor_step_matrix)
        self.clamped_strands = 0  # strand-steps whose rates were scaled down (_limit_rotation)
        self._prev_contacts = None
        self._prev_impulses = None
        self._warm_start = None
        if warm_start is not None and len(warm_start[1]):
            forces = np.asarray(warm_start[1], dtype=np.float64).reshape(-1, 3)
            self._warm_start = (warm_start[0], forces * self.params.dt)
        self._initial_contacts = None
        self._contacts_on = self.params.contacts == "all" or (self.params.contacts == "head" and head is not None)
        self._head_surface = None
        self._radius = self.params.contact_radius
        if self._contacts_on:
            from .contact import DEFAULT_CONTACT_RADIUS, as_head_surface

            if self._radius is None:
                self._radius = DEFAULT_CONTACT_RADIUS
            self._head_surface = as_head_surface(head) if head is not None else None
            self._initial_contacts = self._detect(self.helix(), (0.0, 0.0))

    # ---------------------------------------------------------------- geometry
    def _root_pose(self, t: float):
        if self.head_motion is None:
            return self.base_roots, self.base_frames, None
        R, T, V, Om, acc, alpha = _rigid_motion(self.head_motion, t)
        roots = self.base_roots @ R.T + T
        frames = R @ self.base_frames
        rel = roots - T
        motion = {"root_velocity": V + np.cross(Om, rel), "root_angular_velocity": np.broadcast_to(Om, rel.shape),
                  "root_acceleration": acc + np.cross(alpha, rel) + np.cross(Om, np.cross(Om, rel)),
                  "root_angular_acceleration": np.broadcast_to(alpha, rel.shape)}
        return roots, frames, (R, T, V, Om, motion)

    def helix(self, state: State | None = None) -> sh.SuperHelix:
        """The strands at ``state`` (default: the current one), roots where the head puts them."""
        state = state or self.state
        roots, frames, _ = self._root_pose(state.time)
        return sh.SuperHelix(roots, frames, self.lengths, state.curvatures, self.n_elements)

    # ---------------------------------------------------------------- contacts
    def _detect(self, helix: sh.SuperHelix, margins: tuple[float, float], kin=None):
        """Contacts of the strands sampled ``samples_per_element`` times per element, detected with the
        contact radius plus ``margins`` = (head, strand) (speculative); with a moving head, in the
        head's rest frame."""
        from .contact import detect_contacts

        pts, offsets, _, arc = sh.sample(helix, self.params.samples_per_element, kin)
        pose = None
        if self.head_motion is not None:
            R, T = (np.asarray(a, dtype=np.float64) for a in self.head_motion(self.state.time))
            pose = (R, T)
            pts = (pts - T) @ R  # R^T (x - T)
        contacts = detect_contacts(pts, offsets, arc, radius=self._radius + margins[1], head=self._head_surface,
                                   strand_strand=self.params.contacts == "all",
                                   head_radius=self._radius + margins[0])
        if pose is not None and len(contacts.strand_a):
            R, T = pose
            contacts.point_a = contacts.point_a @ R.T + T
            contacts.point_b = contacts.point_b @ R.T + T
            contacts.normal = contacts.normal @ R.T
            contacts.frame = contacts.frame @ R.T
        return contacts

    def _persistent(self, helix: sh.SuperHelix, kin, detected, margins: tuple[float, float]):
        """Previous-step contacts that carried load (r_N > 0), not re-detected nearby, re-evaluated at
        their arc lengths on the current geometry and kept while within reach: a strand draped over
        a smooth surface keeps several supports instead of one that hops between samples."""
        from .contact import Contacts, contact_frames

        prev, imp = self._prev_contacts, self._prev_impulses
        if prev is None or imp is None or len(imp) == 0:
            return detected
        cand = prev.subset(imp[:, 0] > 0)
        if len(cand) and len(detected):
            spacing = float(np.mean(self.lengths[self.mask])) / self.params.samples_per_element
            cand = cand.subset(match_contacts(detected, cand, max(4.0 * self._radius, spacing)) < 0)
        if len(cand) == 0:
            return detected
        x_a, R_a = sh.evaluate(helix, cand.strand_a, cand.s_a, kin)
        head = cand.strand_b < 0
        point_b = np.empty_like(x_a)
        normal = np.empty_like(x_a)
        dist = np.empty(len(cand))
        if np.any(head):
            x = x_a[head]
            if self.head_motion is not None:
                R, T = (np.asarray(a, dtype=np.float64) for a in self.head_motion(self.state.time))
                d, c, n, _ = self._head_surface.query((x - T) @ R)
                c, n = c @ R.T + T, n @ R.T
            else:
                d, c, n, _ = self._head_surface.query(x)
            dist[head], point_b[head], normal[head] = d, c, n
        if np.any(~head):
            x_b, _ = sh.evaluate(helix, cand.strand_b[~head], cand.s_b[~head], kin)
            gap = x_a[~head] - x_b
            d = np.linalg.norm(gap, axis=1)
            n = np.where(d[:, None] > 1e-12, gap / np.maximum(d, 1e-300)[:, None], cand.normal[~head])
            dist[~head], point_b[~head], normal[~head] = d, x_b, n
        threshold = np.where(head, self._radius + margins[0], 2.0 * self._radius + 2.0 * margins[1])
        keep = dist <= threshold
        if not np.any(keep):
            return detected
        frames = contact_frames(normal[keep], R_a[keep, :, 0])
        kept = Contacts(cand.strand_a[keep], cand.s_a[keep], cand.strand_b[keep], cand.s_b[keep], x_a[keep],
                        point_b[keep], normal[keep], frames, dist[keep], detected.radius)
        return Contacts.concatenate([detected, kept])

    def contact_radius(self) -> float | None:
        return self._radius

    def _allowed_depth(self, contacts) -> np.ndarray:
        """Depth tolerated without push: the allowance, or the contact's own depth at the start."""
        r_c = self._radius
        base = 0.5 * r_c if self.params.penetration_allowance is None else self.params.penetration_allowance
        allowed = np.full(len(contacts.strand_a), base)
        init = self._initial_contacts
        if init is not None and len(init.strand_a):
            sample = float(np.max(self.lengths)) / self.params.samples_per_element
            idx = match_contacts(init, contacts, 4.0 * r_c + 2.0 * sample)
            depth0 = -contact_gaps(init, r_c)
            has = idx >= 0
            allowed[has] = np.maximum(allowed[has], depth0[idx[has]])
        return allowed

    def _speculative_margins(self, speed: float) -> tuple[float, float]:
        """(head, strand) detection margins: 1.5 h |v|max, capped."""
        p = self.params
        reach = 1.5 * speed * p.dt
        head_cap = 100.0 * self._radius if p.head_margin is None else p.head_margin
        strand_cap = 2.0 * self._radius if p.strand_margin is None else p.strand_margin
        return float(min(head_cap, reach)), float(min(strand_cap, reach))

    # ---------------------------------------------------------------- one step
    def _time(self, name: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.timings[name] = self.timings.get(name, 0.0) + t1 - t0
        return t1

    def assemble(self) -> StepSystem:
        """Dynamics, factorisation, free rates, contacts and the scaled contact problem of the next step."""
        p = self.params
        h = p.dt
        st = self.state
        t0 = time.perf_counter()
        roots, frames, pose = self._root_pose(st.time)
        helix = sh.SuperHelix(roots, frames, self.lengths, st.curvatures, self.n_elements)
        kin = sh.kinematics(helix)
        pts = dyn.element_points(helix, kin, p.quadrature_order)
        M = dyn.mass_matrix(helix, self.inertia, kin, points=pts)
        F = sh.gravity_force(helix, self.inertia.linear, self.gravity, kin)
        root_motion = pose[4] if pose is not None else None
        if p.velocity_terms or root_motion is not None:
            A = dyn.velocity_terms(helix, st.rates, self.inertia, kin, points=pts, root_motion=root_motion)
        else:
            A = 0.0
        t0 = self._time("dynamics", t0)

        S, N = self.lengths.shape
        n = 3 * N
        Kf = self.K.reshape(S, n)
        alpha = p.mass_damping + p.air_drag / self.inertia.linear
        Mhat = (1.0 + h * alpha) * M
        Mhat[:, np.arange(n), np.arange(n)] += (h * h + h * p.stiffness_damping) * Kf
        pad = ~np.repeat(self.mask, 3, axis=1)
        Mhat[:, np.arange(n), np.arange(n)] += pad
        force = F - self.K * (st.curvatures - self.rest) - A
        rhs = np.einsum("sij,sj->si", M, st.rates.reshape(S, n)) + h * force.reshape(S, n)
        rhs[pad] = 0.0
        if p.implicit_gravity:
            dF = sh.gravity_force_jacobian(helix, self.inertia.linear, self.gravity, kin)
            chol, modified = factor_step_matrix(Mhat, -h * h * dF, self.n_elements)
            self.modified_strands += modified
        else:
            chol = np.linalg.cholesky(Mhat)
        v_free = _cho_solve(chol, rhs).reshape(S, N, 3)
        t0 = self._time("factor", t0)
        system = StepSystem(helix=helix, kin=kin, chol=chol, v_free=v_free, mass=M)
        if not self._contacts_on:
            return system

        nodes = dyn.node_motion(helix, st.rates, kin)
        margins = self._speculative_margins(float(np.max(np.linalg.norm(nodes.V, axis=-1), initial=0.0)))
        contacts = self._persistent(helix, kin, self._detect(helix, margins, kin), margins)
        t0 = self._time("detect", t0)
        system.stats["contacts"] = len(contacts.strand_a)
        system.contacts = contacts
        if len(contacts.strand_a) == 0:
            return system
        from .contact.jacobian import contact_jacobian

        H = contact_jacobian(helix, contacts, kin)
        t0 = self._time("jacobian", t0)
        gap = contact_gaps(contacts, self._radius)
        ubar = normal_velocity_targets(gap, self._allowed_depth(contacts), h, p.push_rate, p.max_push_speed)
        w = np.zeros((len(gap), 3))
        if pose is not None:
            Om = pose[3]  # both sides move rigidly with the head: v_a - v_b = Omega x (x_a - x_b)
            w = np.einsum("mij,mj->mi", contacts.frame, np.cross(Om, contacts.point_a - contacts.point_b))
        w[:, 0] -= ubar
        system.H = H
        self._build_problem(system, w.ravel())
        self._time("contact_setup", t0)
        return system

    def _build_problem(self, system: StepSystem, w: np.ndarray) -> None:
        """The contact problem u~ = W r~ + b~ with W = H Mhat^-1 H^T (dense Mhat^-1 blocks only for the
        strands in contact), in impulse units r = r_scale r~, u = r_scale u~ (the block Gauss-Seidel
        normalises every local problem, so W needs no scaling)."""
        from .solvers import ContactProblem

        helix = system.helix
        H = system.H
        # a contact that no dof can move (at the clamped root) transmits nothing: drop it
        row_norm = np.sqrt(np.asarray(H.multiply(H).sum(axis=1)).ravel()).reshape(-1, 3).max(axis=1)
        keep = row_norm > 1e-9 * float(np.max(row_norm, initial=0.0))
        if not np.any(keep):
            return
        if not np.all(keep):
            system.contacts = system.contacts.subset(keep)
            H = system.H = H[np.repeat(keep, 3)]
            w = w.reshape(-1, 3)[keep].ravel()
        touched = np.zeros(helix.n_strands, dtype=bool)
        touched[system.contacts.strand_a] = True
        touched[system.contacts.strand_b[system.contacts.strand_b >= 0]] = True
        blocks = [np.zeros(3 * int(k)) for k in helix.n_elements]
        for s in np.flatnonzero(touched):
            blocks[s] = _cho_inverse(system.chol[s], 3 * int(helix.n_elements[s]))
        b = H @ helix.to_flat(system.v_free).ravel() + w
        g = float(np.linalg.norm(self.gravity))
        r_scale = self.inertia.linear * float(np.mean(helix.strand_lengths)) * max(g * self.params.dt, 1e-3)
        mu = np.full(len(system.contacts.strand_a), self.friction)
        system.problem = ContactProblem(H=H, D_blocks=blocks, dof_offsets=3 * helix.flat_offsets(), gamma=0.0,
                                        b=b / r_scale, mu=mu)
        system.r_scale = system.u_scale = r_scale
        r0 = np.zeros((len(mu), 3))
        known = (self._prev_contacts, self._prev_impulses) if self._prev_impulses is not None else self._warm_start
        if known is not None:
            idx = match_contacts(known[0], system.contacts, 2.0 * self._radius + 1e-12)
            has = idx >= 0
            r0[has] = known[1][idx[has]] / r_scale
        system.r0 = r0.ravel()

    def solve_contacts(self, system: StepSystem) -> np.ndarray:
        """Impulses r (m, 3) in newton-seconds, contact frames (N, T1, T2): the Coulomb law (De Saxce).

        Convergence is measured relative to max(max_i rho_i |b_i|, 1) in r~ units, i.e. with a floor
        of one strand's weight impulse over a step: at rest b is round-off and a purely relative
        measure could never be met.  A warm start that already satisfies the law skips the sweeps.
        """
        from .solvers import solve_contact_problem
        from .solvers.residual import residual as law_residual

        p = self.params
        t0 = time.perf_counter()
        problem = system.problem
        scale = max(problem.residual_scale(), 1.0)

        def error(r):
            return law_residual(r, problem.velocity(r), problem.mu, problem.rho(), scale, law="coulomb")

        r = system.r0
        err = error(r)
        iterations, status = 0, "warm_start"
        if not err <= p.solver_tolerance:
            res = solve_contact_problem(problem, law="coulomb", method=p.solver, tol=p.solver_tolerance,
                                        max_iter=p.max_iterations, r0=r, scale=scale)
            r, iterations, status = np.asarray(res.r), int(res.iterations), str(res.status)
            err = error(r)
        self._time("solve", t0)
        system.stats.update(solver_iterations=iterations, solver_residual=float(err),
                            solver_converged=bool(err <= p.solver_tolerance), solver_status=status)
        return np.asarray(r, dtype=np.float64).reshape(-1, 3) * system.r_scale

    def finish(self, system: StepSystem, impulses: np.ndarray | None) -> None:
        """v' = v_free + Mhat^-1 H^T r;  q' = q + h v';  t' = t + h."""
        t0 = time.perf_counter()
        helix = system.helix
        v = system.v_free
        if impulses is not None and len(impulses):
            gen = helix.from_flat((system.H.T @ impulses.ravel()).reshape(-1, 3))
            S = helix.n_strands
            v = v + _cho_solve(system.chol, gen.reshape(S, -1)).reshape(v.shape)
        v = self._limit_rotation(v * self.mask[..., None])
        st = self.state
        self.state = State(st.time + self.params.dt, st.curvatures + self.params.dt * v, v)
        self._prev_contacts = system.contacts
        self._prev_impulses = impulses
        self._time("update", t0)

    def _limit_rotation(self, v: np.ndarray) -> np.ndarray:
        """Safeguard: scale a strand's rates so that no element turns by more than max_rotation_per_step
        (rad: h |v_j| l_j) in one step.  Counted in ``clamped_strands``; never active near equilibrium."""
        bound = self.params.max_rotation_per_step
        if not bound:
            return v
        turn = self.params.dt * np.linalg.norm(v, axis=-1) * self.lengths
        worst = np.max(turn, axis=1)
        over = worst > bound
        if not np.any(over):
            return v
        self.clamped_strands += int(np.count_nonzero(over))
        scale = np.where(over, bound / np.where(over, worst, 1.0), 1.0)
        return v * scale[:, None, None]

    def step(self) -> StepSystem:
        """Advance one time step; returns the step's system (contacts, stats)."""
        system = self.assemble()
        impulses = None
        if system.problem is not None:
            impulses = self.solve_contacts(system)
        self.finish(system, impulses)
        system.stats["impulses"] = impulses
        return system

    # ---------------------------------------------------------------- observables
    def tips(self, helix: sh.SuperHelix | None = None) -> np.ndarray:
        """Tip positions (S, 3)."""
        helix = helix or self.helix()
        kin = sh.kinematics(helix)
        return kin.C[np.arange(helix.n_strands), helix.n_elements]

    def energies(self) -> dict:
        """Kinetic 1/2 v^T M v, elastic 1/2 (q - q0)^T K (q - q0) and gravity -rhoS g . int C ds, summed (J)."""
        helix = self.helix()
        kin = sh.kinematics(helix)
        M = dyn.mass_matrix(helix, self.inertia, kin, self.params.quadrature_order)
        d = self.state.curvatures - self.rest
        return {"kinetic": float(dyn.kinetic_energy(M, self.state.rates).sum()),
                "elastic": float(0.5 * np.sum(self.K * d * d)),
                "gravity": float(sh.gravity_potential(helix, self.inertia.linear, self.gravity, kin).sum())}


# --------------------------------------------------------------------------- linear algebra helpers
def factor_step_matrix(A: np.ndarray, B: np.ndarray, n_elements: np.ndarray) -> tuple[np.ndarray, int]:
    """Cholesky factors of Mhat = A + B per strand, A = M + h^2 K + ... (SPD), B = -h^2 dF/dq.

    Where A/2 + B is positive definite (every mode's step factor 1 + lambda >= 1/2, lambda the
    eigenvalues of B relative to A) Mhat = A + B: gravity is linearly implicit.  Elsewhere a mode of
    the potential is unstable enough that 1 + lambda would approach or cross 0 (amplification
    1 / (1 + lambda) unbounded): there, with B V = A V Lambda, V^T A V = I,

        Mhat = A V diag(d) V^T A,   d = 1 + lambda (lambda >= 0),  d = 1 + |lambda| / 2 (lambda < 0),

    which keeps the stable modes implicit and lets an unstable mode grow at most threefold per step
    instead of blowing up.  Returns the factors and the number of strands so modified.
    """
    import scipy.linalg

    ok = _positive_definite(0.5 * A + B)
    M = A + B
    modified = np.flatnonzero(~ok)
    for s in modified:
        n = 3 * int(n_elements[s])
        a, b = A[s, :n, :n], B[s, :n, :n]
        lam, V = scipy.linalg.eigh(b, a)
        d = np.where(lam >= 0.0, 1.0 + lam, 1.0 + 0.5 * np.abs(lam))
        AV = a @ V
        M[s, :n, :n] = (AV * d) @ AV.T
        M[s, :n, :n] = 0.5 * (M[s, :n, :n] + M[s, :n, :n].T)
    return np.linalg.cholesky(M), len(modified)


def _positive_definite(mats: np.ndarray) -> np.ndarray:
    """(S,) True where the symmetric matrix is positive definite (Cholesky succeeds)."""
    try:
        np.linalg.cholesky(mats)
        return np.ones(len(mats), dtype=bool)
    except np.linalg.LinAlgError:
        ok = np.empty(len(mats), dtype=bool)
        for s in range(len(mats)):
            try:
                np.linalg.cholesky(mats[s])
                ok[s] = True
            except np.linalg.LinAlgError:
                ok[s] = False
        return ok


@njit(cache=True)
def _forward(L, b, n):
    """y = L^-1 b on the first n rows (L lower triangular)."""
    y = np.empty(n)
    for i in range(n):
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * y[k]
        y[i] = acc / L[i, i]
    return y


@njit(cache=True)
def _backward(L, y, n):
    """x = L^-T y on the first n rows."""
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        acc = y[i]
        for k in range(i + 1, n):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return x


@njit(cache=True)
def _cho_solve_kernel(L, b, out):
    for s in range(L.shape[0]):
        n = L.shape[1]
        out[s] = _backward(L[s], _forward(L[s], b[s], n), n)


def _cho_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x = (L L^T)^-1 b for every strand; L (S, n, n) lower, b (S, n).  Compiled loops: these small
    solves must not go through a multi-threaded BLAS (slow for 100 x 100 systems on a busy machine)."""
    out = np.empty_like(b)
    _cho_solve_kernel(np.ascontiguousarray(L), np.ascontiguousarray(b), out)
    return out


@njit(cache=True)
def _cho_inverse_kernel(L, n):
    Linv = np.zeros((n, n))
    e = np.zeros(n)
    for j in range(n):
        e[:] = 0.0
        e[j] = 1.0
        Linv[:, j] = _forward(L, e, n)
    out = np.zeros((n, n))
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for k in range(j, n):  # Linv is lower triangular: rows k >= max(i, j)
                acc += Linv[k, i] * Linv[k, j]
            out[i, j] = acc
            out[j, i] = acc
    return out


def _cho_inverse(L: np.ndarray, n: int) -> np.ndarray:
    """(L L^T)^-1 restricted to the first n dofs (a strand's real elements; padding is identity)."""
    return _cho_inverse_kernel(np.ascontiguousarray(L), int(n))


# --------------------------------------------------------------------------- the one-call API
def simulate(helix: sh.SuperHelix, rest_curvatures, material: Material, gravity, head=None,
             seconds: float = 1.0, dt: float = 1.0 / 240.0, contacts: str = "all",
             frames_per_second: float | None = 24.0, samples_per_frame_element: int = 4,
             callback: Callable | None = None, progress: bool = False,
             params: SimulationParams | None = None, head_motion: Callable | None = None,
             warm_start=None) -> SimulationResult:
    """Simulate ``seconds`` of motion; frames of the sampled strands at ``frames_per_second`` (None: every
    step).  ``callback(simulator, system)`` is called after every step; ``warm_start`` as for Simulator.
    Returns a SimulationResult."""
    params = SimulationParams(dt=dt, contacts=contacts) if params is None else replace(params, dt=dt, contacts=contacts)
    t_start = time.perf_counter()
    sim = Simulator(helix, rest_curvatures, material, gravity, head=head, params=params, head_motion=head_motion,
                    warm_start=warm_start)
    setup = time.perf_counter() - t_start
    steps = int(round(seconds / dt))
    every = 1 if not frames_per_second else max(1, int(round(1.0 / (frames_per_second * dt))))
    pts0, offsets, _, _ = sh.sample(sim.helix(), samples_per_frame_element)
    frames = [pts0]
    times = [0.0]
    tips = [sim.tips()]
    n_contacts, iterations, residuals, failures, step_s = [], [], [], 0, []
    from tqdm.auto import tqdm

    with tqdm(total=steps, desc="simulate", unit="step", disable=not progress, leave=False) as bar:
        for k in range(steps):
            t_step = time.perf_counter()
            system = sim.step()
            step_s.append(time.perf_counter() - t_step)
            n_contacts.append(int(system.stats.get("contacts", 0)))
            if "solver_iterations" in system.stats:
                iterations.append(system.stats["solver_iterations"])
                residuals.append(system.stats["solver_residual"])
                failures += not system.stats["solver_converged"]
            h_now = sim.helix()
            tips.append(sim.tips(h_now))
            if (k + 1) % every == 0 or k + 1 == steps:
                frames.append(sh.sample(h_now, samples_per_frame_element)[0])
                times.append(sim.state.time)
            if callback is not None:
                callback(sim, system)
            bar.update(1)
    total = time.perf_counter() - t_start
    timings = dict(sim.timings)
    later = step_s[1:] or step_s  # the first step may include compiling the kernels
    timings.update(setup=setup, total=total, steps=steps, first_step=step_s[0] if step_s else 0.0,
                   per_step=float(np.mean(later)) if later else 0.0)
    stats = {"contacts_per_step": n_contacts, "solver_iterations": iterations, "solver_residuals": residuals,
             "solver_failures": failures, "contact_radius": sim.contact_radius(), "dt": dt, "seconds": steps * dt,
             "modified_step_matrices": sim.modified_strands, "rate_limited_strand_steps": sim.clamped_strands}
    return SimulationResult(times=np.array(times), frames=np.stack(frames), offsets=offsets, tips=np.stack(tips),
                            final=sim.state, helix=sim.helix(), timings=timings, stats=stats)
