"""Forward simulation of Super-Helices under gravity and Coulomb frictional contact (docs/maths.md section 9).

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

A groom at rest (no element turned by more than params.reuse_rotation since the last full assembly) keeps that
assembly's M, A, factorised Mhat, contacts and H; F(q), K (q - q0), the right-hand side and the contact solve are
new every step (Simulator._at_rest_system; docs/simulation.md section 2).  Strands that moved are assembled alone
(_partial_assembly), and only their contacts and those that turned by params.contact_rotation are made anew, the
others' rows of H and W kept (_partial_contacts).

Super Space Clothoids (rods/clothoid.py, ``groom invert --model clothoid``) take the same step on their nodal
curvatures (Simulator._clothoid_dynamics: M with the cross-section rotation, complex-step dF/dq, the block-tridiagonal
K; their velocity terms A dropped, exact at rest, unless params.clothoid_velocity_terms; sticking impulses
polished, _polish_sticking); docs/simulation.md section 8.

Modules: simulate_motion.py (head and root motion), simulate_contacts.py (detection kept while nothing
moved, persistence, velocity targets, warm start), simulate_linalg.py (per-strand factorisation and
solves), simulate_progress.py (progress and run-time estimate), this one (parameters, the step, the
one-call API).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import scipy.sparse as sp
from threadpoolctl import threadpool_limits

from .deprecation import rename_field
from .material import Material
from .rods import clothoid as cl
from .rods import dynamics as dyn
from .rods import superhelix as sh
from .simulate_contacts import (ContactTracker, contact_gaps, match_contacts,  # noqa: F401 (re-exported)
                                normal_velocity_targets, strand_part, touching)
from .simulate_linalg import (StepCorrections, StrandFactors, factor_step_generators, factor_step_matrix,
                              gravity_jacobian_left, mass_apply, moved_dofs, step_difference_apply, strand_chunks)
from .simulate_motion import HeadMotion
from .simulate_motion import rigid_motion as _rigid_motion  # noqa: F401 (re-exported)

CONTACT_MODES = ("none", "head", "all")
# the contact solve (run_gauss_seidel's options; docs/simulation.md section 3): its residual measured cheaply after every
# sweep (quick_check), so a solve within tolerance after 3 sweeps stops there instead of at the tenth; exact checks
# every SOLVE_CHECK_EVERY sweeps, Coulomb cluster steps (solvers/cluster_newton.py) from the first of them on instead
# of the 20th sweep (a sagging groom's slipping root contacts plateau at ~3e-6 from the first sweeps)
QUICK_CHECK = 1
SOLVE_CHECK_EVERY = 10


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
    scaled down (counted in the result's stats).  detection_skin (m, None: the contact radius): the
    contact set of a detection pass is kept while no sample moved by more than half of it
    (simulate_contacts.py); 0 detects every step.  reuse_rotation (rad, 0: off): a Super-Helix groom at rest
    (static head; no element turned by more than this since the last assembly) keeps that assembly's
    factorised Mhat, A, dF/dq generators, contacts and H (Simulator._at_rest_system; no M; only the strands that
    moved are assembled again: _partial_assembly).  solver, solver_tolerance, max_sweeps, solver_symmetric and
    solver_anderson: the Coulomb solve of each step (solver_symmetric: forward + backward sweeps; solver_anderson:
    the Anderson memory, 0 none).
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
    detection_skin: float | None = None
    solver: str = "auto"
    # the Coulomb solve of each step (docs/simulation.md section 3): 1e-6 of the largest free reaction moves a
    # node by ~h 1e-6 |b|max per step (the README example's inverted run drifts 5.1e-9 m over 1 s at 1e-6 and
    # 4.5e-9 m at 1e-8), and 1e-8 cost its sagging run hundreds of sweeps per step; no Anderson acceleration
    # (it cycles on the Coulomb law's stick/slip switches: the cold first step took 750 sweeps to 1e-6 with it,
    # 500 without); forward sweeps: the sagging run in 175 s CPU with 43 steps out of budget, symmetric ones
    # 233 s with 56; since the Coulomb cluster Newton steps (docs/solvers.md section 13) 79 s with none
    # (bench/results/simulate.md, docs/simulation.md section 6)
    solver_tolerance: float = 1e-6
    max_sweeps: int = 500  # the contact solver's sweep budget per step (a step that runs out is counted, with its residual)
    solver_symmetric: bool = False
    solver_anderson: int = 0
    refresh_warm_start: bool = True  # one sweep from an accepted warm start (solve_contacts)
    keep_step_corrections: bool = True  # reuse a modified strand's step-matrix correction (factor_step_matrix)
    # a groom at rest (every element within reuse_rotation rad of its orientation at the last assembly) keeps
    # that assembly's step matrices, contact set and H; F(q), K (q - q0), the right-hand side and the contact
    # solve are new every step (AtRestSystem; 0: assemble every step)
    reuse_rotation: float = 1e-7
    # a strand at rest keeps its contacts, their H rows and w while no element turned by more than this since they were
    # made (rad; None: reuse_rotation / 100); then a partial step makes them anew (Simulator._partial_contacts).  Kept
    # as long as the dynamics (reuse_rotation), the contacts of a creeping inverted groom let it creep faster: on
    # harolongo every step from the 39th reassembled strands, 190 a step by the 120th (15,624 strand assemblies
    # instead of 35); made anew at reuse_rotation / 10 its 240 steps took 316 s CPU, drift 2.3e-6 m, at / 100 280 s,
    # 1.1e-6 m (docs/simulation.md section 2)
    contact_rotation: float | None = None
    # Super Space Clothoids: compute their velocity terms A (dyn.clothoid_velocity_terms: exact, by complex steps,
    # 80-170 ms per step on 5-strand USC styles, 2-4x M and dF/dq); off: dropped (exact at rest)
    clothoid_velocity_terms: bool = False

    def __post_init__(self):
        if self.contacts not in CONTACT_MODES:
            raise ValueError(f"contacts must be one of {CONTACT_MODES}, got {self.contacts!r}")
        if not (self.dt > 0 and np.isfinite(self.dt)):
            raise ValueError(f"dt must be > 0, got {self.dt}")
        for name in ("mass_damping", "stiffness_damping", "air_drag", "push_rate", "max_push_speed"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not (self.reuse_rotation >= 0):
            raise ValueError(f"reuse_rotation must be >= 0, got {self.reuse_rotation}")
        if self.contact_rotation is not None and not (self.contact_rotation >= 0):
            raise ValueError(f"contact_rotation must be >= 0, got {self.contact_rotation}")
        if self.detection_skin is not None and not (self.detection_skin >= 0):
            raise ValueError(f"detection_skin must be >= 0, got {self.detection_skin}")
        if not (self.rotational_inertia_scale > 0):
            raise ValueError("rotational_inertia_scale must be > 0")
        if self.max_sweeps < 1:
            raise ValueError(f"max_sweeps must be >= 1, got {self.max_sweeps}")


rename_field(SimulationParams, "max_iterations", "max_sweeps")  # deprecated name (before issue 18)


# --------------------------------------------------------------------------- state and results
@dataclass
class State:
    """Time (s), curvatures q and rates v = qdot, (S, N, 3) padded like the helix."""

    time: float
    curvatures: np.ndarray
    rates: np.ndarray


@dataclass
class StepSystem:
    """One step up to the contact problem (exposed for tests): the Cholesky factors of Mhat per strand
    (simulate_linalg.StrandFactors, a buffer the next step overwrites), the free rates v_free (S, N, 3),
    contacts, H, the solver-scaled ContactProblem (r = r_scale r~, u = u_scale u~), and the geometry it
    was built on."""

    helix: sh.SuperHelix
    kin: sh.Kinematics
    factors: StrandFactors
    v_free: np.ndarray
    contacts: object = None
    H: object = None
    problem: object = None
    r_scale: float = 1.0
    u_scale: float = 1.0
    r0: np.ndarray | None = None
    w: np.ndarray | None = None  # (3m,) the contact velocities that do not depend on v' (moving head, -ubar)
    stats: dict = field(default_factory=dict)
    # per strand the dofs its contacts move (k_s) and its block (Mhat_s^-1)[:k_s, :k_s] of the problem's D (views; a
    # partial step writes the blocks of the strands it refactors over them, as it overwrites their factors)
    leading: tuple | None = None


@dataclass
class AtRestSystem:
    """What a step at rest keeps from the last full assembly (Simulator._at_rest_system): the curvatures it was
    built at, its velocity terms A, the generators of its dF/dq (what Mhat holds besides M, with K and the kept
    unstable-mode corrections: no mass matrix is kept) and its system (factors, contacts, H, the contact
    problem's W; not its helix, kinematics and free rates, None there)."""

    curvatures: np.ndarray
    velocity_terms: np.ndarray | None  # A (S, N, 3), None: dropped
    gravity_parts: tuple | None  # (U, G, Dg) of superhelix.gravity_force_jacobian_parts, None: explicit gravity
    system: StepSystem


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
    """Steps Super-Helices (or Super Space Clothoids: a cl.SuperClothoid ``helix``, nodal (S, N + 1, 3) curvatures,
    rest and rates, ``stiffness`` as banded (diagonal, off-diagonal) blocks) forward in time (module docstring).

    helix: the initial configuration (q and root); rest_curvatures q0 (S, N, 3); material; gravity (3,);
    head: a trimesh.Trimesh or None; head_motion: None (static) or t -> (R (3,3), T (3,)) mapping the
    initial pose to the pose at time t (roots and head follow it); initial_rates (S, N, 3) or None;
    stiffness: K (S, N, 3) instead of the material's (e.g. per-strand materials); warm_start: (contacts,
    forces (m, 3) in N) known at the start, e.g. the inversion's: the first contact solve starts from
    r = h * forces on the contacts that match (an inverted groom's first step is then solved before
    any sweep).  external_force: a constant generalized force (S, N, 3) added to F (groom check's
    subsets: the inversion's forces of the strands left out).

    Jobs: head and root motion (simulate_motion.HeadMotion), contacts kept, detected and warm-started
    (simulate_contacts.ContactTracker), per-strand linear algebra (simulate_linalg); this class holds
    the state and does the step: dynamics, step matrix, contact problem, solve, integration.
    """

    def __init__(self, helix: sh.SuperHelix, rest_curvatures, material: Material, gravity, head=None,
                 params: SimulationParams | None = None, head_motion: Callable | None = None,
                 initial_rates=None, stiffness=None, warm_start=None, external_force=None):
        self.params = params or SimulationParams()
        self.clothoid = isinstance(helix, cl.SuperClothoid)  # Super Space Clothoids: nodal dofs (module docstring)
        if self.clothoid and head_motion is not None:
            raise NotImplementedError("a moving head is not supported for Super Space Clothoids (the inertial "
                                      "forces of a moving root are not in their velocity terms)")
        self.material = material
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.head = head
        self.motion = HeadMotion(helix.root_positions, helix.root_frames, head_motion)
        self.head_motion = head_motion
        self.rest = np.asarray(rest_curvatures, dtype=np.float64).reshape(helix.curvatures.shape)
        self.lengths = helix.lengths
        self.n_elements = helix.n_elements
        self.inertia = dyn.Inertia.from_material(material, self.params.rotational_inertia_scale)
        if self.clothoid:  # K block tridiagonal, banded (diagonal blocks (S, N + 1, 3), off-diagonal (S, N, 3))
            self.K = _clothoid_stiffness(helix, material, stiffness)
        elif stiffness is None:
            self.K = sh.stiffness(helix, material.stiffness_diag)
        else:
            self.K = np.asarray(stiffness, dtype=np.float64)
            if self.K.shape != helix.curvatures.shape:
                raise ValueError(f"stiffness must have shape {helix.curvatures.shape} (S, N, 3), got {self.K.shape}")
        self.mask = helix.node_mask if self.clothoid else helix.element_mask
        self._dof_blocks = self.n_elements + 1 if self.clothoid else self.n_elements  # 3-dof blocks per strand
        self.external = None if external_force is None else np.asarray(external_force, dtype=np.float64).reshape(
            helix.curvatures.shape)
        rates = np.zeros_like(helix.curvatures) if initial_rates is None else np.asarray(initial_rates, float)
        self.state = State(0.0, helix.curvatures.copy(), rates * self.mask[..., None])
        self.friction = material.friction if self.params.friction is None else self.params.friction
        self.timings: dict[str, float] = {}
        self.modified_strands = 0  # strand-steps whose step matrix was modified (factor_step_matrix)
        self.clamped_strands = 0  # strand-steps whose rates were scaled down (_limit_rotation)
        self._corrections = StepCorrections(helix.n_strands) if self.params.keep_step_corrections else None
        self._factors = None  # the step's Cholesky factors (StrandFactors), overwritten by the next step
        self._at_rest: AtRestSystem | None = None  # the last assembly, while the groom stays at rest
        self._kept = None  # (A, dF/dq generators) of the assembly under way, for _at_rest (_keeps_assembly)
        self._contacts_at = None  # per strand the curvatures its contacts were made at (_stale_contacts)
        self._last_solve = None  # (contacts, r_scale, r~) of the last contact solve (solve_contacts)
        self.reused_steps = 0  # steps that reused the last assembly (_at_rest_system)
        self.partial_steps = 0  # steps at rest that assembled only the strands that moved (_partial_assembly)
        self.partial_strands = 0  # strands assembled by those steps, summed
        self.refreshed_strands = 0  # strands whose contacts partial steps made anew, summed (_partial_contacts)
        self._chunks = strand_chunks(self._dof_blocks)
        self._geometry = None  # (state, helix, kinematics) of the last state asked for (geometry())
        self._contacts_on = self.params.contacts == "all" or (self.params.contacts == "head" and head is not None)
        self._radius = self.params.contact_radius
        self.tracker: ContactTracker | None = None
        if self._contacts_on:
            from .contact import DEFAULT_CONTACT_RADIUS, as_head_surface

            if self._radius is None:
                self._radius = DEFAULT_CONTACT_RADIUS
            warm = None
            if warm_start is not None and len(warm_start[1]):
                forces = np.asarray(warm_start[1], dtype=np.float64).reshape(-1, 3)
                warm = (warm_start[0], forces * self.params.dt)
            surface = as_head_surface(head) if head is not None else None
            self.tracker = ContactTracker(self.params, self._radius, surface, self.motion, self.lengths,
                                          helix.element_mask, warm_start=warm)
            t0 = time.perf_counter()
            self.tracker.detect_initial(self.helix())
            self._time("detect", t0)

    # ---------------------------------------------------------------- geometry
    @property
    def velocity_terms(self) -> bool:
        """Whether A(q, qd) is computed: params.velocity_terms, and for clothoids params.clothoid_velocity_terms too."""
        return bool(self.params.velocity_terms) and (not self.clothoid or bool(self.params.clothoid_velocity_terms))

    @property
    def model(self):
        """The rod model's module: rods.clothoid or rods.superhelix (sample, kinematics, gravity_potential)."""
        return cl if self.clothoid else sh

    def helix(self, state: State | None = None) -> sh.SuperHelix:
        """The strands at ``state`` (default: the current one), roots where the head puts them."""
        state = state or self.state
        pose = self.motion.pose(state.time)
        rod = cl.SuperClothoid if self.clothoid else sh.SuperHelix
        return rod(pose.roots, pose.frames, self.lengths, state.curvatures, self.n_elements)

    def geometry(self) -> tuple[sh.SuperHelix, sh.Kinematics]:
        """The strands at the current state and their kinematics, computed once per state (the step that follows a
        state's tips and frames uses the same).  Super-Helices only."""
        if self._geometry is None or self._geometry[0] is not self.state:
            self._geometry = None  # the last state's kinematics released before the new ones are computed
            helix = self.helix()
            self._geometry = (self.state, helix, sh.kinematics(helix))
        return self._geometry[1], self._geometry[2]

    def contact_radius(self) -> float | None:
        return self._radius

    # ---------------------------------------------------------------- one step
    def _time(self, name: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.timings[name] = self.timings.get(name, 0.0) + t1 - t0
        return t1

    def assemble(self) -> StepSystem:
        """Dynamics, factorisation, free rates, contacts and the scaled contact problem of the next step."""
        st = self.state
        t0 = time.perf_counter()
        pose = self.motion.pose(st.time)
        if self._at_rest is not None:
            moved = self._moved_strands(pose)
            if moved is not None:
                refresh = moved | self._stale_contacts()
                if not refresh.any():
                    return self._at_rest_system(st, pose, t0)
                if not moved.all() and self._corrections is not None:
                    return self._partial_assembly(st, pose, t0, moved, refresh)
            self._at_rest = None
        dynamics = self._clothoid_dynamics if self.clothoid else self._helix_dynamics
        helix, kin, v_free, t0 = dynamics(st, pose, t0)
        system = self._contact_system(StepSystem(helix=helix, kin=kin, factors=self._factors, v_free=v_free), pose, t0)
        self._contacts_at = st.curvatures.copy() if self._contacts_on else None
        if self._kept is not None:
            kept_all = self._corrections is not None or np.all(self._factors.correction_kept)
            if kept_all:  # without its geometry and free rates (a step at rest has its own; ~0.45 GB on harolongo)
                self._at_rest = AtRestSystem(st.curvatures.copy(), *self._kept,
                                             replace(system, helix=None, kin=None, v_free=None, stats={}))
            self._kept = None
        return system

    def _keeps_assembly(self, pose) -> bool:
        """Whether this assembly is kept for the steps at rest after it: params.reuse_rotation on, a static head,
        Super-Helices (what is kept is small: A and the generators of dF/dq, O(N) per strand)."""
        return bool(self.params.reuse_rotation > 0) and not pose.moving and not self.clothoid

    def _step_scales(self) -> dict:
        """a_scale, k_scale, b_scale of Mhat = a M + k K + b dF/dq (+ C): 1 + h alpha, h^2 + h beta, -h^2 (0 with
        explicit gravity); alpha = mass damping + air drag / rhoS, beta = stiffness damping."""
        p = self.params
        h = p.dt
        alpha = p.mass_damping + p.air_drag / self.inertia.linear
        return {"a_scale": 1.0 + h * alpha, "k_scale": h * h + h * p.stiffness_damping,
                "b_scale": -h * h if p.implicit_gravity else 0.0}

    def _moved_strands(self, pose) -> np.ndarray | None:
        """Per strand, whether an element has turned by reuse_rotation or more since the strand's last assembly (an
        element's frame turns by at most sum_j l_j |dq_j| over the elements j up to it, dq the curvature change
        since then); None with a moving head.  A groom in motion moves every strand the step after an assembly
        (h sum_j l_j |v_j| >= reuse_rotation); one at rest may vibrate at round-off amplitude (the README example's
        inverted groom: 1e-7 rad a step back and forth) without moving any, and a few creeping strands move alone
        (_partial_assembly)."""
        if pose.moving:
            return None
        dq = self.state.curvatures - self._at_rest.curvatures
        turned = np.einsum("sn,sn->s", self.lengths, np.sqrt(np.einsum("snk,snk->sn", dq, dq)))
        return turned >= self.params.reuse_rotation

    def _stale_contacts(self) -> np.ndarray:
        """Per strand, whether an element has turned by contact_rotation or more since the strand's contacts were last
        made (contacts, H rows, w: _contact_system, _partial_contacts)."""
        S = self.lengths.shape[0]
        if self._contacts_at is None or self._at_rest.system.problem is None:
            return np.zeros(S, dtype=bool)
        tau = self.params.contact_rotation
        tau = 0.01 * self.params.reuse_rotation if tau is None else tau
        dq = self.state.curvatures - self._contacts_at
        turned = np.einsum("sn,sn->s", self.lengths, np.sqrt(np.einsum("snk,snk->sn", dq, dq)))
        return turned >= tau

    def _partial_assembly(self, st: State, pose, t0: float, moved: np.ndarray, refresh=None) -> StepSystem:
        """A groom at rest but for the strands ``moved`` (_moved_strands): those get a new M, A, dF/dq generators and
        factorised Mhat (their kept A, generators and curvatures are replaced), the others keep theirs; the free
        rates of all from the kept parts as at rest (_free_rates_kept: exact for a strand whose Mhat, A and dF/dq
        are of one configuration, new or kept), then the contacts of the strands ``refresh`` (``moved`` and those whose
        contacts went stale, _stale_contacts; ``moved`` may be empty) are made anew, the others' kept
        (_partial_contacts).  A full assembly would redo M and Mhat of every strand (harolongo: ~7 s of a step) for one that
        crept by 1e-7 rad."""
        p = self.params
        kept = self._at_rest
        helix, kin = self.geometry()
        refresh = moved if refresh is None else refresh
        if p.implicit_gravity and moved.any():  # the moved strands' generators, into the kept ones (the others keep theirs)
            moved_ids = np.flatnonzero(moved)
            sub = helix.subset(moved_ids)
            n = sub.max_elements
            for old, new in zip(kept.gravity_parts, sh.gravity_force_jacobian_parts(
                    sub, self.inertia.linear, self.gravity, sh.kinematics(sub))):
                old[moved_ids] = 0.0
                old[moved_ids, :n] = new
        t0 = self._time("dynamics", t0)
        for a, b in self._chunks:
            ids = np.flatnonzero(moved[a:b]) + a
            for run in np.split(ids, np.flatnonzero(np.diff(ids) != 1) + 1) if len(ids) else ():
                r0, r1 = int(run[0]), int(run[-1]) + 1  # consecutive moved strands
                mass, A = dyn.inertia_generators(helix, self.inertia, kin, rates=st.rates if kept.velocity_terms is not
                                                 None else None, order=p.quadrature_order,
                                                 root_motion=pose.root_motion, strands=(r0, r1))
                Nc = mass.diag.shape[1]
                if kept.velocity_terms is not None:
                    kept.velocity_terms[r0:r1] = 0.0
                    kept.velocity_terms[r0:r1, :Nc] = A
                kept.curvatures[r0:r1] = st.curvatures[r0:r1]
                t0 = self._time("dynamics", t0)
                dF = tuple(x[r0:r1, :Nc] for x in kept.gravity_parts) if p.implicit_gravity else None
                modified = factor_step_generators(mass, dF, gravity_jacobian_left(self.inertia.linear, self.gravity),
                                                  self.n_elements[r0:r1], self._corrections,
                                                  stiffness=self.K[r0:r1, :Nc], out=self._factors, first=r0,
                                                  **self._step_scales())
                self.modified_strands += modified
                t0 = self._time("factor", t0)
        v_free = self._free_rates_kept(st, helix, kin)
        self.partial_steps += 1
        self.partial_strands += int(np.count_nonzero(moved))
        t0 = self._time("factor", t0)
        system = self._partial_contacts(StepSystem(helix=helix, kin=kin, factors=self._factors, v_free=v_free), pose, t0,
                                        moved, refresh)
        self._at_rest = AtRestSystem(kept.curvatures, kept.velocity_terms, kept.gravity_parts,
                                     replace(system, helix=None, kin=None, v_free=None, stats={}))
        return system

    def _free_rates_kept(self, st: State, helix, kin) -> np.ndarray:
        """v_free = v + Mhat^-1 (h (F - K (q - q0) - A) - (Mhat - M) v) from the kept A, dF/dq generators, corrections
        and factors (_at_rest_system)."""
        p = self.params
        h = p.dt
        kept = self._at_rest
        force = sh.gravity_force(helix, self.inertia.linear, self.gravity, kin) - self.K * (st.curvatures - self.rest)
        if self.external is not None:
            force = force + self.external
        if kept.velocity_terms is not None:
            force = force - kept.velocity_terms
        S, N = self.lengths.shape
        rhs = h * force - step_difference_apply(self._factors, self._corrections, st.rates, stiffness=self.K,
                                                gravity_parts=kept.gravity_parts, **self._step_scales())
        rhs = rhs.reshape(S, 3 * N)
        rhs[~np.repeat(self.mask, 3, axis=1)] = 0.0
        return st.rates + self._factors.solve(rhs).reshape(S, N, 3)

    def _at_rest_system(self, st: State, pose, t0: float) -> StepSystem:
        """A step at rest (no strand moved: _moved_strands): the kept A, factorised Mhat, dF/dq generators, contacts
        and H of the last assembly, with this step's F(q), K (q - q0) and rates.
        v_free = Mhat^-1 (M v + h (F - K (q - q0) - A)) written without M (none is kept, so any groom can reuse,
        harolongo's 1-3 GB of mass matrices included):

            v_free = v + Mhat^-1 (h (F - K (q - q0) - A) - (Mhat - M) v),

        (Mhat - M) v from K, the dF/dq generators and the kept corrections (simulate_linalg.step_difference_apply).
        b = H v_free + w.  Exact up to the change of M, A, Mhat and H over reuse_rotation (relative ~1e-7)."""
        kept = self._at_rest.system
        helix, kin = self.geometry()
        v_free = self._free_rates_kept(st, helix, kin)
        system = StepSystem(helix=helix, kin=kin, factors=kept.factors, v_free=v_free)
        self.reused_steps += 1
        t0 = self._time("at_rest", t0)
        system.contacts = kept.contacts
        if kept.contacts is not None:
            system.stats["contacts"] = len(kept.contacts.strand_a)
        if kept.problem is None:
            return system
        system.H, system.w = kept.H, kept.w
        b = kept.H @ helix.to_flat(v_free).ravel() + kept.w
        system.problem = kept.problem.with_free_velocity(b / kept.r_scale)
        system.r_scale, system.u_scale = kept.r_scale, kept.u_scale
        system.r0 = (self.tracker.initial_impulses(kept.contacts) / kept.r_scale).ravel()
        self._time("at_rest", t0)
        return system

    def _helix_dynamics(self, st: State, pose, t0: float):
        """Super-Helices: M and A (compiled), F and the generators of dF/dq, the factorised Mhat and the free rates."""
        p = self.params
        h = p.dt
        helix, kin = self.geometry()
        with_A = p.velocity_terms or pose.moving
        F = sh.gravity_force(helix, self.inertia.linear, self.gravity, kin)
        parts = (sh.gravity_force_jacobian_parts(helix, self.inertia.linear, self.gravity, kin)
                 if p.implicit_gravity else None)
        S, N = self.lengths.shape
        force = F - self.K * (st.curvatures - self.rest)
        if self.external is not None:
            force = force + self.external
        rhs = np.zeros((S, 3 * N))
        if self._factors is None:
            self._factors = StrandFactors(self._dof_blocks)
        keep = self._keeps_assembly(pose)
        A_all = np.zeros_like(st.curvatures) if keep and with_A else None
        t0 = self._time("dynamics", t0)
        # per chunk of strands (the dense path's M never holds a whole large groom): M's generators and A, then
        # rhs = M v + h (F - K (q - q0) - A) (M v in O(N)) and Mhat = (1 + h alpha) M + (h^2 + h beta) K - h^2 dF/dq
        # factorised from the generators (block semiseparable; dense where a strand needs an unstable-mode correction)
        left = gravity_jacobian_left(self.inertia.linear, self.gravity)
        for a, b in self._chunks:
            mass, A = dyn.inertia_generators(helix, self.inertia, kin, rates=st.rates if with_A else None,
                                             order=p.quadrature_order, root_motion=pose.root_motion, strands=(a, b))
            Nc = mass.diag.shape[1]
            n = 3 * Nc
            f = force[a:b, :Nc] if A is None else force[a:b, :Nc] - A
            rhs[a:b, :n] = (mass_apply(mass, st.rates[a:b, :Nc], self.n_elements[a:b]) + h * f).reshape(b - a, n)
            if A_all is not None and A is not None:
                A_all[a:b, :Nc] = A
            t0 = self._time("dynamics", t0)
            dF = tuple(x[a:b, :Nc] for x in parts) if parts is not None else None
            modified = factor_step_generators(mass, dF, left, self.n_elements[a:b], self._corrections,
                                              stiffness=self.K[a:b, :Nc], out=self._factors, first=a,
                                              **self._step_scales())
            self.modified_strands += modified
            t0 = self._time("factor", t0)
        rhs[~np.repeat(self.mask, 3, axis=1)] = 0.0
        v_free = self._factors.solve(rhs).reshape(S, N, 3)
        self._kept = (A_all, parts) if keep else None
        t0 = self._time("factor", t0)
        return helix, kin, v_free, t0

    def _clothoid_dynamics(self, st: State, pose, t0: float):
        """Super Space Clothoids (nodal dofs): M with the cross-section rotation (dyn.clothoid_mass_matrix), the
        velocity terms A only with params.clothoid_velocity_terms (dyn.clothoid_velocity_terms, Lagrange's equations
        by complex steps; else dropped: exact at rest), F and dF/dq (complex step), the block-tridiagonal K as each
        strand's dense block, the factorised Mhat and the free rates."""
        p = self.params
        h = p.dt
        helix = cl.SuperClothoid(pose.roots, pose.frames, self.lengths, st.curvatures, self.n_elements)
        kin = cl.kinematics(helix)
        F = cl.gravity_force(helix, self.inertia.linear, self.gravity, kin)
        S, N1 = st.curvatures.shape[:2]
        alpha = p.mass_damping + p.air_drag / self.inertia.linear
        force = F - self._stiffness_apply(st.curvatures - self.rest)
        if self.external is not None:
            force = force + self.external
        rhs = np.zeros((S, 3 * N1))
        if self._factors is None:
            self._factors = StrandFactors(self._dof_blocks)
        t0 = self._time("dynamics", t0)
        for a, b in self._chunks:
            M, dF, A = _clothoid_step_terms(helix, kin, np.arange(a, b), self.inertia, self.gravity,
                                            p.quadrature_order, p.implicit_gravity,
                                            st.rates if self.velocity_terms else None)
            n = M.shape[1]
            nodes = n // 3
            rhs[a:b, :n] = _chunk_rhs(M, A, force, st.rates, a, b, h)
            dF = M if dF is None else dF
            K = _banded_dense(self.K[0][a:b, :nodes], self.K[1][a:b, :nodes - 1])
            t0 = self._time("dynamics", t0)
            # a = (1 + h alpha) M + (h^2 + h beta) K (K not diagonal: passed inside a), b = -h^2 dF/dq
            _, modified = factor_step_matrix((1.0 + h * alpha) * M + (h * h + h * p.stiffness_damping) * K, dF,
                                             self._dof_blocks[a:b], self._corrections,
                                             b_scale=-h * h if p.implicit_gravity else 0.0, out=self._factors, first=a)
            self.modified_strands += modified
            t0 = self._time("factor", t0)
        rhs[~np.repeat(self.mask, 3, axis=1)] = 0.0
        v_free = self._factors.solve(rhs).reshape(S, N1, 3)
        t0 = self._time("factor", t0)
        return helix, kin, v_free, t0

    def _stiffness_apply(self, d: np.ndarray) -> np.ndarray:
        """K d: diagonal for the helix, the banded product for the clothoid."""
        if not self.clothoid:
            return self.K * d
        diag, off = self.K
        out = diag * d
        out[:, :-1] += off * d[:, 1:]
        out[:, 1:] += off * d[:, :-1]
        return out

    def _contact_system(self, system: StepSystem, pose, t0: float, refactored: np.ndarray | None = None) -> StepSystem:
        """Contacts (detected or kept), H and the scaled contact problem of the step (both models).  ``refactored``
        (a partial assembly): the strands whose Mhat is new; the others' D blocks may come from the kept problem."""
        st = self.state
        helix, kin = system.helix, system.kin
        if not self._contacts_on:
            return system

        speeds = (dyn.clothoid_node_speeds(helix, st.rates, kin) if self.clothoid
                  else dyn.strand_node_speeds(helix, st.rates, kin))
        margins = self.tracker.margins(speeds)
        contacts = self.tracker.contacts(helix, kin, st.time, margins)
        t0 = self._time("detect", t0)
        system.stats["contacts"] = len(contacts.strand_a)
        system.contacts = contacts
        if len(contacts.strand_a) == 0:
            return system
        from .contact.jacobian import contact_jacobian

        H = contact_jacobian(helix, contacts, kin)
        t0 = self._time("jacobian", t0)
        ubar = self.tracker.targets(contacts)
        w = np.zeros((len(ubar), 3))
        if pose.moving:  # both sides move rigidly with the head: v_a - v_b = Omega x (x_a - x_b)
            w = np.einsum("mij,mj->mi", contacts.frame, np.cross(pose.Omega, contacts.point_a - contacts.point_b))
        w[:, 0] -= ubar
        system.H = H
        self._build_problem(system, w.ravel(), refactored)
        self._time("contact_setup", t0)
        return system

    def _partial_contacts(self, system: StepSystem, pose, t0: float, moved: np.ndarray, refresh=None) -> StepSystem:
        """The contacts, H and contact problem of a partial step (_partial_assembly).  ``refresh``: the strands whose
        contacts are made anew (default ``moved``): those ``moved`` (refactored) and those whose contacts turned by
        params.contact_rotation since they were made (_stale_contacts).  The contacts of the other strands (neither
        side in ``refresh``) keep their kept rows: the contact record, its H row and w, its r0 from the last step, and
        its part of W (diagonal block, the blocks W_ij between two such contacts, the packed H D panels:
        ContactProblem.carry_cache) where its strands keep their D blocks.  Only the contacts that touch a strand of
        ``refresh`` are found again (ContactTracker.contacts_of: the kept strand/strand candidates with a side there,
        revisited; those strands' head contacts; their persistent ones), their H rows computed on the strands involved
        alone (contact_jacobian_part), their w from their gaps; the D blocks of the moved strands and of those whose
        contacts now reach other dofs are new (_build_problem), every block of W with a new contact is computed.
        b = H v_free + w for all.

        For the other strands this is the approximation of a step at rest (_at_rest_system): their contacts, H rows and
        w are those of a configuration within contact_rotation of the current one.  With those strands exactly where
        they were the contacts, H, w, b and W are a full assembly's (_contact_system) to round-off, the kept contacts
        first (tests/test_simulate_partial.py).  Where the kept strand/strand candidates cannot serve (ContactTracker.
        contacts_of), all contacts are made anew (_full_contacts)."""
        kept = self._at_rest.system
        refresh = moved if refresh is None else refresh
        if not self._contacts_on or kept.problem is None or kept.H is None or self.clothoid or pose.moving:
            return self._full_contacts(system, pose, t0, moved)
        from .contact import Contacts
        from .contact.jacobian import contact_jacobian_part

        st = self.state
        helix, kin = system.helix, system.kin
        margins = self.tracker.margins(dyn.strand_node_speeds(helix, st.rates, kin))
        moved_ids = np.flatnonzero(refresh)
        slack = 2.0 * self.params.reuse_rotation * float(np.max(helix.strand_lengths, initial=0.0))
        new = self.tracker.contacts_of(helix, kin, st.time, margins, moved_ids, slack)
        if new is None:
            return self._full_contacts(system, pose, t0, moved)
        self._contacts_at[moved_ids] = st.curvatures[moved_ids]
        self.refreshed_strands += len(moved_ids)
        stay = np.flatnonzero(~touching(kept.contacts, moved_ids, helix.n_strands))
        radius = new.radius
        old = kept.contacts.subset(stay)
        old.radius = new.radius = None
        contacts = Contacts.concatenate([old, new])
        contacts.radius = radius
        t0 = self._time("detect", t0)
        system.stats["contacts"] = len(contacts.strand_a)
        system.contacts = contacts
        if len(contacts.strand_a) == 0:
            return system
        parts = [kept.H[(3 * stay[:, None] + np.arange(3)).ravel()]]
        if len(new.strand_a):
            involved = np.union1d(new.strand_a, new.strand_b[new.strand_b >= 0])
            part, part_kin = strand_part(helix, kin, involved)
            parts.append(contact_jacobian_part(part, part_kin, new, involved, helix.flat_offsets()))
        system.H = sp.vstack(parts, format="csr")
        t0 = self._time("jacobian", t0)
        w = np.zeros((len(contacts.strand_a), 3))
        w[:len(stay)] = kept.w.reshape(-1, 3)[stay]
        w[len(stay):, 0] = -self.tracker.targets(new)
        self._build_problem(system, w.ravel(), moved, np.concatenate([stay, np.full(len(new.strand_a), -1)]))
        self._time("contact_setup", t0)
        return system

    def _full_contacts(self, system: StepSystem, pose, t0: float, moved: np.ndarray) -> StepSystem:
        """A partial step's contacts all made anew (_contact_system)."""
        if self._contacts_at is not None:
            self._contacts_at[:] = self.state.curvatures
        return self._contact_system(system, pose, t0, refactored=moved)

    def _build_problem(self, system: StepSystem, w: np.ndarray, refactored: np.ndarray | None = None,
                       kept_rows: np.ndarray | None = None) -> None:
        """The contact problem u~ = W r~ + b~ with W = H Mhat^-1 H^T (dense Mhat^-1 blocks only for the
        strands in contact, and of those only on the dofs up to their farthest contact's element), in
        impulse units r = r_scale r~, u = r_scale u~ (the block Gauss-Seidel normalises every local
        problem, so W needs no scaling)."""
        from .solvers import ContactProblem

        helix = system.helix
        # a contact that no dof can move (at the clamped root) transmits nothing: dropped; the problem on the dofs
        # the contacts move: strand s's first k_s (a contact on element e moves the dofs of elements 0..e only),
        # with D_s = (Mhat_s^-1)[:k_s, :k_s] (StrandFactors.leading_inverse)
        moved = moved_dofs(system.H, 3 * helix.flat_offsets())
        if moved is None:
            return
        keep, H, k, H_moved = moved
        if not np.all(keep):
            system.contacts = system.contacts.subset(keep)
            system.H = H
            w = w.reshape(-1, 3)[keep].ravel()
            kept_rows = kept_rows[keep] if kept_rows is not None else None
        system.w = w
        b = H @ helix.to_flat(system.v_free).ravel() + w
        touched = np.flatnonzero(k > 0)
        # a partial assembly: a strand whose Mhat was kept has the kept problem's block where its contacts move as many
        # dofs (the same factor, the same k), or its leading part where they move fewer ((Mhat^-1)[:k, :k] of the kept
        # (Mhat^-1)[:k', :k']): taken from there instead of inverted again
        kept = self._at_rest.system.leading if refactored is not None and self._at_rest is not None else None
        same = np.zeros(len(k), dtype=bool)  # strands whose D block is the kept one as it is
        blocks = []
        for s in touched:
            if kept is not None and not refactored[s] and s in kept[1] and kept[0][s] >= k[s]:
                same[s] = kept[0][s] == k[s]
                blocks.append(kept[1][s] if same[s] else kept[1][s][:k[s], :k[s]])
            elif kept is not None and s in kept[1] and kept[0][s] == k[s]:
                # a refactored strand's new block written over its kept one (the same size): the D storage stays
                # shared (ContactProblem.from_dense_blocks(like=)), as the factors are, which every step overwrites
                # (harolongo: no copy of its 185 MB of D blocks for the few strands a partial step refactors)
                kept[1][s][...] = system.factors.leading_inverse(s, int(k[s]))
                blocks.append(kept[1][s])
            else:
                blocks.append(system.factors.leading_inverse(s, int(k[s])))
        g = float(np.linalg.norm(self.gravity))
        r_scale = self.inertia.linear * float(np.mean(helix.strand_lengths)) * max(g * self.params.dt, 1e-3)
        mu = np.full(len(system.contacts.strand_a), self.friction)
        system.problem = ContactProblem.from_dense_blocks(H_moved, blocks, np.concatenate([[0], np.cumsum(k[touched])]),
                                                          0.0, b / r_scale, mu,
                                                          like=self._at_rest.system.problem if kept is not None else None)
        system.leading = (k, dict(zip(touched.tolist(), system.problem.D_blocks)))
        system.r_scale = system.u_scale = r_scale
        carried = None
        if kept_rows is not None:  # a partial step (_partial_contacts): W's cached parts of the kept contacts carried
            old = self._at_rest.system
            old_k = old.leading[0]
            old_touched = np.flatnonzero(old_k > 0)
            start = np.full(len(k), -1, dtype=np.int64)
            start[touched] = system.problem.dof_offsets[:-1]
            dof_strand = np.repeat(old_touched, old_k[old_touched])
            local = np.arange(old.problem.n_dofs) - np.repeat(old.problem.dof_offsets[:-1], old_k[old_touched])
            columns = np.where(same[dof_strand], start[dof_strand] + local, -1)
            a, bb = system.contacts.strand_a, system.contacts.strand_b
            rows = np.where(same[a] & ((bb < 0) | same[np.maximum(bb, 0)]), kept_rows, -1)
            system.problem.carry_cache(old.problem, rows, columns)
            carried = (old.contacts, kept_rows)
        system.r0 = (self.tracker.initial_impulses(system.contacts, carried) / r_scale).ravel()

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
        last = self._last_solve
        if last is not None and last[0] is system.contacts and last[1] == system.r_scale and len(last[2]) == len(r):
            # the same contact set as the last solve's (a step at rest): r0 is that solve's r~ times r_scale over
            # r_scale; its own r~ instead (the same to round-off), for which the problem (W kept) has v = D H^T r~
            r = last[2]
        iterations, status = 0, "warm_start"
        if p.refresh_warm_start:
            # one sweep from the warm start in any case: an accepted warm start is a force held constant, not a
            # constraint, and a strand held by dead loads alone can be unstable (the round-off drift then grows
            # until the residual exceeds the tolerance); the sweep re-imposes every contact's law on the current
            # b.  The solver's residuals (its history's first, of r0, and its last) are error(r0) and error(r1):
            # the same u, mu, rho and scale.
            res = solve_contact_problem(problem, law="coulomb", method="gs", tol=0.0, max_iter=1, r0=r,
                                        scale=scale)
            history = res.info.get("history")
            err = float(history[0][1]) if history else error(r)
            if err <= p.solver_tolerance:
                if float(res.residual) <= p.solver_tolerance:
                    r, err, iterations, status = np.asarray(res.r), float(res.residual), 1, "warm_start_swept"
            else:  # the solve goes on from the sweep's output (the same first sweep it would take)
                r, err, iterations = np.asarray(res.r), float(res.residual), 1
        else:
            err = error(r)
        if not err <= p.solver_tolerance:
            res = solve_contact_problem(problem, law="coulomb", method=p.solver, tol=p.solver_tolerance,
                                        max_iter=max(1, p.max_sweeps - iterations), r0=r, scale=scale,
                                        symmetric=p.solver_symmetric, anderson=p.solver_anderson,
                                        quick_check=QUICK_CHECK, check_every=SOLVE_CHECK_EVERY,
                                        cluster=SOLVE_CHECK_EVERY)
            r, status = np.asarray(res.r), str(res.status)
            iterations += int(res.iterations)
            err = float(res.residual)
        if self.clothoid:
            r, err, status = _polish_sticking(problem, r, err, error, status)
        self._last_solve = (system.contacts, system.r_scale, np.asarray(r, dtype=np.float64).reshape(-1))
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
            v = v + system.factors.solve(gen.reshape(S, -1)).reshape(v.shape)
        v = self._limit_rotation(v * self.mask[..., None])
        st = self.state
        self.state = State(st.time + self.params.dt, st.curvatures + self.params.dt * v, v)
        if self.tracker is not None:
            self.tracker.remember(system.contacts, impulses)
        self._time("update", t0)

    def _limit_rotation(self, v: np.ndarray) -> np.ndarray:
        """Safeguard: scale a strand's rates so that no element turns by more than max_rotation_per_step
        (rad: h |v_j| l_j) in one step.  Counted in ``clamped_strands``; never active near equilibrium."""
        bound = self.params.max_rotation_per_step
        if not bound:
            return v
        if self.clothoid:  # an element turns with the rates of its two nodes
            speed = np.linalg.norm(v, axis=-1)
            turn = self.params.dt * np.maximum(speed[:, :-1], speed[:, 1:]) * self.lengths
        else:
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
        """Tip positions (S, 3), of ``helix`` or of the current state."""
        if helix is None and not self.clothoid:
            helix, kin = self.geometry()
        else:
            helix = helix or self.helix()
            kin = cl.kinematics(helix, moments=False) if self.clothoid else sh.kinematics(helix)
        return kin.C[np.arange(helix.n_strands), helix.n_elements]

    def energies(self) -> dict:
        """Kinetic 1/2 v^T M v, elastic 1/2 (q - q0)^T K (q - q0) and gravity -rhoS g . int C ds, summed (J)."""
        helix = self.helix()
        kin = self.model.kinematics(helix)
        mass = dyn.clothoid_mass_matrix if self.clothoid else dyn.mass_matrix
        M = mass(helix, self.inertia, kin, self.params.quadrature_order)
        d = self.state.curvatures - self.rest
        return {"kinetic": float(dyn.kinetic_energy(M, self.state.rates).sum()),
                "elastic": float(0.5 * np.sum(d * self._stiffness_apply(d))),
                "gravity": float(self.model.gravity_potential(helix, self.inertia.linear, self.gravity, kin).sum())}


# --------------------------------------------------------------------------- the one-call API
def simulate(helix: sh.SuperHelix, rest_curvatures, material: Material, gravity, head=None,
             seconds: float = 1.0, dt: float | None = None, contacts: str | None = None,
             frames_per_second: float | None = 24.0, samples_per_frame_element: int = 4,
             callback: Callable | None = None, progress=False,
             params: SimulationParams | None = None, head_motion: Callable | None = None,
             warm_start=None, stiffness=None, external_force=None) -> SimulationResult:
    """Simulate ``seconds`` of motion; frames of the sampled strands at ``frames_per_second`` (None: every
    step).  ``callback(simulator, system)`` is called after every step; ``warm_start``, ``stiffness`` and
    ``external_force`` as for Simulator.  ``params`` carries the options; ``dt`` and ``contacts``, when given, override
    its fields on a copy (the caller's params are never modified).  ``progress``: False, True (a bar)
    or a simulate_progress.StepProgress to report to.  Returns a SimulationResult."""
    from .simulate_progress import StepProgress

    params = SimulationParams() if params is None else params
    overrides = {k: v for k, v in (("dt", dt), ("contacts", contacts)) if v is not None}
    if overrides:
        params = replace(params, **overrides)
    dt = params.dt
    t_start = time.perf_counter()
    sim = Simulator(helix, rest_curvatures, material, gravity, head=head, params=params, head_motion=head_motion,
                    warm_start=warm_start, stiffness=stiffness, external_force=external_force)
    setup = time.perf_counter() - t_start
    steps = int(round(seconds / dt))
    every = 1 if not frames_per_second else max(1, int(round(1.0 / (frames_per_second * dt))))
    pts0, offsets, _, _ = sim.model.sample(sim.helix(), samples_per_frame_element)
    frames = [pts0]
    times = [0.0]
    tips = [sim.tips()]
    n_contacts, iterations, residuals, step_s = [], [], [], []
    failed_steps, failed_residuals = [], []
    own_bar = not isinstance(progress, StepProgress)
    reporter = StepProgress([("simulate", steps)], enabled=bool(progress)) if own_bar else progress
    blas_one_thread = threadpool_limits(1, user_api="blas")  # per-strand systems of 30-300 dofs: threads only wait
    try:
        for k in range(steps):
            t_step = time.perf_counter()
            system = sim.step()
            n_contacts.append(int(system.stats.get("contacts", 0)))
            if "solver_iterations" in system.stats:
                iterations.append(system.stats["solver_iterations"])
                residuals.append(system.stats["solver_residual"])
                if not system.stats["solver_converged"]:
                    failed_steps.append(k)
                    failed_residuals.append(system.stats["solver_residual"])
            if callback is None:
                system = None  # the last state's kinematics are not held while the new state's are computed
            tips.append(sim.tips())
            if (k + 1) % every == 0 or k + 1 == steps:
                h_now, kin_now = (sim.helix(), None) if sim.clothoid else sim.geometry()
                frames.append(sim.model.sample(h_now, samples_per_frame_element, kin=kin_now)[0])
                times.append(sim.state.time)
            if callback is not None:
                callback(sim, system)
            system = None  # not held through the next step's assembly
            step_s.append(time.perf_counter() - t_step)
            reporter.step(step_s[-1])
    finally:
        blas_one_thread.restore_original_limits()
        if own_bar:
            reporter.close()
    total = time.perf_counter() - t_start
    timings = dict(sim.timings)
    later = step_s[1:] or step_s  # the first step may include compiling the kernels
    timings.update(setup=setup, total=total, steps=steps, first_step=step_s[0] if step_s else 0.0,
                   per_step=float(np.mean(later)) if later else 0.0)
    tracker = sim.tracker
    stats = {"contacts_per_step": n_contacts, "solver_iterations": iterations, "solver_residuals": residuals,
             "solver_failures": len(failed_steps), "failed_steps": failed_steps,
             "failed_residuals": failed_residuals, "contact_radius": sim.contact_radius(), "dt": dt,
             "seconds": steps * dt, "modified_step_matrices": sim.modified_strands,
             "rate_limited_strand_steps": sim.clamped_strands,
             "detection_passes": tracker.passes if tracker is not None else 0,
             "detection_reused": tracker.reused if tracker is not None else 0,
             "head_redetections": tracker.head_redetections if tracker is not None else 0,
             "steps_at_rest": sim.reused_steps,
             "steps_partially_assembled": sim.partial_steps,
             "strands_partially_assembled": sim.partial_strands,
             "strands_contacts_refreshed": sim.refreshed_strands,
             "model": "clothoid" if sim.clothoid else "superhelix",
             "velocity_terms": sim.velocity_terms}
    return SimulationResult(times=np.array(times), frames=np.stack(frames), offsets=offsets, tips=np.stack(tips),
                            final=sim.state, helix=sim.helix(), timings=timings, stats=stats)


def _chunk_rhs(M, A, force, rates, a: int, b: int, h: float) -> np.ndarray:
    """The right-hand side M v + h (f - A) of strands a..b-1 (M (chunk, n, n) on their first n = 3 N_c dofs; A None:
    no velocity terms); f = F - K (q - q0) (+ external)."""
    n = M.shape[1]
    Nc = n // 3
    f = force[a:b, :Nc] if A is None else force[a:b, :Nc] - A
    return np.einsum("sij,sj->si", M, rates[a:b, :Nc].reshape(b - a, n)) + h * f.reshape(b - a, n)


# --------------------------------------------------------------------------- Super Space Clothoid helpers
def _clothoid_stiffness(rod: cl.SuperClothoid, material: Material, stiffness):
    """The banded K (diagonal blocks (S, N + 1, 3), off-diagonal blocks (S, N, 3)) of the material, or ``stiffness``
    given in that form (e.g. the per-strand materials of groom check), checked."""
    if stiffness is None:
        return cl.stiffness(rod, material.stiffness_diag)
    diag, off = (np.asarray(x, dtype=np.float64) for x in stiffness)
    S, N = rod.lengths.shape
    if diag.shape != (S, N + 1, 3) or off.shape != (S, N, 3):
        raise ValueError(f"a clothoid's stiffness is banded: (diagonal (S, N + 1, 3), off-diagonal (S, N, 3)) = "
                         f"({(S, N + 1, 3)}, {(S, N, 3)}), got {diag.shape}, {off.shape}")
    return diag, off


def _banded_dense(diag: np.ndarray, off: np.ndarray) -> np.ndarray:
    """The dense (S, 3 n, 3 n) block-tridiagonal K from its banded blocks: diagonal (S, n, 3), off (S, n - 1, 3)
    (every block diagonal in the components, K = D (x) M_FE)."""
    S, n = diag.shape[:2]
    K = np.zeros((S, n, 3, n, 3))
    i = np.arange(n)
    c = np.arange(3)
    K[:, i[:, None], c[None, :], i[:, None], c[None, :]] = diag
    j = np.arange(n - 1)
    K[:, j[:, None], c[None, :], j[:, None] + 1, c[None, :]] = off
    K[:, j[:, None] + 1, c[None, :], j[:, None], c[None, :]] = off
    return K.reshape(S, 3 * n, 3 * n)


def _clothoid_part(rod: cl.SuperClothoid, kin, ids: np.ndarray):
    """Strands ``ids`` of a clothoid groom and their kinematics, trimmed to their largest element count (no
    recomputation: the arrays are gathered)."""
    n = max(int(rod.n_elements[ids].max(initial=1)), 1)
    sub = cl.SuperClothoid(rod.root_positions[ids], rod.root_frames[ids], rod.lengths[ids, :n],
                           rod.curvatures[ids, :n + 1], rod.n_elements[ids])
    el = {name: getattr(kin, name)[ids, :n] for name in ("Q", "p", "P", "Mphi", "MX", "MZ", "a", "b", "stats")}
    return sub, cl.Kinematics(sub, kin.C[ids, :n + 1], kin.R[ids, :n + 1], **el)


GROUP_RATIO = 1.25  # clothoid strands whose element counts are within this factor share one dense batch


def element_count_groups(n_elements: np.ndarray, ratio: float = GROUP_RATIO) -> list[np.ndarray]:
    """Positions of ``n_elements`` grouped by similar counts (sorted; a group's largest count <= ratio x its
    smallest, or + 1): the dense clothoid terms then cost about sum_g S_g N_g^3, not S max(N)^3 on the padding."""
    order = np.argsort(n_elements, kind="stable")
    groups, start = [], 0
    for k in range(1, len(order) + 1):
        smallest = n_elements[order[start]]
        if k == len(order) or n_elements[order[k]] > max(ratio * smallest, smallest + 1):
            groups.append(order[start:k])
            start = k
    return groups


def _clothoid_step_terms(rod: cl.SuperClothoid, kin, ids: np.ndarray, inertia, gravity, order: int,
                         implicit_gravity: bool, rates=None):
    """M (len(ids), n, n), dF/dq (or None) and the velocity terms A (len(ids), n / 3, 3) (None without ``rates``)
    of the strands ``ids``, n = 3 (their largest N + 1), computed per group of similar element counts
    (element_count_groups) on arrays trimmed to each group's N and scattered into the padded result (zero rows
    and columns beyond a strand's nodes, as the factorisation expects)."""
    n_el = rod.n_elements[ids]
    n = 3 * (max(int(n_el.max(initial=1)), 1) + 1)
    M = np.zeros((len(ids), n, n))
    dF = np.zeros((len(ids), n, n)) if implicit_gravity else None
    A = np.zeros((len(ids), n // 3, 3)) if rates is not None else None
    for group in element_count_groups(n_el):
        sub, sub_kin = _clothoid_part(rod, kin, ids[group])
        Mg = dyn.clothoid_mass_matrix(sub, inertia, sub_kin, order)
        m = Mg.shape[1]
        M[group, :m, :m] = Mg
        if implicit_gravity:
            dF[group, :m, :m] = cl.gravity_force_jacobian(sub, inertia.linear, gravity, sub_kin)
        if rates is not None:
            A[group, :m // 3] = dyn.clothoid_velocity_terms(sub, inertia, rates[ids[group], :m // 3], sub_kin, order)
    return M, dF, A


POLISH_MAX_ROWS = 3000  # sticking contact rows up to which _polish_sticking builds a dense W_SS
POLISH_RCOND = 1e-6  # singular values of W_SS below this fraction of the largest are left alone


def _polish_sticking(problem, r, err, error, status):
    """Super Space Clothoids: the sticking contacts' impulses made exact (u_S = 0 to round-off) by one least-squares
    correction, kept only when the law residual does not grow.

    Why: on a clothoid the contacts near the root all lie on the first element(s), whose two nodes they can hardly
    move apart (the rows of H there have singular values down to ~1e-5 of the largest), and the light zig-zag modes
    of the nodal curvatures (v_j = -v_{j+1}) are steered by the contact impulses' error in those weak directions.
    With the solver's tolerance (1e-8 of the weight impulse) that error fed back into a mode growing ~1.8x per step
    (a numerical instability: the stick-constrained strand and the step with exact impulses are stable, checked by
    their linearisations; measured on example_groom(4, seed=3) inverted at r_c = 0.5 mm: 2x per step from step 30,
    solves failing from step 41).  Applied to clothoids only: the Super-Helix path is unchanged.
    Sticking: r_N > 0 and |r_T| < mu r_N strictly; the correction is the minimum-norm least-squares solution of
    W_SS dr_S = -u_S over the well-determined directions of W_SS (singular values above POLISH_RCOND of the largest;
    W_SS may be singular: several contacts on one element).  The weak directions are left as the solver had them:
    corrected from round-off-level u they amplify noise (measured on that groom, 240 steps: cut-off 1e-13, 40 failed
    solves; 1e-10, 106; 1e-7 and 1e-5, none, tip drift 4e-13 and 2e-15 m)."""
    R = np.asarray(r, dtype=np.float64).reshape(-1, 3)
    tangential = np.linalg.norm(R[:, 1:], axis=1)
    stick = (R[:, 0] > 0.0) & (tangential < (1.0 - 1e-9) * problem.mu * R[:, 0])
    rows = np.flatnonzero(np.repeat(stick, 3))
    if len(rows) == 0 or len(rows) > POLISH_MAX_ROWS:
        return r, err, status
    u = problem.velocity(R.ravel())
    W = problem.assemble_W()[rows][:, rows].toarray()
    delta = np.linalg.lstsq(W, -u[rows], rcond=POLISH_RCOND)[0]
    candidate = R.ravel().copy()
    candidate[rows] += delta
    err_new = error(candidate)
    if err_new <= err:
        return candidate, err_new, status + "+polished"
    return r, err, status
