"""Strand/head contacts: signed distance to a mesh, contacts on a sphere, root gaps and snapping."""

import numpy as np
import pytest
import trimesh

from groomtool.contact import (DEFAULT_CONTACT_RADIUS, HEAD, HeadSurface, detect_contacts, detect_head_contacts,
                               root_gaps, snap_roots)
from groomtool.groom import Groom
from groomtool.io import read_data

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
