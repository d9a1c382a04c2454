"""Strand/strand contact detection, segment distances, frames and the Contacts record."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize

from groomtool.contact import (HEAD, Contacts, close_segment_pairs, contact_frames, detect_contacts,
                               detect_strand_contacts, segment_closest_points)
from groomtool.contact import detect
from groomtool.contact.detect import strand_segments
from groomtool.groom import Groom
from reference import contact as contact_reference

RC = 1e-4  # contact radius used by the hand-made configurations (m)


def ragged(strands):
    """points, offsets, arc of a list of (n_i, 3) polylines."""
    g = Groom.from_strands(strands)
    return g.points, g.offsets, g.arc_lengths()


def line(a, b, n):
    return np.linspace(a, b, n)


# ------------------------------------------------------------------------ segment/segment distance
def _point_segment(p, a, b):
    ab = b - a
    L2 = ab @ ab
    t = 0.0 if L2 == 0 else min(max((p - a) @ ab / L2, 0.0), 1.0)
    return np.linalg.norm(p - (a + t * ab))


def reference_distance(p0, p1, q0, q1):
    """Minimum of |P(s) - Q(t)| over the unit square: the interior critical point if any, else the
    best of the four edges (each a point-to-segment distance)."""
    cands = [_point_segment(p0, q0, q1), _point_segment(p1, q0, q1),
             _point_segment(q0, p0, p1), _point_segment(q1, p0, p1)]
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    A = np.array([[d1 @ d1, -d1 @ d2], [-d1 @ d2, d2 @ d2]])
    if abs(np.linalg.det(A)) > 1e-12 * max(1e-300, (d1 @ d1) * (d2 @ d2)):
        s, t = np.linalg.solve(A, [-d1 @ r, d2 @ r])
        if 0 <= s <= 1 and 0 <= t <= 1:
            cands.append(np.linalg.norm(p0 + s * d1 - q0 - t * d2))
    return min(cands)


coord = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
vec = st.tuples(coord, coord, coord).map(np.array)


@st.composite
def segment_pairs(draw):
    p0, p1, q0, q1 = draw(vec), draw(vec), draw(vec), draw(vec)
    kind = draw(st.sampled_from(["random", "parallel", "collinear", "zero_p", "zero_both", "shared"]))
    if kind == "parallel":
        scale = draw(st.floats(-2.0, 2.0))
        q1 = q0 + scale * (p1 - p0)
    elif kind == "collinear":
        a, b = draw(st.floats(-2, 2)), draw(st.floats(-2, 2))
        q0, q1 = p0 + a * (p1 - p0), p0 + b * (p1 - p0)
    elif kind == "zero_p":
        p1 = p0.copy()
    elif kind == "zero_both":
        p1, q1 = p0.copy(), q0.copy()
    elif kind == "shared":
        q0 = p1.copy()
    return p0, p1, q0, q1


@settings(max_examples=400, deadline=None)
@given(segment_pairs())
def test_segment_distance_matches_reference(seg):
    p0, p1, q0, q1 = seg
    s, t, c1, c2, d = segment_closest_points(p0, p1, q0, q1)
    assert 0.0 <= s[0] <= 1.0 and 0.0 <= t[0] <= 1.0
    np.testing.assert_allclose(c1[0], p0 + s[0] * (p1 - p0), atol=1e-12)
    np.testing.assert_allclose(c2[0], q0 + t[0] * (q1 - q0), atol=1e-12)
    assert d[0] == pytest.approx(np.linalg.norm(c1[0] - c2[0]), abs=1e-12)
    assert d[0] == pytest.approx(reference_distance(p0, p1, q0, q1), abs=1e-9)


@pytest.mark.parametrize("lift", [5.96e-8, 1e-9, 3e-7])
def test_nearly_parallel_segments_sharing_an_endpoint_touch(lift):
    """Hypothesis found it: two nearly antiparallel segments from one point were 'parallel' and the
    pair (p0, q1) was returned, |lift| away, instead of the shared point."""
    p0, p1, q0, q1 = np.array([1.0, 0, 0]), np.zeros(3), np.zeros(3), np.array([1.0, 0, lift])
    assert segment_closest_points(p0, p1, q0, q1)[4][0] == pytest.approx(0.0, abs=1e-15)
    # and along, with an offset: the distance is the offset, not offset + lift
    off = np.array([0.0, 2e-6, 0.0])
    assert segment_closest_points(p0, p1, q0 + off, q1 + off)[4][0] == pytest.approx(2e-6, rel=1e-9)


@settings(max_examples=60, deadline=None)
@given(segment_pairs())
def test_segment_distance_not_above_dense_sampling_and_scipy(seg):
    p0, p1, q0, q1 = seg
    d = segment_closest_points(p0, p1, q0, q1)[4][0]
    u = np.linspace(0.0, 1.0, 41)
    P = p0 + u[:, None] * (p1 - p0)
    Q = q0 + u[:, None] * (q1 - q0)
    dense = np.min(np.linalg.norm(P[:, None] - Q[None], axis=2))
    assert d <= dense + 1e-12
    res = minimize(lambda x: np.sum((p0 + x[0] * (p1 - p0) - q0 - x[1] * (q1 - q0)) ** 2), [0.5, 0.5],
                   bounds=[(0, 1), (0, 1)], method="L-BFGS-B", options={"ftol": 1e-15, "gtol": 1e-12})
    assert d <= np.sqrt(max(res.fun, 0.0)) + 1e-7


def test_segment_distance_vectorised_batch():
    rng = np.random.default_rng(1)
    p0, p1, q0, q1 = (rng.normal(size=(500, 3)) for _ in range(4))
    d = segment_closest_points(p0, p1, q0, q1)[4]
    ref = [reference_distance(*x) for x in zip(p0, p1, q0, q1)]
    np.testing.assert_allclose(d, ref, atol=1e-12)


# --------------------------------------------------------------------------- hand-made strands
def crossing_pair(h, x_cross=0.3e-2, n=11):
    """Strand 0 along x (z = 0), strand 1 along y at height h crossing it at x = x_cross."""
    a = line([-1e-2, 0, 0], [1e-2, 0, 0], n)
    b = line([x_cross, -1e-2, h], [x_cross, 1e-2, h], n)
    return ragged([a, b])


@pytest.mark.parametrize("x_cross", [0.3e-2, 0.2e-2, 0.0])  # inside a segment, at a vertex
def test_crossing_strands_one_contact(x_cross):
    h = 1.5 * RC
    c = detect_strand_contacts(*crossing_pair(h, x_cross), RC)
    assert len(c) == 1 and c.n_strand_strand == 1 and c.n_strand_head == 0
    assert (c.strand_a[0], c.strand_b[0]) == (0, 1)
    assert c.s_a[0] == pytest.approx(1e-2 + x_cross, abs=1e-12)
    assert c.s_b[0] == pytest.approx(1e-2, abs=1e-12)
    assert c.distance[0] == pytest.approx(h, rel=1e-9)
    np.testing.assert_allclose(c.normal[0], [0, 0, -1], atol=1e-12)  # from b (above) to a
    np.testing.assert_allclose(c.point_a[0], [x_cross, 0, 0], atol=1e-12)
    np.testing.assert_allclose(c.point_b[0], [x_cross, 0, h], atol=1e-12)
    np.testing.assert_allclose(c.frame[0, 0], c.normal[0])
    np.testing.assert_allclose(c.frame[0, 1], [1, 0, 0], atol=1e-12)  # strand a's tangent
    assert c.radius == RC


def test_crossing_strands_vertex_on_both():
    """Both strands have a vertex at the crossing: four segment pairs touch, one contact remains."""
    h = RC
    a = line([-1e-2, 0, 0], [1e-2, 0, 0], 11)
    b = line([0, -1e-2, h], [0, 1e-2, h], 11)
    pairs = close_segment_pairs(*ragged([a, b]), RC)
    assert len(pairs.i) == 4
    c = detect_strand_contacts(*ragged([a, b]), RC)
    assert len(c) == 1 and c.s_a[0] == pytest.approx(1e-2) and c.s_b[0] == pytest.approx(1e-2)


def test_no_contact_beyond_twice_the_radius():
    assert len(detect_strand_contacts(*crossing_pair(2.0001 * RC), RC)) == 0
    assert len(detect_strand_contacts(*crossing_pair(1.9999 * RC), RC)) == 1


def test_far_apart_strands_have_no_contacts():
    a = line([0, 0, 0], [1e-2, 0, 0], 20)
    b = a + [0, 0, 1e-3]
    c = a + [0, 5e-3, 0]
    assert len(detect_strand_contacts(*ragged([a, b, c]), RC)) == 0


def test_parallel_strands_one_contact_per_flat_valley():
    h = 1.2 * RC
    a = line([0, 0, 0], [1e-2, 0, 0], 11)
    b = line([0, h, 0], [1e-2, h, 0], 11)
    c = detect_strand_contacts(*ragged([a, b]), RC)
    assert len(c) == 1
    assert c.distance[0] == pytest.approx(h)
    np.testing.assert_allclose(c.normal[0], [0, -1, 0], atol=1e-12)
    # shifted sampling: still parallel, still one contact at distance h
    b2 = line([0.05e-2, h, 0], [1.05e-2, h, 0], 7)
    c2 = detect_strand_contacts(*ragged([a, b2]), RC)
    assert len(c2) == 1 and c2.distance[0] == pytest.approx(h)


def test_converging_strands_contact_at_closest_end():
    a = line([0, 0, 0], [1e-2, 0, 0], 11)
    b = line([0, 1.9 * RC, 0], [1e-2, 0.5 * RC, 0], 11)
    c = detect_strand_contacts(*ragged([a, b]), RC)
    assert len(c) == 1 and c.s_a[0] == pytest.approx(1e-2) and c.distance[0] == pytest.approx(0.5 * RC)


def test_same_strand_neighbours_are_skipped():
    # densely sampled (segments shorter than r_c), bent strand: every nearby pair is a neighbour
    u = np.linspace(0, 1, 400)
    strand = np.column_stack([1e-2 * u, 2e-3 * np.sin(6 * u), np.zeros_like(u)])
    assert len(detect_strand_contacts(*ragged([strand]), RC)) == 0
    # a sharp zig-zag: segments two apart are close but separated by less than pi r_c of arc
    zig = np.array([[0, 0, 0], [1e-4, 0, 0], [1e-4, 0.2e-4, 0], [0, 0.2e-4, 0]], float)
    assert len(detect_strand_contacts(*ragged([zig]), RC)) == 0


def self_crossing_strand(h, n_line=21, n_arc=41):
    """Diagonal, a half-turn loop, then back across the first diagonal at height h (1 cm scale)."""
    L = 1e-2
    first = line([-L, -L, 0], [L, L, 0], n_line)
    ang = np.linspace(np.pi / 2, -np.pi / 2, n_arc)[1:-1]
    loop = np.column_stack([L + L * np.cos(ang), L * np.sin(ang), h * (0.5 - ang / np.pi)])
    back = line([L, -L, h], [-L, L, h], n_line)
    return np.concatenate([first, loop, back])


def test_strand_touching_itself_far_along_is_found():
    h = 1.5 * RC
    strand = self_crossing_strand(h)
    pts, off, arc = ragged([strand])
    c = detect_strand_contacts(pts, off, arc, RC)
    assert len(c) == 1
    assert c.strand_a[0] == c.strand_b[0] == 0
    assert c.s_a[0] == pytest.approx(np.sqrt(2) * 1e-2, rel=1e-9)
    assert c.s_b[0] == pytest.approx(arc[-1] - np.sqrt(2) * 1e-2, rel=1e-9)
    assert c.distance[0] == pytest.approx(h, rel=1e-9)
    np.testing.assert_allclose(c.normal[0], [0, 0, -1], atol=1e-12)


def test_min_self_arc_controls_self_contacts():
    strand = self_crossing_strand(1.5 * RC)
    pts, off, arc = ragged([strand])
    assert len(detect_strand_contacts(pts, off, arc, RC, min_self_arc=arc[-1])) == 0


def test_resampling_does_not_change_contacts():
    """Inserting midpoints splits segments but the polylines, hence the contacts, are the same."""
    rng = np.random.default_rng(3)
    strands = [np.cumsum(rng.normal(scale=1e-3, size=(15, 3)), axis=0) for _ in range(30)]
    fine = [np.insert(s, np.arange(1, len(s)), 0.5 * (s[:-1] + s[1:]), axis=0) for s in strands]
    r = 2e-4
    c1 = detect_strand_contacts(*ragged(strands), r)
    c2 = detect_strand_contacts(*ragged(fine), r)
    assert len(c1) > 5
    assert len(c1) == len(c2)
    np.testing.assert_array_equal(c1.strand_a, c2.strand_a)
    np.testing.assert_array_equal(c1.strand_b, c2.strand_b)
    np.testing.assert_allclose(c1.distance, c2.distance, atol=1e-12)
    np.testing.assert_allclose(c1.s_a, c2.s_a, atol=1e-9)


def test_detection_is_deterministic_and_ordered():
    rng = np.random.default_rng(5)
    strands = [np.cumsum(rng.normal(scale=1e-3, size=(25, 3)), axis=0) for _ in range(40)]
    data = ragged(strands)
    c1 = detect_strand_contacts(*data, 3e-4)
    c2 = detect_strand_contacts(*data, 3e-4, cell_size=1e-3)
    for name in Contacts.ARRAYS:
        np.testing.assert_array_equal(getattr(c1, name), getattr(c2, name))
    key = np.lexsort((c1.s_b, c1.strand_b, c1.s_a, c1.strand_a))
    np.testing.assert_array_equal(key, np.arange(len(c1)))
    assert np.all(c1.strand_a <= c1.strand_b)
    assert np.all(c1.distance < 2 * 3e-4)
    np.testing.assert_allclose(np.linalg.norm(c1.normal, axis=1), 1.0)
    np.testing.assert_allclose(c1.point_a - c1.point_b, c1.normal * c1.distance[:, None], atol=1e-15)


# ---------------------------------------------------------------------- spatial hash vs brute force
def brute_force_pairs(points, offsets, arc, radius, min_self_arc):
    """Every segment pair tested; same-strand pairs minimised numerically under the arc constraint."""
    v0, strand = strand_segments(offsets)
    n = len(v0)
    i, j = np.triu_indices(n, 1)
    d = segment_closest_points(points[v0[i]], points[v0[i] + 1], points[v0[j]], points[v0[j] + 1])[4]
    for k in np.flatnonzero(strand[i] == strand[j]):
        d[k] = constrained_self_distance(points, arc, v0[i[k]], v0[j[k]], min_self_arc)
    close = d < 2 * radius
    return {(a, b): dd for a, b, dd in zip(i[close].tolist(), j[close].tolist(), d[close])}, d, i, j


def constrained_self_distance(points, arc, u, w, min_arc):
    """min |P(s) - Q(t)| over the unit square cut by s_b - s_a >= min_arc (inf when empty).

    The feasible set is a convex polygon (square clipped by a half-plane); the minimum of the
    convex distance is the free minimum if feasible, else on an edge: minimised in closed form.
    """
    p0, d1, q0, d2 = points[u], points[u + 1] - points[u], points[w], points[w + 1] - points[w]
    a0, la, b0, lb = arc[u], arc[u + 1] - arc[u], arc[w], arc[w + 1] - arc[w]

    def gap(x):
        return b0 + x[1] * lb - a0 - x[0] * la - min_arc

    def F(x):
        return p0 + x[0] * d1 - q0 - x[1] * d2

    square = [np.array(c, float) for c in ((0, 0), (1, 0), (1, 1), (0, 1))]
    poly = []
    for k in range(4):  # Sutherland-Hodgman against gap >= 0
        A, B = square[k], square[(k + 1) % 4]
        gA, gB = gap(A), gap(B)
        if gA >= 0:
            poly.append(A)
        if (gA >= 0) != (gB >= 0):
            poly.append(A + gA / (gA - gB) * (B - A))
    if not poly:
        return np.inf
    best = min(np.linalg.norm(F(x)) for x in poly)
    for k in range(len(poly)):
        A, B = poly[k], poly[(k + 1) % len(poly)]
        fa, df = F(A), F(B) - F(A)
        if df @ df > 0:
            lam = min(max(-(fa @ df) / (df @ df), 0.0), 1.0)
            best = min(best, np.linalg.norm(fa + lam * df))
    s, t, _, _, d = segment_closest_points(points[u], points[u + 1], points[w], points[w + 1])
    if gap((s[0], t[0])) >= 0:
        best = min(best, d[0])
    return best


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10**6), n_strands=st.integers(1, 12), radius=st.floats(2e-4, 2e-3),
       cell=st.sampled_from([None, 1e-4, 5e-4, 3e-3, 1.0]))
def test_spatial_hash_equals_brute_force(seed, n_strands, radius, cell):
    rng = np.random.default_rng(seed)
    strands = []
    for _ in range(n_strands):
        n = int(rng.integers(1, 12))
        strands.append(np.cumsum(rng.normal(scale=2e-3, size=(n, 3)), axis=0) + rng.uniform(-3e-3, 3e-3, 3))
    if rng.random() < 0.3:  # zero-length segments
        strands[0] = np.repeat(strands[0], 2, axis=0)
    pts, off, arc = ragged(strands)
    pairs = close_segment_pairs(pts, off, arc, radius, cell_size=cell)
    expected, d_all, i_all, j_all = brute_force_pairs(pts, off, arc, radius, np.pi * radius)
    got = dict(zip(zip(pairs.i.tolist(), pairs.j.tolist()), pairs.distance))
    assert len(got) == len(pairs.i)  # no pair twice
    borderline = {(a, b) for a, b, d in zip(i_all, j_all, d_all) if abs(d - 2 * radius) < 1e-9}
    assert set(got) - borderline == set(expected) - borderline
    for key, d in got.items():
        assert d == pytest.approx(d_all[(i_all == key[0]) & (j_all == key[1])][0], abs=1e-9)
    assert pairs.n_candidates >= len(got)


def reference_pairs(points, offsets, arc, radius):
    """The pairs of the segment-level hash that the grouped broad phase replaced, sorted by (i, j)."""
    ref = contact_reference.close_segment_pairs_reference(points, offsets, arc, radius)
    order = np.lexsort((ref.j, ref.i))
    return detect.SegmentPairs(ref.i[order], ref.j[order], ref.s[order], ref.t[order], ref.distance[order],
                               ref.n_candidates)


def random_groom(rng, n_strands, radius):
    """Random walks, near-parallel copies, U-turns and kinks on the scale of the contact radius."""
    step = radius * rng.uniform(0.5, 20.0)  # segments from shorter than r_c to long ones
    strands = []
    for _ in range(n_strands):
        kind = rng.choice(["walk", "parallel", "uturn", "kink"])
        n = int(rng.integers(2, 40))
        start = rng.uniform(-10 * radius, 10 * radius, 3)
        if kind == "walk" or not strands:
            strands.append(start + np.cumsum(rng.normal(scale=step, size=(n, 3)), axis=0))
        elif kind == "parallel":  # a copy of another strand, shifted about 2 r_c and jittered
            base = strands[int(rng.integers(len(strands)))]
            shift = rng.normal(size=3)
            shift *= rng.uniform(1.0, 2.5) * radius / np.linalg.norm(shift)
            strands.append(base + shift + rng.normal(scale=1e-3 * radius, size=base.shape))
        elif kind == "uturn":  # out and back along a half circle of diameter about 2 r_c
            leg = np.outer(np.arange(n), rng.normal(size=3) * step)
            turn = rng.uniform(0.5, 3.0) * radius * np.array([0.0, 1.0, 0.0])
            ang = np.linspace(0, np.pi, 9)[1:-1]
            bend = leg[-1] + 0.5 * turn + np.outer(np.cos(ang), -0.5 * turn) + np.outer(np.sin(ang), step * np.ones(3))
            strands.append(start + np.concatenate([leg, bend, leg[::-1] + turn]))
        else:  # sharp kinks: every other vertex pushed sideways
            pts = start + np.outer(np.arange(n), rng.normal(size=3) * step)
            pts[1::2] += rng.normal(scale=step, size=(len(pts[1::2]), 3))
            strands.append(pts)
    if rng.random() < 0.2:  # zero-length segments
        strands[0] = np.repeat(strands[0], 2, axis=0)
    return strands


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10**6), n_strands=st.integers(1, 25), radius=st.floats(1e-5, 1e-3),
       cell=st.sampled_from([None, None, 0.5, 2.0]))
def test_grouped_broad_phase_equals_segment_hash(seed, n_strands, radius, cell):
    """Same close pairs (bit for bit, sorted by segment pair) and same contacts as the segment-level
    hash it replaced, on random walks, near-parallel strands, U-turns and kinks."""
    strands = random_groom(np.random.default_rng(seed), n_strands, radius)
    pts, off, arc = ragged(strands)
    cell_size = None if cell is None else cell * 20 * radius
    pairs = close_segment_pairs(pts, off, arc, radius, cell_size=cell_size)
    ref = reference_pairs(pts, off, arc, radius)
    for name in ("i", "j", "s", "t", "distance"):
        np.testing.assert_array_equal(getattr(pairs, name), getattr(ref, name))
    got = detect_strand_contacts(pts, off, arc, radius)
    expected = contact_reference.detect_strand_contacts_reference(pts, off, arc, radius)
    for name in Contacts.ARRAYS:
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name))


# --------------------------------------------------------------------------------------- frames
unit_normals = st.tuples(coord, coord, coord).map(np.array).filter(lambda v: np.linalg.norm(v) > 1e-3)


@settings(max_examples=200, deadline=None)
@given(unit_normals, st.one_of(st.none(), st.tuples(coord, coord, coord).map(np.array)))
def test_frames_orthonormal_right_handed(n, tangent):
    F = contact_frames(n[None], None if tangent is None else tangent[None])[0]
    np.testing.assert_allclose(F @ F.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(F) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(F[0], n / np.linalg.norm(n), atol=1e-12)
    if tangent is not None:
        proj = tangent - (tangent @ F[0]) * F[0]
        if np.linalg.norm(proj) > 1e-3 * max(np.linalg.norm(tangent), 1e-300):
            # the expected direction normalised without underflow (|proj|^2 of a 1e-161 tangent is subnormal)
            scaled = proj / np.abs(proj).max()
            np.testing.assert_allclose(F[1], scaled / np.linalg.norm(scaled), atol=1e-9)


def test_frames_are_continuous_along_a_tangent():
    ang = np.linspace(0, np.pi, 200)
    n = np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)])
    F = contact_frames(n, np.tile([0, 0, 1.0], (200, 1)))
    assert np.max(np.linalg.norm(np.diff(F, axis=0), axis=2)) < 0.05
    with pytest.raises(ValueError):
        contact_frames(np.zeros((1, 3)))


# ------------------------------------------------------------------------------------- record
def test_contacts_record_helpers():
    c = detect_strand_contacts(*crossing_pair(RC), RC)
    e = Contacts.empty()
    assert len(e) == 0 and e.n_strand_strand == 0
    both = Contacts.concatenate([c, c, e])
    assert len(both) == 2 and both.radius == RC
    assert len(both.subset(np.array([True, False]))) == 1
    assert len(both.subset(np.array([1]))) == 1
    head = Contacts(np.array([3]), np.array([0.1]), np.array([HEAD]), np.array([np.nan]), np.zeros((1, 3)),
                    np.zeros((1, 3)), np.array([[0, 0, 1.0]]), np.eye(3)[None], np.array([0.0]))
    mixed = Contacts.concatenate([c, head])
    assert mixed.n_strand_strand == 1 and mixed.n_strand_head == 1
    np.testing.assert_array_equal(mixed.is_head, [False, True])
    with pytest.raises(ValueError):
        Contacts.concatenate([c, Contacts.empty(radius=2 * RC)])


def test_input_validation():
    pts, off, arc = crossing_pair(RC)
    with pytest.raises(ValueError):
        detect_strand_contacts(pts, off[:-1], arc, RC)
    with pytest.raises(ValueError):
        detect_strand_contacts(pts, off, arc[:-1], RC)
    with pytest.raises(ValueError):
        detect_strand_contacts(pts, off, arc, 0.0)
    one = ragged([np.zeros((1, 3))])
    assert len(detect_strand_contacts(*one, RC)) == 0


def test_detect_contacts_without_head_uses_default_radius():
    from groomtool.contact import DEFAULT_CONTACT_RADIUS

    c = detect_contacts(*crossing_pair(1.5 * DEFAULT_CONTACT_RADIUS))
    assert len(c) == 1 and c.radius == DEFAULT_CONTACT_RADIUS
    assert len(detect_contacts(*crossing_pair(1.5 * RC), strand_strand=False)) == 0


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10**6), n_strands=st.integers(1, 20), radius=st.floats(1e-5, 1e-3),
       spread=st.sampled_from([1.0, 1.5, 4.0]))
def test_one_radius_per_strand_is_the_largest_radius_filtered_by_the_pairs_threshold(seed, n_strands, radius,
                                                                                      spread):
    """The simulator's per-strand speculative margins: with radii r_s per strand, the close pairs are
    exactly those of the segment-level reference at max(r) whose distance is below r_a + r_b (same
    parameters, bit for bit), and the contacts those of max(r) below their own threshold."""
    rng = np.random.default_rng(seed)
    strands = random_groom(rng, n_strands, radius)
    pts, off, arc = ragged(strands)
    radii = radius * rng.uniform(1.0, spread, size=len(off) - 1)
    r_max = float(radii.max())
    seg_v0, seg_strand = detect.strand_segments(off)
    pairs = close_segment_pairs(pts, off, arc, radii, min_self_arc=np.pi * r_max)
    ref = contact_reference.close_segment_pairs_reference(pts, off, arc, r_max)
    order = np.lexsort((ref.j, ref.i))
    keep = ref.distance[order] < radii[seg_strand[ref.i[order]]] + radii[seg_strand[ref.j[order]]]
    for name in ("i", "j", "s", "t", "distance"):
        np.testing.assert_array_equal(getattr(pairs, name), getattr(ref, name)[order][keep])
    if spread > 1.0 and n_strands > 1:
        assert np.all(pairs.distance < 2.0 * r_max)
    got = detect_strand_contacts(pts, off, arc, radii)
    assert got.radius == r_max
    threshold = radii[got.strand_a] + radii[got.strand_b]
    assert np.all(got.distance < threshold)
    with pytest.raises(ValueError, match="one per strand"):
        close_segment_pairs(pts, off, arc, radii[:-1] if len(radii) > 1 else np.ones(3))
    with pytest.raises(ValueError, match="positive"):
        close_segment_pairs(pts, off, arc, -radii)
