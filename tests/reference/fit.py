"""References for groomtool.fit: the numpy versions (vectorised over strands, elements or points)
that the fitting's numba kernels were ported from and reproduce, operation for operation; the tests
compare them bit for bit (with libm's arctan2, arcsin, sin, cos in the references: the functions the
kernels call; the frames to 1e-13, as numpy's 3x3 products go through BLAS).

helix: :func:`solve_helix_numpy`, :func:`solve_chain_numpy` (and the helpers ``_unit``, ``_F``,
:func:`cohelicity_defect`); state: :func:`assemble_numpy`, :func:`curve_table` (the CurveTable of any
SuperHelix); error: :func:`closest_distances_numpy`, :func:`strand_errors_numpy`,
:func:`evaluate_table`, and :func:`closest_distances` (the package's closest-point kernel ``_closest_s``
over any points, with :func:`locate`: the tests' entry to the kernel); sampling:
:func:`drop_repeated_vertices_numpy`, :func:`vertex_arc_lengths_numpy`, :func:`evaluate_numpy` (``PolylineCurves.evaluate``); cohelicity:
:func:`project_numpy`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from groomtool.fit.error import PRECHECK_STRIDE, _closest_s, _element_arrays
from groomtool.fit.helix import _TINY, ANTIPODAL_M, FLAT_D, NEAR_STRAIGHT_D, STRAIGHT_D, HelixSolution, helix_chord
from groomtool.fit.kernels import cross, dot, f123
from groomtool.fit.sampling import _kept
from groomtool.fit.state import CurveTable, root_frames
from groomtool.rods.superhelix import SuperHelix, kinematics


# ------------------------------------------------------------------------------------------ helix
def _unit(v):
    n = np.sqrt(dot(v, v))
    return v / np.maximum(n, _TINY)[..., None], n


def _F(phi, d, mb1, mb2, gamma):
    """F(phi) and F'(phi); m_a = a.m/2, m_e = e.m/2 with a' = e, e' = -a."""
    c, s = np.cos(phi), np.sin(phi)
    ma = c * mb1 + s * mb2
    me = c * mb2 - s * mb1
    h = np.arctan2(d, me)
    H = h * ma
    dh = d * ma / (d * d + me * me)
    dH = dh * ma + h * me
    F = np.arctan2(d, H) - gamma + phi
    dF = 1.0 - d * dH / (d * d + H * H)
    return F, dF


def solve_helix_numpy(t0, t1, chord, chord_tolerance=None, max_iter: int = 100) -> HelixSolution:
    """Reference for :func:`solve_helix`, vectorised over elements (numpy)."""
    t0, _ = _unit(np.asarray(t0, dtype=np.float64).reshape(-1, 3))
    t1, _ = _unit(np.asarray(t1, dtype=np.float64).reshape(-1, 3))
    chord = np.asarray(chord, dtype=np.float64).reshape(-1, 3)
    E = len(t0)
    phi_out = np.zeros((E, 3))
    length = np.zeros(E)
    iterations = np.zeros(E, dtype=np.int64)
    kind = np.zeros(E, dtype=np.int64)

    n, D = _unit(t1 - t0)
    d = 0.5 * D

    # ---- t1 == t0 to round-off: straight piece (planar arc), or one full turn about the chord
    ch, cl = _unit(chord)
    mh, _ = _unit(t0 + t1)
    along = dot(ch, mh) >= 1.0 - 5e-13          # chord within 1e-6 rad of the bisector
    arc = (d < STRAIGHT_D) & along
    if np.any(arc):
        phi_out[arc], length[arc] = _planar_arc(t0[arc], t1[arc], d[arc], cl[arc])
        kind[arc] = 1
    flat = (d < FLAT_D) & ~arc
    if np.any(flat):
        idx = np.nonzero(flat)[0]
        cos_a = dot(ch[idx], t0[idx])
        turn = cos_a > 1e-12
        kind[idx[turn]] = 2
        phi_out[idx[turn]] = 2.0 * np.pi * ch[idx[turn]]
        length[idx[turn]] = cl[idx[turn]] / cos_a[turn]
        kind[idx[~turn]] = 3
        length[idx[~turn]] = cl[idx[~turn]]

    # ---- general case
    gen = np.nonzero(~flat & ~arc)[0]
    if len(gen):
        t0g, t1g, cg, ng, dg = t0[gen], t1[gen], chord[gen], n[gen], d[gen]
        m = t0g + t1g
        c_pi = cg - dot(cg, ng)[:, None] * ng          # chord projected on Pi
        mh, mlen = _unit(m)
        anti = mlen < ANTIPODAL_M
        if np.any(anti):
            mh[anti], _ = _unit(c_pi[anti])
        b2 = mh
        b1 = cross(b2, ng)
        half_m = 0.5 * m
        mb1, mb2 = dot(half_m, b1), dot(half_m, b2)
        gamma = np.arctan2(dot(c_pi, b2), dot(c_pi, b1))
        if chord_tolerance is not None:
            budget = np.broadcast_to(np.asarray(chord_tolerance, dtype=np.float64), (E,))[gen]
            angle = budget / np.maximum(np.sqrt(dot(c_pi, c_pi)), _TINY)
            F0, _ = _F(np.zeros(len(gen)), dg, mb1, mb2, gamma)
            gamma = gamma + np.where(np.abs(F0) <= angle, F0, 0.0)
        lo, hi = gamma - np.pi, gamma.copy()
        # initial guess: the small-winding asymptote F ~ d^2 tan(phi) / (3 M^2) - (gamma - pi/2)
        M2 = np.maximum(1.0 - dg * dg, 0.0)
        x = np.arctan2(3.0 * M2 * (gamma - 0.5 * np.pi), dg * dg)
        x = np.where((x > lo) & (x < hi), x, gamma - 0.5 * np.pi)
        active = np.arange(len(gen))
        its = np.zeros(len(gen), dtype=np.int64)
        for _ in range(max_iter):
            if len(active) == 0:
                break
            xa, la, ha = x[active], lo[active], hi[active]
            F, dF = _F(xa, dg[active], mb1[active], mb2[active], gamma[active])
            neg = F < 0.0
            la = np.where(neg, xa, la)
            ha = np.where(neg, ha, xa)
            step = F / np.maximum(dF, _TINY)
            xn = xa - step
            tol = 2e-16 * (1.0 + np.abs(xa))
            done = (np.abs(step) <= tol) | (ha - la <= 2.0 * tol)
            outside = ~((xn > la) & (xn < ha)) & ~done
            xn = np.where(outside, 0.5 * (la + ha), xn)
            x[active], lo[active], hi[active] = xn, la, ha
            its[active] += 1
            active = active[~done]
        a = np.cos(x)[:, None] * b1 + np.sin(x)[:, None] * b2
        e = cross(ng, a)
        ma = dot(half_m, a)
        me = dot(half_m, e)
        h = np.arctan2(dg, me)
        phi_out[gen] = (2.0 * h)[:, None] * a
        length[gen] = np.sqrt(dot(c_pi, c_pi)) / np.sqrt(ma * ma + (dg / h) ** 2)
        iterations[gen] = its
        # nearly straight: keep the planar arc where its chord is closer to c than the helix's
        near = gen[(dg < NEAR_STRAIGHT_D) & along[gen]]
        if len(near):
            arc_phi, arc_length = _planar_arc(t0[near], t1[near], d[near], cl[near])
            better = (_chord_error(arc_phi, arc_length, t0[near], chord[near])
                      < _chord_error(phi_out[near], length[near], t0[near], chord[near]))
            idx = near[better]
            phi_out[idx], length[idx], kind[idx] = arc_phi[better], arc_length[better], 1
    return HelixSolution(phi_out, length, iterations, kind)


def _planar_arc(t0, t1, d, cl):
    """The minimal rotation (least twist): a planar arc of winding 2 asin(d), chord l sin(h)/h = |c|."""
    axis, _ = _unit(cross(t0, t1))
    h = np.arcsin(np.minimum(d, 1.0))
    return (2.0 * h)[:, None] * axis, cl / np.sinc(h / np.pi)


def _chord_error(phi, length, t0, chord):
    """|helix_chord(phi, length, t0) - chord|^2 per element."""
    e = helix_chord(phi, length, t0) - chord
    return e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1] + e[:, 2] * e[:, 2]


def cohelicity_defect(t0, t1, chord):
    """(P1 - P0) . (t1 - t0): zero iff the pair can be joined by a circular helix."""
    return dot(chord, np.asarray(t1) - np.asarray(t0))


def solve_chain_numpy(P, T, n_elements, chord_tolerance) -> HelixSolution:
    """Reference for :func:`solve_chain`: a loop over i, batched over strands (numpy)."""
    S, N1, _ = P.shape
    N = N1 - 1
    phi, lengths = np.zeros((S, N, 3)), np.zeros((S, N))
    its, kind = np.zeros((S, N), dtype=np.int64), np.zeros((S, N), dtype=np.int64)
    C = P[:, 0].copy()
    tol = np.broadcast_to(np.asarray(chord_tolerance, dtype=np.float64), (S,))
    for i in range(N):
        act = np.nonzero(i < n_elements)[0]
        sol = solve_helix_numpy(T[act, i], T[act, i + 1], P[act, i + 1] - C[act], tol[act])
        phi[act, i], lengths[act, i], its[act, i], kind[act, i] = sol.phi, sol.length, sol.iterations, sol.kind
        C[act] += helix_chord(sol.phi, sol.length, T[act, i])
    mask = np.arange(N)[None, :] < n_elements[:, None]
    return HelixSolution(phi[mask], lengths[mask], its[mask], kind[mask])



# ------------------------------------------------------------------------------------------ state
def rotation_matrices(phi) -> np.ndarray:
    """exp([Phi]x) = I + f1 [Phi]x + f2 [Phi]x^2 for phi (..., 3) -> (..., 3, 3)."""
    phi = np.asarray(phi, dtype=np.float64)
    x = dot(phi, phi)
    a, b, _ = f123(x)
    out = np.empty(phi.shape[:-1] + (3, 3))
    px, py, pz = phi[..., 0], phi[..., 1], phi[..., 2]
    out[..., 0, 0] = 1.0 + b * (px * px - x)
    out[..., 1, 1] = 1.0 + b * (py * py - x)
    out[..., 2, 2] = 1.0 + b * (pz * pz - x)
    out[..., 0, 1] = -a * pz + b * px * py
    out[..., 1, 0] = a * pz + b * px * py
    out[..., 0, 2] = a * py + b * px * pz
    out[..., 2, 0] = -a * py + b * px * pz
    out[..., 1, 2] = -a * px + b * py * pz
    out[..., 2, 1] = a * px + b * py * pz
    return out


def assemble_numpy(root_positions, root_tangents, phi, lengths, n_elements, frames=None):
    """Reference for :func:`assemble`, vectorised over strands (numpy)."""
    phi = np.asarray(phi, dtype=np.float64)
    lengths = np.asarray(lengths, dtype=np.float64)
    n_elements = np.asarray(n_elements, dtype=np.int64)
    S, N = lengths.shape
    R0 = root_frames(root_tangents) if frames is None else np.asarray(frames, dtype=np.float64).reshape(S, 3, 3)
    Q = rotation_matrices(phi)                                     # (S, N, 3, 3)
    R = np.empty((S, N + 1, 3, 3))
    R[:, 0] = R0
    for j in range(N):
        R[:, j + 1] = Q[:, j] @ R[:, j]
    safe_l = np.where(lengths > 0, lengths, 1.0)
    q = np.einsum("snba,snb->sna", R[:, :-1], phi) / safe_l[..., None]
    q[lengths <= 0] = 0.0
    helix = SuperHelix(root_positions, R0, lengths, q, n_elements)
    return helix, _table(helix, R[:, :-1, :, 0], phi, safe_l)


def _table(helix: SuperHelix, T, phi, safe_l) -> CurveTable:
    """Node positions by C_{j+1} = C_j + l_j (t_j + f2 Phi x t_j + f3 Phi x (Phi x t_j))."""
    S, N = helix.lengths.shape
    _, f2, f3 = f123(dot(phi, phi))
    pt = cross(phi, T)
    chord = helix.lengths[..., None] * (T + f2[..., None] * pt + f3[..., None] * cross(phi, pt))
    C = np.empty((S, N + 1, 3))
    C[:, 0] = helix.root_positions
    np.cumsum(chord, axis=1, out=C[:, 1:])
    C[:, 1:] += helix.root_positions[:, None]
    mask = helix.element_mask
    starts = helix.element_starts[:, :-1]
    return CurveTable(
        elem_offsets=helix.flat_offsets(),
        start=starts[mask], length=helix.lengths[mask],
        C=C[:, :-1][mask], T=T[mask], Omega=(phi / safe_l[..., None])[mask],
        strand_length=helix.strand_lengths,
    )


def curve_table(helix: SuperHelix) -> CurveTable:
    """The :class:`CurveTable` of any SuperHelix (node frames from superhelix.kinematics)."""
    kin = kinematics(helix)
    mask = helix.element_mask
    R = kin.R[:, :-1]
    omega_world = np.einsum("snab,snb->sna", R, helix.curvatures)
    return CurveTable(
        elem_offsets=helix.flat_offsets(),
        start=helix.element_starts[:, :-1][mask], length=helix.lengths[mask],
        C=kin.C[:, :-1][mask], T=R[..., 0][mask], Omega=omega_world[mask],
        strand_length=helix.strand_lengths,
    )



# ------------------------------------------------------------------------------------------ error
CHUNK = 1 << 17          # vertices per batch of closest-point queries


def locate(table: CurveTable, strand, s):
    """Element (global index) and local parameter of arc lengths s (clamped) on strands."""
    strand = np.asarray(strand, dtype=np.int64)
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, table.strand_length[strand])
    counts = np.diff(table.elem_offsets)
    base = np.concatenate([[0.0], np.cumsum(table.strand_length + 1.0)])[:-1]
    key = table.start + np.repeat(base, counts)
    e = np.searchsorted(key, s + base[strand], side="right") - 1
    e = np.clip(e, table.elem_offsets[strand], table.elem_offsets[strand + 1] - 1)
    return e, np.clip(s - table.start[e], 0.0, table.length[e])


def closest_distances(table: CurveTable, points, strand, s_guess=None, elem=None, t=None, iterations: int = 2):
    """Distances (P,) from points to their strand's curve, with the foot points' (element, t).

    Start from arc lengths ``s_guess`` or directly from elements ``elem`` and local parameters ``t``.
    """
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    strand = np.asarray(strand, dtype=np.int64)
    if elem is None:
        elem, t = locate(table, strand, s_guess)
    e = np.array(elem, dtype=np.int64).ravel()
    t = np.array(t, dtype=np.float64).ravel()
    first = np.ascontiguousarray(np.broadcast_to(table.elem_offsets[strand], e.shape))
    last = np.ascontiguousarray(np.broadcast_to(table.elem_offsets[strand + 1] - 1, e.shape))
    dist = np.empty(len(e))
    _closest_kernel(*_element_arrays(table), points, e, t, first, last, iterations, dist)
    return dist, e, t


@njit(cache=True, error_model="numpy")
def _closest_kernel(C, T, Om, length, points, e, t, first, last, iterations, dist):
    """:func:`closest_distances` over points; e, t updated in place."""
    for k in range(points.shape[0]):
        dist[k], e[k], t[k] = _closest_s(C, T, Om, length, points[k, 0], points[k, 1], points[k, 2], e[k], t[k],
                                         first[k], last[k], iterations)


class ElementRows:
    """Per-element rows (3, E): C_e, T_e, u1, u2; and w (E,), l (E,)."""

    def __init__(self, table: CurveTable):
        w = np.sqrt((table.Omega * table.Omega).sum(axis=1))
        a = table.Omega / np.where(w > 0, w, 1.0)[:, None]
        u1 = cross(a, table.T)
        u2 = cross(a, u1)
        self.rows = np.ascontiguousarray(np.concatenate([table.C, table.T, u1, u2], axis=1).T)  # (12, E)
        self.w = np.where(w > 0, w, 1.0)
        self.length = table.length


def _point(soa: ElementRows, e, t, want_derivatives=True):
    """C(t) (3, P) and, if asked, T(t), C''(t) on elements e at local parameters t."""
    rows = soa.rows[:, e]
    C0, T0, u1, u2 = rows[0:3], rows[3:6], rows[6:9], rows[9:12]
    w = soa.w[e]
    half = 0.5 * w * t
    sh, ch = np.sin(half), np.cos(half)
    sn = 2.0 * sh * ch                 # sin(theta)
    vc = 2.0 * sh * sh                 # 1 - cos(theta)
    C = C0 + t * T0 + (vc / w) * u1 + (t - sn / w) * u2
    if not want_derivatives:
        return C
    T = T0 + sn * u1 + vc * u2
    K = (w * (1.0 - vc)) * u1 + (w * sn) * u2
    return C, T, K


def evaluate_table(table: CurveTable, strand, s):
    """Points (P, 3), unit tangents (P, 3) and C'' (P, 3) at arc lengths s on strands."""
    e, t = locate(table, strand, s)
    C, T, K = _point(ElementRows(table), e, t)
    return C.T, T.T, K.T


def closest_distances_numpy(table: CurveTable, points, strand, s_guess=None, elem=None, t=None,
                             iterations: int = 2, rows: ElementRows | None = None):
    """Reference for :func:`closest_distances`, vectorised over points (numpy); ``rows``: the table's
    :class:`ElementRows` when already built."""
    points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).T)
    strand = np.asarray(strand, dtype=np.int64)
    if elem is None:
        elem, t = locate(table, strand, s_guess)
    e = np.asarray(elem, dtype=np.int64).copy()
    t = np.asarray(t, dtype=np.float64).copy()
    first = table.elem_offsets[strand]
    last = table.elem_offsets[strand + 1] - 1
    soa = rows if rows is not None else ElementRows(table)
    for _ in range(iterations):
        C, T, K = _point(soa, e, t)
        r = C - points
        g = (r * T).sum(axis=0)
        dg = 1.0 + (r * K).sum(axis=0)
        t = t - np.where(dg > 0.2, g / np.maximum(dg, 0.2), g)
        back = (t < 0.0) & (e > first)
        e[back] -= 1
        t[back] += soa.length[e[back]]
        ahead = (t > soa.length[e]) & (e < last)
        t[ahead] -= soa.length[e[ahead]]
        e[ahead] += 1
        t = np.clip(t, 0.0, soa.length[e])
    C = _point(soa, e, t, want_derivatives=False)
    d = C - points
    return np.sqrt((d * d).sum(axis=0)), e, t


def strand_errors_numpy(table, offsets, vpoints, vfrac, active, n_act, tol, full, stride: int = PRECHECK_STRIDE):
    """Reference for :func:`strand_errors` (numpy)."""
    vidx, owner, vcount = _ranges(offsets, active)
    starts = np.cumsum(vcount) - vcount
    local = np.arange(len(vidx)) - starts[owner]
    sub = (local % stride == 0) | (local == vcount[owner] - 1)
    mx, mn = np.zeros(len(active)), np.zeros(len(active))
    rows = ElementRows(table)
    d = vertex_distances(table, rows, vpoints, vfrac, n_act, vidx[sub], owner[sub])
    sub_max = np.zeros(len(active))
    np.maximum.at(sub_max, owner[sub], d)
    mean_sub = np.bincount(owner[sub], d, minlength=len(active)) / np.bincount(owner[sub], minlength=len(active))
    again = (sub_max <= tol) | full
    mx[~again], mn[~again] = sub_max[~again], mean_sub[~again]
    rest = again[owner] & ~sub
    if np.any(again):
        d_all = np.zeros(len(vidx))
        d_all[sub] = d
        d_all[rest] = vertex_distances(table, rows, vpoints, vfrac, n_act, vidx[rest], owner[rest])
        ids = np.nonzero(again)[0]
        d_all = d_all[again[owner]]
        cnt = vcount[ids]
        st = np.cumsum(cnt) - cnt
        mx[ids] = np.maximum.reduceat(d_all, st)
        mn[ids] = np.add.reduceat(d_all, st) / cnt
    return mx, mn


def vertex_distances(table, rows, vpoints, vfrac, n_act, vidx, owner, iterations=2, chunk: int = CHUNK):
    """Distances of vertices vidx to their strand (owner: index in the pass), from the point that
    corresponds to them: sample interval i <-> element i at the same fraction.  In chunks of
    ``chunk`` vertices (bounded memory, better cache use)."""
    dist = np.empty(len(vidx))
    for a in range(0, len(vidx), chunk):
        v, o = vidx[a:a + chunk], owner[a:a + chunk]
        u = vfrac[v] * n_act[o]
        i = np.minimum(u.astype(np.int64), n_act[o] - 1)
        e = table.elem_offsets[o] + i
        dist[a:a + chunk], _, _ = closest_distances_numpy(table, vpoints[v], o, elem=e, t=(u - i) * table.length[e],
                                                    iterations=iterations, rows=rows)
    return dist


def _ranges(offsets, ids):
    """Concatenated index ranges offsets[i]:offsets[i+1] for i in ids, and their owner positions."""
    counts = offsets[ids + 1] - offsets[ids]
    owner = np.repeat(np.arange(len(ids)), counts)
    starts = np.repeat(offsets[ids], counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    return starts + local, owner, counts



# --------------------------------------------------------------------------------------- sampling
def drop_repeated_vertices_numpy(points, offsets, relative: float = 1e-6, absolute: float = 1e-12):
    """Reference for :func:`drop_repeated_vertices` (numpy)."""
    points = np.asarray(points, dtype=np.float64)
    offsets = np.asarray(offsets, dtype=np.int64)
    V = len(points)
    keep = np.ones(V, dtype=bool)
    if V > 1:
        _, lengths = vertex_arc_lengths_numpy(points, offsets)
        strand = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
        seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
        keep[1:] = seg >= np.maximum(absolute, relative * lengths[strand[1:]])
    return _kept(points, offsets, keep)


def vertex_arc_lengths_numpy(points, offsets) -> tuple[np.ndarray, np.ndarray]:
    """Reference for :func:`vertex_arc_lengths` (numpy)."""
    counts = np.diff(offsets)
    d = np.zeros(len(points))
    if len(points) > 1:
        d[1:] = np.linalg.norm(np.diff(points, axis=0), axis=1)
    d[offsets[:-1][counts > 0]] = 0.0
    csum = np.cumsum(d)
    start = np.repeat(csum[offsets[:-1][counts > 0]], counts[counts > 0])
    s = csum - start
    last = np.maximum(offsets[1:] - 1, 0)
    lengths = np.where(counts > 0, s[last], 0.0)
    return s, lengths



def evaluate_numpy(self, strand, s):
    """Reference for :meth:`PolylineCurves.evaluate` (``self``: a PolylineCurves), vectorised over
    samples (numpy)."""
    strand = np.asarray(strand, dtype=np.int64)
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.lengths[strand])
    first = self.offsets[strand]
    n = self.counts[strand]
    v = np.searchsorted(self._key, s + self._base[strand], side="right") - 1
    seg = np.clip(v - first, 0, n - 2)
    w = first + np.clip(seg - 1, 0, n - 4)                # window start: vertices w..w+3
    x0, x1, x2, x3 = (self.arc[w + j] for j in range(4))
    u0, u1, u2 = self._u[w], self._u[w + 1], self._u[w + 2]
    d2 = (u1 - u0) / (x2 - x0)[:, None]
    d3 = ((u2 - u1) / (x3 - x1)[:, None] - d2) / (x3 - x0)[:, None]
    a0 = (s - x0)[:, None]
    a1 = (s - x1)[:, None]
    a2 = (s - x2)[:, None]
    q2 = d2 + a2 * d3
    q1 = u0 + a1 * q2
    pts = self.points[w] + a0 * q1
    tan = q1 + a0 * (q2 + a1 * d3)
    tan /= np.sqrt(dot(tan, tan))[:, None]
    return pts, tan


# ------------------------------------------------------------------------------------- cohelicity
def project_numpy(X, V, n_elements, eps):
    """Closest X' to X, X'_0 = X_0, with (X'_{i+1} - X'_i) . V_i = 0 for i < n: the KKT system above.

    X (S, N+1, 3); V (S, N, 3) the constraint directions (dt_i); padding has V = 0.
    """
    S, N1, _ = X.shape
    N = N1 - 1
    real = np.arange(N)[None, :] < n_elements[:, None]
    V = np.where(real[..., None], V, 0.0)
    dx = np.where(real[..., None], X[:, 1:] - X[:, :-1], 0.0)
    diag = 2.0 * dot(V, V)
    diag[:, 0] *= 0.5
    diag += eps
    off = -dot(V[:, :-1], V[:, 1:])
    rhs = -dot(dx, V)
    lam = _thomas(diag, off, rhs)
    move = lam[..., None] * V
    out = X.copy()
    out[:, 1:] += move
    out[:, 1:-1] -= move[:, 1:]
    return out


def _thomas(diag, off, rhs):
    """Solve the symmetric tridiagonal systems (diag, off) lam = rhs, batched over rows."""
    S, N = diag.shape
    cp = np.empty((S, N))
    rp = np.empty((S, N))
    cp[:, 0] = diag[:, 0]
    rp[:, 0] = rhs[:, 0]
    for i in range(1, N):
        w = off[:, i - 1] / cp[:, i - 1]
        cp[:, i] = diag[:, i] - w * off[:, i - 1]
        rp[:, i] = rhs[:, i] - w * rp[:, i - 1]
    lam = np.empty((S, N))
    lam[:, N - 1] = rp[:, N - 1] / cp[:, N - 1]
    for i in range(N - 2, -1, -1):
        lam[:, i] = (rp[:, i] - off[:, i] * lam[:, i + 1]) / cp[:, i]
    return lam

