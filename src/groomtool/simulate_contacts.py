"""Contact tracking for the simulator: detection (kept while nothing moved), persistence, the
velocity-level targets and the warm start of the contact solve (docs/simulation.md section 3).

**Detection with a skin.**  Contacts are detected on the helices sampled ``samples_per_element`` times
per element with the thresholds 2 r_c + m_s[a] + m_s[b] (strand/strand) and r_c + m_h[a] (head), m the
speculative margins of each strand (1.5 h times its fastest node's speed, capped).  The detection pass
runs with thresholds grown by a skin delta (strand/strand + delta, head + delta) and its candidates
are kept.  At a later step, with D the largest displacement of any sample since that pass (in the
head's frame) and G_s, G_h the largest growth of a strand's margins since then, a pair now within
its threshold was within threshold + 2 D + 2 G_s (strand/strand) or + D + G_h (head) at the pass,
hence a candidate, as long as

    D + G_s <= delta / 2   and   D + G_h <= delta.

Then the candidates are re-evaluated on the current samples as the detection builds them
(revisit: strand/strand closest points of the candidate's segment pair, so the normal stays
orthogonal to both axes; head contacts at their arc length, the surface queried; e_T1 keeps its
previous direction) and filtered by the current thresholds instead of a new detection pass.  Head
contacts keep the pass's arc lengths: they slide by at most delta / 2 before the next pass.
Otherwise a new pass runs, with the skin unless the samples moved by more than delta / 2 since the
last pass (fast motion: the next step could not keep it either; same contacts, a cheaper pass).
delta = 0 detects every step (the previous behaviour); at rest (an inverted groom) one pass serves
the whole run.

**Head contacts strand by strand.**  A strand's head contacts depend on that strand alone (the head is
fixed in its frame), so their test is per strand: with D_s its largest sample displacement since its own
last head pass and G_h,s the growth of its head margin, its candidates are kept while D_s + G_h,s <= delta;
only the strands that fail it are detected again (with the skin unless they move by more than delta / 2 a
step, from their margin).  A sagging groom whose tips swing re-detects those strands' head contacts, not
the whole head's.  The strand/strand candidates keep the groom-wide test above.

**A partial step's contacts** (ContactTracker.contacts_of): only the contacts of some strands are made anew (the
others keep theirs, Simulator._partial_contacts): the kept candidates with a side among them are revisited on the
samples of the strands involved alone, their head contacts kept or detected strand by strand, under the per-pair
form of the test above (e_a + e_b <= delta, e_s = D_s + G_s of strand s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .rods import clothoid as cl
from .rods import superhelix as sh


def rod_module(rod):
    """The rod model's module (sample, evaluate): rods.clothoid for Super Space Clothoids, else rods.superhelix."""
    return cl if isinstance(rod, cl.SuperClothoid) else sh


# --------------------------------------------------------------------------- pure helpers
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
    _closest_in_ranges(order, lo, hi, np.asarray(new.s_a, dtype=np.float64), sb_new,
                       np.asarray(old.s_a, dtype=np.float64), sb_old, float(arc_tolerance), out)
    return out


@njit(cache=True)
def _closest_in_ranges(order, lo, hi, sa_new, sb_new, sa_old, sb_old, tol, out):
    """out[i] = the j = order[k], k in [lo[i], hi[i]) (in that order), of the smallest d = |sa_new[i] - sa_old[j]| +
    |sb_new[i] - sb_old[j]| <= tol, the first of equal ones (out[i] left where there is none)."""
    for i in range(lo.shape[0]):
        best = np.inf
        for k in range(lo[i], hi[i]):
            j = order[k]
            d = abs(sa_new[i] - sa_old[j]) + abs(sb_new[i] - sb_old[j])
            if d <= tol and d < best:
                best = d
                out[i] = j


def normal_velocity_targets(gap, allowed, dt: float, push_rate: float, max_push_speed: float) -> np.ndarray:
    """ubar per contact: -gap/h ahead of touching, 0 within the allowed depth, a bounded push beyond."""
    gap = np.asarray(gap, dtype=np.float64)
    excess = -gap - allowed
    push = np.minimum(push_rate * np.maximum(excess, 0.0) / dt, max_push_speed)
    return np.where(gap > 0.0, -gap / dt, np.where(excess > 0.0, push, 0.0))


def contact_thresholds(contacts, radius: float, margins) -> np.ndarray:
    """Distance below which a contact is in the problem: r_c + m_h[a] (head), 2 r_c + m_s[a] + m_s[b]
    (strand/strand); margins = (m_h, m_s), each a number or one per strand (S,)."""
    a = np.asarray(contacts.strand_a, dtype=np.int64)
    b = np.asarray(contacts.strand_b, dtype=np.int64)
    head = b < 0

    def at(m, strand):
        m = np.asarray(m, dtype=np.float64)
        return m if m.ndim == 0 else m[strand]

    other = np.where(head, a, b)
    return np.where(head, radius + at(margins[0], a), 2.0 * radius + at(margins[1], a) + at(margins[1], other))


def reevaluate(helix: sh.SuperHelix, kin, contacts, head_surface, transform=None, tangents=None):
    """The contacts' geometry at their arc lengths on ``helix``: (point_a, point_b, normal, frame,
    distance).  Head contacts: closest point of the head surface (queried in the head's rest frame
    when ``transform`` = (R, T)); strand/strand: the two axis points, normal from b to a (the old
    normal where they coincide).  Frames: e_T1 along ``tangents`` (default the strand tangent)."""
    from .contact import contact_frames

    model = rod_module(helix)
    x_a, R_a = model.evaluate(helix, contacts.strand_a, contacts.s_a, kin)
    head = contacts.strand_b < 0
    point_b = np.empty_like(x_a)
    normal = np.empty_like(x_a)
    dist = np.empty(len(contacts.strand_a))
    if np.any(head):
        x = x_a[head]
        if transform is not None:
            R, T = transform
            d, c, n, _ = head_surface.query((x - T) @ R)
            c, n = c @ R.T + T, n @ R.T
        else:
            d, c, n, _ = head_surface.query(x)
        dist[head], point_b[head], normal[head] = d, c, n
    if np.any(~head):
        x_b, _ = model.evaluate(helix, contacts.strand_b[~head], contacts.s_b[~head], kin)
        gap = x_a[~head] - x_b
        d = np.linalg.norm(gap, axis=1)
        n = np.where(d[:, None] > 1e-12, gap / np.maximum(d, 1e-300)[:, None], contacts.normal[~head])
        dist[~head], point_b[~head], normal[~head] = d, x_b, n
    hint = R_a[:, :, 0] if tangents is None else tangents
    frames = contact_frames(normal, hint) if len(dist) else np.zeros((0, 3, 3))
    return x_a, point_b, normal, frames, dist


def polyline_segments(offsets: np.ndarray, arc: np.ndarray, strand, s) -> tuple[np.ndarray, np.ndarray]:
    """Segment (first vertex) and parameter in [0, 1] of arc lengths s on the sampled polylines."""
    strand = np.asarray(strand, dtype=np.int64)
    s = np.asarray(s, dtype=np.float64)
    span = float(np.max(arc, initial=0.0)) + 1.0
    vertex_strand = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    key = arc + vertex_strand * span
    v = np.searchsorted(key, s + strand * span, side="right") - 1
    v = np.clip(v, offsets[strand], offsets[strand + 1] - 2)
    seg = arc[v + 1] - arc[v]
    t = np.clip((s - arc[v]) / np.where(seg > 0, seg, 1.0), 0.0, 1.0)
    return v, t


def closest_on_segments(pts, offsets, strand_a, va, at_vertex_a, strand_b, vb, at_vertex_b):
    """Closest points between segments va and vb (the candidate's own pair, as the detection found it;
    where an arc length sits on a vertex, the segment before it is tried too: the detection may have
    placed it at that segment's end): (s, t, point_a, point_b, distance, ia, ib)."""
    from .contact import segment_closest_points

    out = None
    for da, db in ((0, 0), (-1, 0), (0, -1), (-1, -1)):
        allowed = np.ones(len(va), dtype=bool)
        if da:
            allowed &= at_vertex_a & (va > offsets[strand_a])
        if db:
            allowed &= at_vertex_b & (vb > offsets[strand_b])
        if out is not None and not np.any(allowed):
            continue
        ia, ib = va + da * allowed, vb + db * allowed
        s, t, c1, c2, d = segment_closest_points(pts[ia], pts[ia + 1], pts[ib], pts[ib + 1])
        if out is None:
            out = [s, t, c1, c2, d, ia, ib]
            continue
        better = allowed & (d < out[4])
        for k, x in enumerate((s, t, c1, c2, d, ia, ib)):
            out[k] = np.where(better[:, None], x, out[k]) if x.ndim == 2 else np.where(better, x, out[k])
    return tuple(out)


def revisit(pts: np.ndarray, offsets: np.ndarray, arc: np.ndarray, candidates, head_surface):
    """The candidates' geometry on the current samples, built as the detection builds it.

    Strand/strand: the closest points of the candidate's segment pair (segment_closest_points,
    normals by pair_normals): the contact follows a strand sliding along the other, its normal stays
    orthogonal to both axes (a pair is not moved to its neighbours: the detection's minima are its
    own, and two candidates must not become one contact).  Head: the point at the candidate's arc
    length on the polyline, the head's closest point and normal (HeadSurface.query).  e_T1 keeps the
    last frame's direction.  On unchanged samples this is the detection's own result (to round-off)."""
    from .contact import Contacts, contact_frames
    from .contact.detect import pair_normals

    c = candidates
    m = len(c.strand_a)
    if m == 0:
        return c
    va, ta = polyline_segments(offsets, arc, c.strand_a, c.s_a)
    point_a = pts[va] + ta[:, None] * (pts[va + 1] - pts[va])
    s_a, s_b = c.s_a.copy(), c.s_b.copy()
    head = c.strand_b < 0
    point_b = np.empty_like(point_a)
    normal = np.empty_like(point_a)
    dist = np.empty(m)
    if np.any(head):
        d, closest, n, _ = head_surface.query(point_a[head])
        dist[head], point_b[head], normal[head] = d, closest, n
    pair = ~head
    if np.any(pair):
        vb, tb = polyline_segments(offsets, arc, c.strand_b[pair], c.s_b[pair])
        s, t, c1, c2, d, ia, ib = closest_on_segments(pts, offsets, c.strand_a[pair], va[pair], ta[pair] == 0.0,
                                                      c.strand_b[pair], vb, tb == 0.0)
        s_a[pair] = arc[ia] + s * (arc[ia + 1] - arc[ia])
        s_b[pair] = arc[ib] + t * (arc[ib + 1] - arc[ib])
        point_a[pair], point_b[pair], dist[pair] = c1, c2, d
        normal[pair] = pair_normals(c1, c2, pts[ia + 1] - pts[ia], pts[ib + 1] - pts[ib], d)
    frames = contact_frames(normal, c.frame[:, 1])
    return Contacts(c.strand_a, s_a, c.strand_b, s_b, point_a, point_b, normal, frames, dist, c.radius)


@dataclass
class DetectionCache:
    """The last strand/strand detection pass: its samples (V, 3) in the head's frame, the margins and skin it
    used and its candidates (in the head's frame)."""

    samples: np.ndarray
    margins: tuple  # (head, strand) margins per strand (S,) each
    candidates: object
    skin: float = 0.0


@dataclass
class HeadCache:
    """Each strand's last head pass: the samples (V, 3, in the head's frame; a strand's rows from its own
    pass), the head margin (S,) and skin (S,) it used, and the candidates of all strands (ordered by strand)."""

    samples: np.ndarray
    margin: np.ndarray
    skin: np.ndarray
    candidates: object


def strand_rows(offsets: np.ndarray, strands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sample rows of ``strands`` (in order) and the offsets of the sub-array they form."""
    counts = offsets[strands + 1] - offsets[strands]
    sub = np.zeros(len(strands) + 1, dtype=np.int64)
    np.cumsum(counts, out=sub[1:])
    rows = np.repeat(offsets[strands] - sub[:-1], counts) + np.arange(int(sub[-1]))
    return rows, sub


def touching(contacts, strands, n_strands: int) -> np.ndarray:
    """(m,) whether each contact has a side (strand_a, or strand_b of a strand/strand contact) in ``strands``."""
    on = np.zeros(n_strands, dtype=bool)
    on[np.asarray(strands, dtype=np.int64)] = True
    b = np.asarray(contacts.strand_b, dtype=np.int64)
    return on[np.asarray(contacts.strand_a, dtype=np.int64)] | ((b >= 0) & on[np.maximum(b, 0)])


def strand_part(helix: sh.SuperHelix, kin, ids: np.ndarray):
    """Strands ``ids`` (sorted) of a Super-Helix groom and their kinematics, gathered from ``kin`` (nothing
    recomputed; trimmed to their largest element count): sampling, evaluating or differentiating them there gives
    the whole groom's numbers for those strands (a partial step's contacts, Simulator._partial_contacts)."""
    ids = np.asarray(ids, dtype=np.int64)
    part = helix.subset(ids)
    n = part.max_elements
    per_element = {name: getattr(kin, name)[ids, :n] for name in ("Q", "p", "P", "D", "DP", "Theta", "z")}
    return part, sh.Kinematics(part, kin.C[ids, :n + 1], kin.R[ids, :n + 1], c=kin.c[:, ids, :n],
                               dc=kin.dc[:, ids, :n], **per_element)


# --------------------------------------------------------------------------- the tracker
class ContactTracker:
    """Which contacts enter each step's problem, and their warm start.

    params: SimulationParams; radius r_c; head_surface (contact.HeadSurface or None); motion
    (simulate_motion.HeadMotion); lengths (S, N) and mask of the elements; warm_start = (contacts,
    impulses (m, 3) in N s) for the first solve or None.
    """

    def __init__(self, params, radius: float, head_surface, motion, lengths: np.ndarray, mask: np.ndarray,
                 warm_start=None):
        self.params = params
        self.radius = float(radius)
        self.head_surface = head_surface
        self.motion = motion
        self.lengths = lengths
        self.mask = mask
        skin = params.detection_skin
        self.skin = self.radius if skin is None else float(skin)
        self.warm_start = warm_start
        self.previous = None  # (contacts, impulses) of the last step
        self.initial = None
        self.cache: DetectionCache | None = None  # strand/strand candidates
        self.head_cache: HeadCache | None = None  # strand/head candidates, strand by strand
        self.passes = 0  # steps that ran a detection pass (strand/strand, or head for some strands)
        self.reused = 0  # steps served by the kept candidates alone
        self.head_redetections = 0  # strand-steps whose head contacts were detected again
        self._sample_offsets = None  # the sample offsets of the whole groom (the last _samples)
        # per strand e_s = D_s + G_s at its last sampling: its largest sample displacement since the strand/strand pass
        # and the growth of its strand margin since then (contacts_of)
        self._pair_excess = None

    # ---------------------------------------------------------------- margins
    def margins(self, speeds) -> tuple[np.ndarray, np.ndarray]:
        """(head, strand) detection margins per strand from its largest node speed (S,): 1.5 h |v|max,s,
        capped at 100 r_c and 2 r_c (or the params').  Per strand, not the groom's fastest: two strands
        approach by at most h (|v_a| + |v_b|) in a step, within the threshold 2 r_c + m_a + m_b (a fast
        strand does not widen the search of the slow ones: ~2x less detection on a sagging groom)."""
        p = self.params
        reach = 1.5 * np.asarray(speeds, dtype=np.float64) * p.dt
        head_cap = 100.0 * self.radius if p.head_margin is None else p.head_margin
        strand_cap = 2.0 * self.radius if p.strand_margin is None else p.strand_margin
        return np.minimum(head_cap, reach), np.minimum(strand_cap, reach)

    # ---------------------------------------------------------------- detection
    def _samples(self, helix, kin, t):
        pts, offsets, _, arc = rod_module(helix).sample(helix, self.params.samples_per_element, kin)
        self._sample_offsets = offsets
        transform = self.motion.transform(t)
        if transform is not None:
            R, T = transform
            pts = (pts - T) @ R  # R^T (x - T): the head's rest frame
        return pts, offsets, arc, transform

    def _strand_pairs(self, pts, offsets, arc, margins) -> tuple[object, bool]:
        """Strand/strand contacts on the samples (head's frame): the kept candidates revisited while the
        groom-wide test holds (module docstring), else a pass with the thresholds grown by the skin.
        Returns (contacts, whether a pass ran)."""
        from .contact import detect_strand_contacts

        c = self.cache
        moved = None
        if c is not None and c.samples.shape == pts.shape:
            per_strand = np.sqrt(np.maximum.reduceat(np.sum((pts - c.samples) ** 2, axis=1), offsets[:-1]))
            moved = float(np.max(per_strand, initial=0.0))
            growth = np.maximum(np.asarray(margins[1], dtype=np.float64) - c.margins[1], 0.0)
            grow = float(np.max(growth, initial=0.0))
            if c.skin > 0.0 and moved + grow <= 0.5 * c.skin:
                self._pair_excess = per_strand + growth
                return revisit(pts, offsets, arc, c.candidates, self.head_surface), False
        # strands that moved by more than half the skin since the last pass would not keep the next one
        # either: detect without the skin (same contacts, a cheaper pass)
        skin = self.skin if moved is None or moved <= 0.5 * self.skin else 0.0
        r_s = self.radius + margins[1]  # per strand
        s_max = float(np.max(r_s, initial=self.radius))
        found = detect_strand_contacts(pts, offsets, arc, r_s + 0.5 * skin, min_self_arc=np.pi * s_max,
                                       merge_arc=4.0 * s_max)
        self.cache = DetectionCache(pts, tuple(np.broadcast_to(np.asarray(m, dtype=np.float64), (len(offsets) - 1,))
                                               for m in margins), found, skin)
        self._pair_excess = np.zeros(len(offsets) - 1)
        return found, True

    def _head(self, pts, offsets, arc, margins, ids=None) -> tuple[object, bool]:
        """Strand/head contacts on the samples (head's frame), strand by strand: the kept candidates of the
        strands that pass their own test (module docstring) revisited, the others' detected again.  ``ids``: the
        (sorted) strands whose samples pts, offsets and arc are (local strand k is ids[k]; None: all, the full
        groom's samples).  Returns (the contacts of those strands, ordered by strand, whether any strand was
        detected)."""
        from .contact import Contacts, detect_head_contacts

        S = len(self._sample_offsets) - 1 if ids is not None else len(offsets) - 1
        ids = np.arange(S) if ids is None else np.asarray(ids, dtype=np.int64)
        rows_all = strand_rows(self._sample_offsets, ids)[0] if len(ids) != S else np.arange(len(pts))
        c = self.head_cache
        head_margin = np.broadcast_to(np.asarray(margins[0], dtype=np.float64), (S,))
        if c is None or c.samples.shape[0] != int(self._sample_offsets[-1]):
            c = self.head_cache = HeadCache(np.zeros((int(self._sample_offsets[-1]), 3)), np.zeros(S), np.zeros(S),
                                            None)
            stale = np.ones(len(ids), dtype=bool)
        else:
            moved = np.maximum.reduceat(np.sqrt(np.sum((pts - c.samples[rows_all]) ** 2, axis=1)), offsets[:-1])
            stale = ~(moved + np.maximum(head_margin[ids] - c.margin[ids], 0.0) <= c.skin[ids]) | (c.skin[ids] <= 0.0)
        local = np.full(S, -1, dtype=np.int64)  # global strand -> position in ids
        local[ids] = np.arange(len(ids))
        redo_global = np.zeros(S, dtype=bool)
        redo_global[ids[stale]] = True
        old = kept = None  # the candidates of the strands that keep theirs (all strands), and ids' revisited
        if c.candidates is not None and len(c.candidates.strand_a):
            old = c.candidates.subset(~redo_global[c.candidates.strand_a])
            mine = old.subset(local[old.strand_a] >= 0) if len(ids) != S else old
            if len(mine.strand_a):
                mine.strand_a = local[mine.strand_a]
                kept = revisit(pts, offsets, arc, mine, self.head_surface)
                kept.strand_a = ids[kept.strand_a]
            if not len(old.strand_a):
                old = None
        redo = np.flatnonzero(stale)  # local
        if len(redo) == 0:
            return kept, False
        # a strand moving by more than half the skin a step (its margin, 1.5 h |v|) could not keep its
        # candidates the next step either: detected without the skin (the same contacts, a cheaper pass)
        g = ids[redo]
        skin = np.where(head_margin[g] <= 0.5 * self.skin, self.skin, 0.0)
        r_h = self.radius + head_margin
        h_max = float(np.max(r_h, initial=self.radius))
        rows, sub = strand_rows(offsets, redo)
        found = detect_head_contacts(pts[rows], sub, arc[rows], self.head_surface, r_h[g] + skin,
                                     min_root_arc=np.pi * h_max, merge_arc=4.0 * h_max)
        found.strand_a = g[found.strand_a]
        c.samples[rows_all[rows]] = pts[rows]
        c.margin[g] = head_margin[g]
        c.skin[g] = skin
        self.head_redetections += len(redo)
        found.radius = None
        merged = Contacts.concatenate([x for x in (old, found) if x is not None])
        c.candidates = merged.subset(np.argsort(merged.strand_a, kind="stable"))
        fresh = found if kept is None else Contacts.concatenate([kept, found])
        return fresh.subset(np.argsort(fresh.strand_a, kind="stable")), True

    def detect(self, helix: sh.SuperHelix, kin, t: float, margins: tuple[float, float]):
        """Contacts within the thresholds at ``margins`` on the current geometry (world frame)."""
        from .contact import Contacts

        pts, offsets, arc, transform = self._samples(helix, kin, t)
        parts, ran = [], False
        if self.params.contacts == "all":
            part, did = self._strand_pairs(pts, offsets, arc, margins)
            parts.append(part)
            ran |= did
        if self.head_surface is not None:
            part, did = self._head(pts, offsets, arc, margins)
            if part is not None:
                parts.append(part)
            ran |= did
        if ran:
            self.passes += 1
        else:
            self.reused += 1
        for part in parts:
            part.radius = None
        found = Contacts.concatenate(parts)
        if transform is not None and len(found.strand_a):
            R, T = transform
            found = Contacts(found.strand_a, found.s_a, found.strand_b, found.s_b, found.point_a @ R.T + T,
                             found.point_b @ R.T + T, found.normal @ R.T, found.frame @ R.T, found.distance,
                             found.radius)
        keep = found.distance <= contact_thresholds(found, self.radius, margins)
        out = found.subset(keep) if not np.all(keep) else found
        out.radius = self.radius + float(np.max(margins[1], initial=0.0))
        return out

    def detect_initial(self, helix: sh.SuperHelix, kin=None):
        """The contacts at the start (no margins): the depths they may keep without push."""
        zero = np.zeros(helix.n_strands)
        self.initial = self.detect(helix, kin, 0.0, (zero, zero))
        return self.initial

    # ---------------------------------------------------------------- persistence
    def persistent(self, helix: sh.SuperHelix, kin, t: float, detected, margins: tuple[float, float],
                   strands: np.ndarray | None = None):
        """Previous-step contacts that carried load (r_N > 0), not re-detected nearby, re-evaluated at
        their arc lengths on the current geometry and kept while within reach: a strand draped over
        a smooth surface keeps several supports instead of one that hops between samples.  ``strands``: only
        the contacts that touch them (contacts_of)."""
        from .contact import Contacts

        if self.previous is None or self.previous[1] is None or len(self.previous[1]) == 0:
            return detected
        prev, imp = self.previous
        loaded = imp[:, 0] > 0
        if strands is not None:
            loaded &= touching(prev, strands, helix.n_strands)
        cand = prev.subset(loaded)
        if len(cand) and len(detected):
            spacing = float(np.mean(self.lengths[self.mask])) / self.params.samples_per_element
            cand = cand.subset(match_contacts(detected, cand, max(4.0 * self.radius, spacing)) < 0)
        if len(cand) == 0:
            return detected
        x_a, point_b, normal, frames, dist = reevaluate(helix, kin, cand, self.head_surface, self.motion.transform(t))
        keep = dist <= contact_thresholds(cand, self.radius, margins)
        if not np.any(keep):
            return detected
        kept = Contacts(cand.strand_a[keep], cand.s_a[keep], cand.strand_b[keep], cand.s_b[keep], x_a[keep],
                        point_b[keep], normal[keep], frames[keep], dist[keep], detected.radius)
        return Contacts.concatenate([detected, kept])

    def contacts(self, helix: sh.SuperHelix, kin, t: float, margins: tuple[float, float]):
        """The step's contacts: detected (or kept) plus the persistent ones."""
        return self.persistent(helix, kin, t, self.detect(helix, kin, t, margins), margins)

    def contacts_of(self, helix: sh.SuperHelix, kin, t: float, margins, strands: np.ndarray, slack: float = 0.0):
        """The step's contacts that touch ``strands`` (sorted; a partial step, Simulator._partial_contacts: the other
        strands keep theirs), found as contacts() finds them, on the strands involved alone: the kept strand/strand
        candidates with a side in ``strands`` revisited on the samples of both sides, the head contacts of ``strands``
        (kept or detected again strand by strand, _head), the previous step's loaded contacts of ``strands``
        (persistent), filtered by the thresholds.  Super-Helices under a static head.  None where the kept
        strand/strand candidates cannot serve (or there are none yet): the caller then takes contacts().

        The candidates serve when every pair of a strand a of ``strands`` and any strand b was a candidate if now
        within its threshold: e_a + e_b <= skin with e_s = D_s + G_s (the strand's largest sample displacement since
        the pass and the growth of its strand margin since then: the per-pair form of the module docstring's test),
        e fresh for the strands sampled here, for the others the value at their last sampling plus ``slack`` (how far
        their samples may have moved since: the caller's bound for strands that did not move)."""
        from .contact import Contacts

        if self._sample_offsets is None or self.motion.transform(t) is not None or isinstance(helix, cl.SuperClothoid):
            return None
        strands = np.asarray(strands, dtype=np.int64)
        S = helix.n_strands
        c = pairs = None
        involved = strands
        if self.params.contacts == "all":
            c = self.cache
            if c is None or not c.skin > 0.0 or self._pair_excess is None:
                return None
            pairs = c.candidates.subset(touching(c.candidates, strands, S))
            involved = np.union1d(strands, np.concatenate([pairs.strand_a, pairs.strand_b[pairs.strand_b >= 0]]))
        part, part_kin = strand_part(helix, kin, involved)
        pts, offsets, _, arc = sh.sample(part, self.params.samples_per_element, part_kin)
        local = np.full(S, -1, dtype=np.int64)  # global strand -> its position in involved
        local[involved] = np.arange(len(involved))
        found = []
        if c is not None:
            rows = strand_rows(self._sample_offsets, involved)[0]
            fresh = np.sqrt(np.maximum.reduceat(np.sum((pts - c.samples[rows]) ** 2, axis=1), offsets[:-1]))
            fresh += np.maximum(np.asarray(margins[1], dtype=np.float64)[involved] - c.margins[1][involved], 0.0)
            excess = self._pair_excess + slack
            excess[involved] = fresh
            if not float(np.max(excess[strands], initial=0.0)) + float(np.max(excess, initial=0.0)) <= c.skin:
                return None
            self._pair_excess[involved] = fresh
            if len(pairs.strand_a):
                head_b = pairs.strand_b < 0
                pairs.strand_a = local[pairs.strand_a]
                pairs.strand_b = np.where(head_b, pairs.strand_b, local[np.maximum(pairs.strand_b, 0)])
                near = revisit(pts, offsets, arc, pairs, self.head_surface)
                near.strand_a = involved[near.strand_a]
                near.strand_b = np.where(head_b, near.strand_b, involved[np.maximum(near.strand_b, 0)])
                found.append(near)
        ran = False
        if self.head_surface is not None:
            rows, sub = strand_rows(offsets, local[strands])
            part_head, ran = self._head(pts[rows], sub, arc[rows], margins, ids=strands)
            if part_head is not None:
                found.append(part_head)
        if ran:
            self.passes += 1
        else:
            self.reused += 1
        for x in found:
            x.radius = None
        found = Contacts.concatenate(found) if found else Contacts.empty()
        keep = found.distance <= contact_thresholds(found, self.radius, margins)
        out = found.subset(keep)
        out.radius = self.radius + float(np.max(margins[1], initial=0.0))
        return self.persistent(helix, kin, t, out, margins, strands=strands)

    # ---------------------------------------------------------------- targets and warm start
    def allowed_depth(self, contacts) -> np.ndarray:
        """Depth tolerated without push: the allowance, or the contact's own depth at the start."""
        r_c = self.radius
        p = self.params
        base = 0.5 * r_c if p.penetration_allowance is None else p.penetration_allowance
        allowed = np.full(len(contacts.strand_a), base)
        init = self.initial
        if init is not None and len(init.strand_a):
            sample = float(np.max(self.lengths)) / p.samples_per_element
            idx = match_contacts(init, contacts, 4.0 * r_c + 2.0 * sample)
            depth0 = -contact_gaps(init, r_c)
            has = idx >= 0
            allowed[has] = np.maximum(allowed[has], depth0[idx[has]])
        return allowed

    def targets(self, contacts) -> np.ndarray:
        """ubar (m,) of normal_velocity_targets for these contacts."""
        p = self.params
        return normal_velocity_targets(contact_gaps(contacts, self.radius), self.allowed_depth(contacts), p.dt,
                                       p.push_rate, p.max_push_speed)

    def initial_impulses(self, contacts, carried=None) -> np.ndarray:
        """(m, 3) impulses (N s) to start the solve from: the previous step's on the matching contacts
        (same strands, arc lengths within 2 r_c), else the warm start's.  ``carried`` = (old, rows): contact i is
        contact rows[i] of the contact set ``old`` (-1: another); where the previous step's set is ``old``, those
        take its impulses as they are (what matching finds: the same contact) and only the others are matched."""
        r0 = np.zeros((len(contacts.strand_a), 3))
        known = self.previous if self.previous is not None and self.previous[1] is not None else self.warm_start
        if known is not None and known[0] is contacts and len(known[1]) == len(r0):  # the same set (a step at rest)
            return np.array(known[1], dtype=np.float64)
        if (carried is not None and known is not None and known[0] is carried[0]
                and len(known[1]) == len(carried[0].strand_a)):
            rows = np.asarray(carried[1], dtype=np.int64)
            has = rows >= 0
            r0[has] = known[1][rows[has]]
            rest = np.flatnonzero(~has)
            if len(rest) and len(known[1]):
                idx = match_contacts(known[0], contacts.subset(rest), 2.0 * self.radius + 1e-12)
                r0[rest[idx >= 0]] = known[1][idx[idx >= 0]]
            return r0
        if known is not None and len(known[1]):
            idx = match_contacts(known[0], contacts, 2.0 * self.radius + 1e-12)
            has = idx >= 0
            r0[has] = known[1][idx[has]]
        return r0

    def remember(self, contacts, impulses) -> None:
        """The step's contacts and impulses, for persistence and the next warm start."""
        self.previous = (contacts, impulses)
