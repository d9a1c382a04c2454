"""Strand/head contacts: signed distance to a mesh, contacts on a sphere, root gaps and snapping."""

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from groomtool.contact import (DEFAULT_CONTACT_RADIUS, HEAD, HeadSurface, detect_contacts, detect_head_contacts,
                               root_gaps, snap_roots)
from groomtool.contact import head as head_mod
from groomtool.contact.detect import strand_segments
from groomtool.groom import Groom
from groomtool.io import read_data
from reference import contact as contact_reference

R = 0.1  # sphere radius (m)
RC = 1e-4


def ragged(strands):
    g = Groom.from_strands(strands)
    return g.points, g.offsets, g.arc_lengths()


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=5, radius=R)


@pytest.fixture(scope="module")
def sphere_surface(sphere):
    return HeadSurface(sphere)


def brute_force_distance(mesh, points):
    tri = mesh.triangles
    out = np.empty(len(points))
    for k, p in enumerate(points):
        cp = trimesh.triangles.closest_point(tri, np.tile(p, (len(tri), 1)))
        out[k] = np.min(np.linalg.norm(cp - p, axis=1))
    return out


# ---------------------------------------------------------------------------------- signed distance
@pytest.mark.parametrize("make", [lambda: trimesh.creation.icosphere(2, radius=0.1),
                                  lambda: trimesh.creation.box((0.1, 0.2, 0.05)),
                                  lambda: trimesh.creation.torus(0.1, 0.03, major_sections=24, minor_sections=12)])
def test_signed_distance_matches_brute_force_and_contains(make):
    mesh = make()
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.15, 0.15, size=(300, 3))
    d, closest, normal, face = HeadSurface(mesh).query(pts)
    np.testing.assert_allclose(np.abs(d), brute_force_distance(mesh, pts), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(pts - closest, axis=1), np.abs(d), atol=1e-12)
    clear = np.abs(d) > 1e-6
    np.testing.assert_array_equal((d < 0)[clear], mesh.contains(pts)[clear])
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0)
    # the normal points out of the head: moving along it increases the signed distance
    d2 = HeadSurface(mesh).query(pts + 1e-6 * normal)[0]
    assert np.all(d2[clear] > d[clear])


def test_signed_distance_matches_trimesh_nearest(sphere, sphere_surface):
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(400, 3))
    pts *= (R * rng.uniform(0.5, 1.5, 400) / np.linalg.norm(pts, axis=1))[:, None]
    d = sphere_surface.query(pts)[0]
    _, d_tm, _ = trimesh.proximity.closest_point(sphere, pts)
    assert np.all(np.abs(d) <= d_tm + 1e-12)  # never worse than trimesh's nearest point
    same = np.isclose(np.abs(d), d_tm, atol=1e-9)
    assert same.mean() > 0.95
    # where trimesh's candidate search misses the nearest face, brute force agrees with us
    np.testing.assert_allclose(np.abs(d[~same]), brute_force_distance(sphere, pts[~same]), atol=1e-12)


def test_real_head_distances_match_trimesh(shared_data):
    mesh = trimesh.load(shared_data / "usc" / "head_model.obj", process=False)
    rng = np.random.default_rng(2)
    centre = mesh.bounds.mean(axis=0)
    pts = centre + rng.normal(scale=0.08, size=(300, 3))
    d = HeadSurface(mesh).query(pts)[0]
    _, d_tm, _ = trimesh.proximity.closest_point(mesh, pts)
    assert np.all(np.abs(d) <= d_tm + 1e-12)
    assert np.mean(np.isclose(np.abs(d), d_tm, atol=1e-9)) > 0.95


def test_unwelded_and_inward_meshes_give_the_same_answer(sphere_surface):
    mesh = trimesh.creation.icosphere(3, radius=R)
    soup = trimesh.Trimesh(mesh.triangles.reshape(-1, 3), np.arange(3 * len(mesh.faces)).reshape(-1, 3),
                           process=False)
    inward = trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
    pts = np.random.default_rng(3).uniform(-0.12, 0.12, size=(200, 3))
    ref = HeadSurface(mesh).query(pts)[0]
    np.testing.assert_allclose(HeadSurface(soup).query(pts)[0], ref, atol=1e-14)
    flipped = HeadSurface(inward)
    assert flipped.flipped
    np.testing.assert_allclose(flipped.query(pts)[0], ref, atol=1e-14)


def test_open_mesh_rim_counts_as_outside():
    bowl_src = trimesh.creation.icosphere(3, radius=R)
    keep = bowl_src.triangles_center[:, 2] > 0.0
    bowl = trimesh.Trimesh(bowl_src.vertices, bowl_src.faces[keep], process=False)
    d = HeadSurface(bowl).query(np.array([[0, 0, -2 * R], [0, 0, 0.5 * R], [0, 0, 2 * R]]))[0]
    assert d[0] > 0 and d[1] < 0 and d[2] > 0


# ---------------------------------------------------------------------------------- head contacts
def test_tangent_strand_on_sphere_one_radial_contact(sphere_surface):
    gap = 0.5 * RC
    x = np.linspace(-0.05, 0.07, 13)  # tangent point at x = 0 lies inside a segment
    strand = np.column_stack([x, np.zeros_like(x), np.full_like(x, R + gap)])
    pts, off, arc = ragged([strand])
    c = detect_head_contacts(pts, off, arc, sphere_surface, RC)
    assert len(c) == 1 and c.n_strand_head == 1
    assert c.strand_b[0] == HEAD and np.isnan(c.s_b[0])
    assert c.s_a[0] == pytest.approx(0.05, abs=2e-3)
    assert gap - 1e-9 <= c.distance[0] <= gap + 1e-5  # faceting: the mesh lies inside the sphere
    radial = c.point_a[0] / np.linalg.norm(c.point_a[0])
    assert np.arccos(np.clip(c.normal[0] @ radial, -1, 1)) < 0.03
    np.testing.assert_allclose(c.point_a[0] - c.point_b[0], c.normal[0] * c.distance[0], atol=1e-12)
    F = c.frame[0]
    np.testing.assert_allclose(F @ F.T, np.eye(3), atol=1e-12)
    assert c.radius == RC


def test_strand_wrapped_on_sphere_normals_are_radial(sphere_surface):
    ang = np.linspace(0.2, 2.0, 60)
    strand = (R + 0.3 * RC) * np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)])
    pts, off, arc = ragged([strand])
    c = detect_head_contacts(pts, off, arc, sphere_surface, RC)
    assert len(c) >= 1
    radial = c.point_a / np.linalg.norm(c.point_a, axis=1, keepdims=True)
    assert np.all(np.einsum("ij,ij->i", c.normal, radial) > np.cos(0.03))
    assert np.all(c.distance < RC) and np.all(np.diff(c.s_a) >= 4 * RC)


def test_penetrating_strand_reports_negative_distance(sphere_surface):
    depth = 2e-3
    x = np.linspace(-0.05, 0.05, 11)
    strand = np.column_stack([x, np.zeros_like(x), np.full_like(x, R - depth)])
    pts, off, arc = ragged([strand])
    c = detect_head_contacts(pts, off, arc, sphere_surface, RC)
    assert len(c) == 1
    assert c.distance[0] == pytest.approx(-depth, abs=1e-5)
    np.testing.assert_allclose(c.normal[0], [0, 0, 1], atol=0.03)  # outward, pushing the strand out


def test_no_head_contacts_when_far_or_at_the_root(sphere_surface):
    far = np.column_stack([np.linspace(0, 0.05, 10), np.zeros(10), np.full(10, R + 1e-2)])
    root_out = np.array([[0, 0, R], [0, 0, R + 0.02], [0, 0, R + 0.04]])  # from the scalp outwards
    pts, off, arc = ragged([far, root_out])
    assert len(detect_head_contacts(pts, off, arc, sphere_surface, RC)) == 0


def test_detect_contacts_combines_both_kinds(sphere):
    h = 1.5 * RC
    x = np.linspace(-0.02, 0.02, 11)
    a = np.column_stack([x, np.zeros_like(x), np.full_like(x, R + 0.5 * RC)])
    b = np.column_stack([np.full_like(x, 0.003), x, np.full_like(x, R + 0.5 * RC + h)])
    pts, off, arc = ragged([a, b])
    c = detect_contacts(pts, off, arc, RC, head=sphere)
    assert c.n_strand_strand == 1 and c.n_strand_head >= 1
    assert np.all(c.is_head[c.n_strand_strand:])
    head_only = detect_contacts(pts, off, arc, RC, head=sphere, strand_strand=False)
    assert head_only.n_strand_strand == 0 and head_only.n_strand_head == c.n_strand_head
    assert len(detect_contacts(pts, off, arc, RC, head=sphere, head_radius=1e-9).subset(c.is_head[:0])) == 0
    assert detect_contacts(pts, off, arc, head=sphere).radius == DEFAULT_CONTACT_RADIUS


def test_detect_contacts_reports_its_passes(sphere):
    """A progress bar is advanced once per pass and told which pass runs."""
    class Bar:
        def __init__(self):
            self.n, self.names = 0, []

        def update(self, k):
            self.n += k

        def set_postfix_str(self, name):
            self.names.append(name)

    x = np.linspace(-0.02, 0.02, 11)
    pts, off, arc = ragged([np.column_stack([x, np.zeros_like(x), np.full_like(x, R + 0.5 * RC)])])
    bar = Bar()
    detect_contacts(pts, off, arc, RC, head=sphere, progress=bar)
    assert bar.n == 2 and bar.names == ["strand/strand", "head"]
    bar = Bar()
    detect_contacts(pts, off, arc, RC, head=None, progress=bar)
    assert bar.n == 1 and bar.names == ["strand/strand"]


# ----------------------------------------------------------------------------------------- roots
def test_root_gaps_and_snapping(sphere, sphere_surface):
    rng = np.random.default_rng(4)
    dirs = rng.normal(size=(50, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    offsets = rng.uniform(-5e-3, 5e-3, 50)
    roots = dirs * (R + offsets)[:, None]
    gaps = root_gaps(roots, sphere)
    np.testing.assert_allclose(gaps, offsets, atol=5e-5)  # faceting: the mesh lies inside the sphere
    snapped, gaps2 = snap_roots(roots, sphere_surface)
    np.testing.assert_array_equal(gaps, gaps2)
    np.testing.assert_allclose(root_gaps(snapped, sphere_surface), 0.0, atol=1e-12)
    lifted, _ = snap_roots(roots, sphere_surface, offset=4e-5)
    np.testing.assert_allclose(root_gaps(lifted, sphere_surface), 4e-5, atol=1e-12)


# ---------------------------------------------------------------------------------------- real data


def test_real_groom_subset(shared_data):
    strands = list(read_data(shared_data / "digital-salon" / "harolongo.data", scale=0.01).strands())[::20]  # cm -> m
    mesh = trimesh.load(shared_data / "digital-salon" / "Retopologised_Female_Head_01_mod.obj", process=False)
    mesh.apply_scale(0.01)
    pts, off, arc = ragged(strands)
    stats = {}
    c = detect_contacts(pts, off, arc, head=mesh, stats=stats)
    assert c.n_strand_strand > 0 and c.n_strand_head > 0
    assert stats["candidates"] >= stats["close_pairs"] >= stats["local_minima"] >= stats["strand_contacts"]
    F = c.frame
    np.testing.assert_allclose(np.einsum("mij,mkj->mik", F, F), np.broadcast_to(np.eye(3), F.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(F), 1.0, atol=1e-9)
    ss = ~c.is_head
    assert np.all(c.distance[ss] < 2 * c.radius) and np.all(c.distance[~ss] < c.radius)
    v = HeadSurface(mesh).query(pts[:2000])[0]
    _, d_tm, _ = trimesh.proximity.closest_point(mesh, pts[:2000])
    assert np.all(np.abs(v) <= d_tm + 1e-12)


# ------------------------------------------------------- bounded detection == reference, bit for bit
# ``detect_head_contacts`` queries only the vertices whose distance bounds cannot rule them out;
# ``_detect_head_contacts_reference`` (the previous implementation) queries every vertex in the box.

FIELDS = ("strand_a", "s_a", "strand_b", "s_b", "point_a", "point_b", "normal", "frame", "distance")


def assert_same_contacts(pts, off, arc, surface, radius, **kw):
    """Both implementations, every field bit for bit, and the shared counters; returns the new stats."""
    new_stats, ref_stats = {}, {}
    new = detect_head_contacts(pts, off, arc, surface, radius, stats=new_stats, **kw)
    ref = contact_reference.detect_head_contacts_reference(pts, off, arc, surface, radius, stats=ref_stats, **kw)
    for name in FIELDS:
        a, b = np.asarray(getattr(new, name)), np.asarray(getattr(ref, name))
        assert a.shape == b.shape, name
        assert np.array_equal(a, b, equal_nan=True), name
    assert new.radius == ref.radius
    for key in ("head_vertices_inside", "head_candidates", "head_minima", "head_contacts"):
        assert new_stats[key] == ref_stats[key], key
    assert new_stats["head_vertices_in_box"] == ref_stats["head_vertices_queried"]
    assert new_stats["head_vertices_queried"] + new_stats["head_vertices_bounded"] == new_stats["head_vertices_in_box"]
    return new_stats


def assert_bounds_hold(pts, off, surface, radius):
    """The vertex pass: exact values equal the reference's per-vertex distances bit for bit, and
    every bounded vertex's reference distance is at least its bound.  Returns the bounded count."""
    max_seg = head_mod._max_segment(pts, off)
    ref = contact_reference.vertex_signed_distances(pts, off, surface, radius + max_seg)
    lo, hi = surface.bounds
    in_box = head_mod._in_box_kernel(pts, lo - (radius + max_seg), hi + (radius + max_seg))
    ok, guard = surface._sign_info()
    val, exact, _, n_bounded = head_mod._strand_bounds_kernel(
        pts, off, in_box, surface._bvh, surface._triangle_boxes(), np.full(len(off) - 1, radius), max_seg, ok, guard,
        1e-12 * (1.0 + float(np.max(np.abs(surface.bounds)))))
    np.testing.assert_array_equal(np.isfinite(ref), in_box)
    assert np.array_equal(val[exact], ref[exact])
    assert np.all(ref[~exact] >= val[~exact]) and np.all(val[~exact] > radius)
    return n_bounded


def _curve(a, b, n, sag=0.0, normal=(0.0, 0.0, 1.0)):
    t = np.linspace(0.0, 1.0, n)[:, None]
    return (1 - t) * np.asarray(a, float) + t * np.asarray(b, float) + sag * 4 * t * (1 - t) * np.asarray(normal)


def sphere_strands(rc, rng):
    """Strands around the sphere of radius R at the origin: dipping, grazing, crossing, far, rooted
    on the surface, with repeated vertices, leaving and re-entering the box, single vertices."""
    out = []
    for depth in (-3e-3, -2 * rc, -0.3 * rc, 0.0, 0.4 * rc, 0.99 * rc, 1.01 * rc, 3 * rc, 2e-2):
        z = R + depth  # a chord whose closest approach to the centre is at z, dense and coarse
        for n in (7, 40, 400):
            out.append(_curve([-0.06, 0.01, z], [0.07, -0.01, z], n))
    out.append(_curve([-0.2, 0.0, 0.0], [0.2, 0.003, 0.001], 120))  # through the whole head
    out.append(_curve([0.0, -0.3, 0.2], [0.01, 0.3, 0.2], 50))  # far, long
    out.append(_curve([0.3, 0.3, 0.3], [0.4, 0.3, 0.3], 5))  # outside the box
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    root = R * d  # rooted on the surface, going out, coming back to graze far along
    side = np.cross(d, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    ang = np.linspace(0.0, 1.2, 300)
    lift = 0.004 * np.sin(np.pi * ang / 1.2) ** 2 + 0.5 * rc * ang / 1.2
    out.append((R + lift)[:, None] * (np.cos(ang)[:, None] * d + np.sin(ang)[:, None] * side))
    out[-1][0] = root
    rep = _curve([-0.05, 0.0, R + 0.5 * rc], [0.05, 0.0, R + 0.5 * rc], 21)
    out.append(np.repeat(rep, [1, 2, 1, 3] + [1] * 13 + [2, 1, 1, 4], axis=0))  # zero-length segments
    out.append(np.tile([[0.0, 0.0, R + 0.2 * rc]], (5, 1)))  # one point, five times
    out.append(np.array([[0.0, 0.0, R - 1e-3]]))  # a single vertex
    out.append(_curve([-0.12, 0.0, 0.05], [0.12, 0.0, 0.05], 30, sag=0.2, normal=(0, 0, 1.0)))  # leaves the box
    for _ in range(12):  # random walks near the surface
        p = rng.normal(size=3)
        p *= (R + rng.uniform(-2e-3, 4e-3)) / np.linalg.norm(p)
        steps = rng.normal(size=(rng.integers(2, 200), 3)) * rng.choice([rc, 1e-3, 5e-3])
        out.append(p + np.cumsum(steps, axis=0))
    return out


@pytest.mark.parametrize("rc", [RC, DEFAULT_CONTACT_RADIUS, 2e-3])
def test_bounded_equals_reference_on_a_sphere(sphere_surface, rc):
    pts, off, arc = ragged(sphere_strands(rc, np.random.default_rng(11)))
    stats = assert_same_contacts(pts, off, arc, sphere_surface, rc)
    assert stats["head_contacts"] > 10 and stats["head_vertices_bounded"] > 0
    assert assert_bounds_hold(pts, off, sphere_surface, rc) > 0
    assert_same_contacts(pts, off, arc, sphere_surface, rc, min_root_arc=0.0, merge_arc=0.0)
    assert_same_contacts(pts, off, arc, sphere_surface, rc, min_root_arc=0.02, merge_arc=0.01)


def test_bounded_equals_reference_on_a_box_with_exact_ties():
    """Axis-aligned faces: points equidistant from several faces, closest points on shared edges."""
    surface = HeadSurface(trimesh.creation.box((0.1, 0.2, 0.05)))
    rng = np.random.default_rng(12)
    strands = [_curve([-0.08, y, z], [0.08, y, z], n) for y in (0.0, 0.1 - 3e-5, 0.12)
               for z in (0.025 + 3e-5, 0.025, 0.0125, 0.0, 0.03) for n in (9, 161)]
    strands += [_curve([-0.05, -0.1, 0.025], [0.05, 0.1, 0.025 + 4e-5], 99),  # along the top face
                _curve([0.05 + 2e-5, -0.12, 0.0], [0.05 + 2e-5, 0.12, 0.03], 77)]  # grazes an edge
    strands += [p + np.cumsum(rng.normal(size=(100, 3)) * 2e-3, axis=0) for p in rng.uniform(-0.05, 0.05, (15, 3))]
    pts, off, arc = ragged(strands)
    stats = assert_same_contacts(pts, off, arc, surface, RC)
    assert stats["head_contacts"] > 10 and stats["head_vertices_inside"] > 0
    assert assert_bounds_hold(pts, off, surface, RC) > 0


def test_open_mesh_is_guarded_at_its_hole():
    """A bowl open at the bottom: a strand rising from far below through the opening into the dome
    never crosses the surface, yet its sign flips (outside, rim closest -> inside, dome closest).
    The guard box around the hole keeps the bounds off that path; without it they would be wrong."""
    src = trimesh.creation.icosphere(4, radius=R)
    bowl = trimesh.Trimesh(src.vertices, src.faces[src.triangles_center[:, 2] > -0.3 * R], process=False)
    surface = HeadSurface(bowl)
    ok, guard = surface._sign_info()
    assert ok and len(guard) == 1
    strands = [_curve([x, 0.01, -0.6], [x, 0.0, 0.5 * R], 400) for x in (0.0, 0.03, 0.06)]
    strands += [_curve([0.0, 0.0, -0.6], [0.0, 0.0, R + 2e-3], 300, sag=0.02, normal=(1, 0, 0))]
    strands += [_curve([-0.15, 0.0, 0.05], [0.15, 0.0, 0.05], 300)]  # in and out through the dome's wall
    pts, off, arc = ragged(strands)
    stats = assert_same_contacts(pts, off, arc, surface, RC)
    assert stats["head_vertices_inside"] > 0 and stats["head_vertices_bounded"] > 0
    assert_bounds_hold(pts, off, surface, RC)
    # without the guard the sign carried up from below is wrong inside the dome
    unguarded = HeadSurface(bowl)
    unguarded._sign_cache = (True, np.zeros((0, 15)))
    wrong = detect_head_contacts(pts, off, arc, unguarded, RC)
    right = contact_reference.detect_head_contacts_reference(pts, off, arc, surface, RC)
    assert len(wrong) < len(right)


def test_meshes_whose_sign_cannot_be_carried():
    """Two components (a sphere inside a sphere), an inconsistently oriented face, an edge in three
    faces, two sheets pinched at a vertex: the bounds are not used (every vertex queried), the result
    is unchanged."""
    outer = trimesh.creation.icosphere(3, radius=R)
    inner = trimesh.creation.icosphere(2, radius=0.3 * R)
    nested = trimesh.util.concatenate([outer, inner])
    flipped = outer.faces.copy()
    flipped[0] = flipped[0, ::-1]
    fin = np.vstack([outer.faces, [[outer.faces[0, 0], outer.faces[0, 1], len(outer.vertices)]]])
    fin_vertices = np.vstack([outer.vertices, [[0.0, 0.0, 2 * R]]])
    top, bottom = np.argmax(outer.vertices[:, 2]), np.argmin(outer.vertices[:, 2])
    pinched_vertices = outer.vertices.copy()
    pinched_vertices[bottom] = pinched_vertices[top] = [0.0, 0.0, 0.0]  # the poles meet at the centre
    rng = np.random.default_rng(13)
    strands = [p + np.cumsum(rng.normal(size=(150, 3)) * 2e-3, axis=0)
               for p in rng.normal(size=(20, 3)) * 0.4 * R]
    strands += [_curve([-0.2, 0.0, 0.0], [0.2, 0.0, 0.001], 200),
                _curve([0.0, -0.2, 0.3 * R + 3e-5], [0.0, 0.2, 0.3 * R], 300)]
    pts, off, arc = ragged(strands)
    for mesh in (nested, (outer.vertices, flipped), (fin_vertices, fin), (pinched_vertices, outer.faces)):
        surface = HeadSurface(mesh)
        assert surface._sign_info()[0] is False
        stats = assert_same_contacts(pts, off, arc, surface, RC)
        assert stats["head_vertices_bounded"] == 0
    assert HeadSurface(outer)._sign_info()[0] is True and len(HeadSurface(outer)._sign_info()[1]) == 0


def test_empty_and_degenerate_inputs(sphere_surface):
    for strands in ([np.zeros((1, 3))], [np.tile([[0.0, 0.0, R]], (3, 1))]):
        pts, off, arc = ragged(strands)
        assert_same_contacts(pts, off, arc, sphere_surface, RC)
    off = np.array([0, 0, 3, 3, 5])  # empty strands between real ones
    pts = np.array([[0, 0, R + 1e-2], [0, 0, R - 1e-3], [0, 0.001, R + 1e-2], [0, 0, R - 1e-3], [0, 0.01, R - 1e-3]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts[0:3], axis=0), axis=1)),
                          [0.0, np.linalg.norm(pts[4] - pts[3])]])
    assert_same_contacts(pts.astype(float), off, arc, sphere_surface, RC)


def test_fast_helpers_match_the_reference_arithmetic():
    rng = np.random.default_rng(14)
    lo = rng.uniform(-1, 1, (50, 3))
    box = np.ascontiguousarray(np.hstack([lo, lo + rng.uniform(0, 0.5, (50, 3))]))
    pts = np.vstack([rng.uniform(-1.5, 1.5, (200, 3)), box[:, :3], box[:, 3:]])  # on the faces too
    for i in range(len(box)):
        for p in pts:
            assert head_mod._box_gap2(box, i, *p) == head_mod._box_dist2(box, i, *p)
    pts, off, arc = ragged([rng.normal(size=(n, 3)) for n in (1, 2, 30, 5)])
    seg_v0, _ = strand_segments(off)
    assert head_mod._max_segment(pts, off) == np.max(np.linalg.norm(pts[seg_v0 + 1] - pts[seg_v0], axis=1))


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10**6), n_strands=st.integers(1, 12), rc=st.sampled_from([2e-5, RC, 1e-3]),
       step=st.sampled_from([3e-5, 5e-4, 3e-3, 2e-2]), shape=st.sampled_from(["sphere", "box", "bowl"]))
def test_bounded_equals_reference_property(seed, n_strands, rc, step, shape, sphere_surface):
    surface = {"sphere": sphere_surface, "box": _BOX, "bowl": _BOWL}[shape]
    rng = np.random.default_rng(seed)
    strands = []
    for _ in range(n_strands):
        p = rng.normal(size=3)
        p *= R * rng.uniform(0.8, 1.3) / np.linalg.norm(p)
        drift = rng.normal(size=3) * step
        strands.append(p + np.cumsum(drift + rng.normal(size=(rng.integers(1, 120), 3)) * step, axis=0))
    pts, off, arc = ragged(strands)
    assert_same_contacts(pts, off, arc, surface, rc)
    assert_bounds_hold(pts, off, surface, rc)


_BOX = HeadSurface(trimesh.creation.box((0.15, 0.2, 0.1)))
_BOWL_SRC = trimesh.creation.icosphere(3, radius=R)
_BOWL = HeadSurface(trimesh.Trimesh(_BOWL_SRC.vertices, _BOWL_SRC.faces[_BOWL_SRC.triangles_center[:, 1] < 0.5 * R],
                                    process=False))


def _densify(strands, k):
    """k points per original segment (linear), like sampling a fitted curve densely."""
    out = []
    for s in strands:
        t = np.linspace(0.0, 1.0, k, endpoint=False)
        dense = (s[:-1, None, :] * (1 - t)[None, :, None] + s[1:, None, :] * t[None, :, None]).reshape(-1, 3)
        out.append(np.vstack([dense, s[-1:]]))
    return out


def test_bounded_equals_reference_on_real_grooms(shared_data):
    """A few hundred harolongo strands (8 points per original segment, as dense as the inversion
    samples them) against its open head, and USC styles against the closed USC head."""
    strands = list(read_data(shared_data / "digital-salon" / "harolongo.data", scale=0.01).strands())[::25]
    mesh = trimesh.load(shared_data / "digital-salon" / "Retopologised_Female_Head_01_mod.obj", process=False)
    mesh.apply_scale(0.01)
    surface = HeadSurface(mesh)
    ok, guard = surface._sign_info()
    assert ok and len(guard) == 2  # the neck and a second hole
    pts, off, arc = ragged(_densify(strands, 8))
    stats = assert_same_contacts(pts, off, arc, surface, DEFAULT_CONTACT_RADIUS)
    assert stats["head_contacts"] > 100 and stats["head_vertices_bounded"] > 0.2 * stats["head_vertices_in_box"]
    assert_bounds_hold(pts, off, surface, DEFAULT_CONTACT_RADIUS)

    usc = HeadSurface(trimesh.load(shared_data / "usc" / "head_model.obj", process=False))
    assert usc._sign_info()[0] and len(usc._sign_info()[1]) == 0  # closed
    files = sorted((shared_data / "usc" / "cstrands").glob("*.data"))[::40]
    strands = [s for f in files for s in read_data(f).strands()]
    pts, off, arc = ragged(strands)
    for rc in (DEFAULT_CONTACT_RADIUS, 1e-3):
        stats = assert_same_contacts(pts, off, arc, usc, rc)
        assert stats["head_contacts"] > 0 and stats["head_vertices_bounded"] > 0.3 * stats["head_vertices_in_box"]
    assert_bounds_hold(pts, off, usc, DEFAULT_CONTACT_RADIUS)


def test_search_among_candidates_equals_tree_search():
    """``_signed_among`` (any order of the faces, exact ties resolved by sign) gives the tree
    search's value bit for bit, also at points equidistant from several faces of a box, and
    ``_segment_candidates`` holds the closest face of every point of a segment within reach."""
    rng = np.random.default_rng(15)
    for mesh in (trimesh.creation.box((0.1, 0.2, 0.05)), trimesh.creation.icosphere(2, radius=R)):
        surface = HeadSurface(mesh)
        bvh, tri_box = surface._bvh, surface._triangle_boxes()
        n_face = len(bvh[3])
        pts = np.vstack([rng.uniform(-0.12, 0.12, (300, 3)), np.zeros((1, 3)),
                         np.column_stack([rng.uniform(-0.1, 0.1, (50, 2)), np.zeros(50)]),  # symmetry planes
                         np.column_stack([np.zeros(50), rng.uniform(-0.1, 0.1, (50, 2))]),
                         rng.integers(-2, 3, (100, 3)) * 0.0125])
        for order in (np.arange(n_face), rng.permutation(n_face), np.arange(n_face)[::-1]):
            order = np.ascontiguousarray(order, dtype=np.int64)
            for p in pts:
                ref = head_mod._signed_point(p[0], p[1], p[2], bvh, np.inf)[0]
                assert head_mod._signed_among(p[0], p[1], p[2], bvh, tri_box, np.inf, order, n_face) == ref
        for _ in range(100):
            a = rng.uniform(-0.12, 0.12, 3)
            b = a + rng.normal(size=3) * rng.choice([1e-4, 1e-3, 3e-2])
            da, db = (head_mod._signed_point(*q, bvh, np.inf)[0] for q in (a, b))
            length = np.linalg.norm(b - a)
            cand, n = head_mod._segment_candidates(a, b, 0.5 * (abs(da) + abs(db) + length), bvh[0], bvh[1],
                                                   bvh[2], tri_box, np.empty(4, np.int64))
            for x in np.linspace(0.0, 1.0, 23):
                q = a + x * (b - a)
                face = head_mod._signed_point(*q, bvh, np.inf)[7]
                assert face in cand[:n]
                assert head_mod._signed_among(*q, bvh, tri_box, min(abs(da) + x * length, abs(db) + (1 - x) * length),
                                              cand, n) == head_mod._signed_point(*q, bvh, np.inf)[0]


def test_one_radius_per_strand_equals_each_strand_detected_with_its_own(sphere_surface):
    """Head detection is strand by strand: with one radius per strand (the simulator's per-strand
    speculative margins) every strand gets exactly the contacts of a pass at its own radius."""
    rng = np.random.default_rng(5)
    strands = sphere_strands(RC, rng)
    pts, off, arc = ragged(strands)
    radii = RC * rng.choice([0.5, 1.0, 3.0, 10.0], size=len(off) - 1)
    kw = dict(min_root_arc=np.pi * RC, merge_arc=4.0 * RC)
    got = detect_head_contacts(pts, off, arc, sphere_surface, radii, **kw)
    assert got.radius == float(radii.max())
    total = 0
    for s in range(len(off) - 1):
        p, o, a = ragged([strands[s]])
        one = detect_head_contacts(p, o, a, sphere_surface, float(radii[s]), **kw)
        mine = got.strand_a == s
        total += len(one.strand_a)
        # (arc lengths of one strand alone differ from the groom's in the last bit, the refinement follows)
        np.testing.assert_allclose(got.s_a[mine], one.s_a, rtol=1e-9, atol=0)
        np.testing.assert_allclose(got.distance[mine], one.distance, rtol=1e-9, atol=1e-15)
    assert total == len(got.strand_a) > 10
    assert len(np.unique(radii[got.strand_a])) > 1  # several radii took part
