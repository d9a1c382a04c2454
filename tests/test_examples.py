"""The bundled example groom: geometry, contact with the head, smoothness, determinism, files."""

import os

import numpy as np
import pytest
import trimesh

from groomtool import Groom
from groomtool.examples import FIBRE_RADIUS, HEAD_SEMI_AXES, LIFT, example_groom, write_example
from groomtool.io import load_groom, load_head, validate


@pytest.fixture(scope="module")
def example():
    return example_groom()


def turning_angles(strand: np.ndarray) -> np.ndarray:
    e = np.diff(strand, axis=0)
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    return np.arccos(np.clip(np.einsum("ij,ij->i", e[1:], e[:-1]), -1.0, 1.0))


def test_shape_of_the_groom(example):
    groom, head = example
    assert isinstance(groom, Groom) and groom.n_strands == 200 and groom.up == "y"
    assert groom.counts.min() >= 60 and groom.counts.max() <= 100
    lengths = groom.lengths()
    assert lengths.min() >= 0.2 - 1e-9 and lengths.max() <= 0.3 + 1e-9
    assert validate(groom) is groom  # finite, no repeated points
    kinds = groom.metadata["kinds"]
    assert 60 < kinds.count("curly") < 140 and kinds.count("wavy") == 200 - kinds.count("curly")
    # roots on the upper back of the head, strands hanging down from there
    roots, tips = groom.points[groom.offsets[:-1]], groom.points[groom.offsets[1:] - 1]
    assert np.all(roots[:, 1] > 0.05) and np.all(roots[:, 2] < 0)
    assert np.all(tips[:, 1] < roots[:, 1] - 0.1)
    assert np.all(groom.metadata["on_head"][groom.offsets[:-1]])  # every root lies on the head


def test_head_mesh(example):
    _, head = example
    assert head.is_watertight and head.is_winding_consistent and head.volume > 0
    np.testing.assert_allclose(head.bounds[1], HEAD_SEMI_AXES, rtol=1e-3)
    np.testing.assert_allclose(head.bounds[0], -HEAD_SEMI_AXES, rtol=1e-3)


def test_strands_rest_on_the_head_and_never_enter_it():
    groom, head = example_groom(n_strands=40, seed=3)
    on_head = groom.metadata["on_head"]
    assert 0.1 < on_head.mean() < 0.6
    _, distance, _ = trimesh.proximity.closest_point(head, groom.points)
    # the mesh is inscribed in the ellipsoid: outside the ellipsoid is outside the mesh
    assert np.all(np.sum((groom.points / HEAD_SEMI_AXES) ** 2, axis=1) > 1.0)
    # lying on the head: one fibre radius + 0.2 mm from the mesh (facets sit a little inside the ellipsoid)
    assert distance[on_head].min() >= LIFT - 1e-6
    assert distance[on_head].max() <= LIFT + 0.05e-3
    assert distance.min() >= LIFT - 1e-6 > FIBRE_RADIUS


def test_smooth_polylines(example):
    groom, _ = example
    seg = groom.segment_lengths()
    for i in range(groom.n_strands):
        s = seg[groom.offsets[i] - i : groom.offsets[i + 1] - i - 1]
        np.testing.assert_allclose(s, s.mean(), rtol=5e-3)  # uniform in arc length (chords of a curve)
        angles = turning_angles(groom.strand(i))
        assert angles.max() < 0.5  # at least ~12 vertices per wave or curl
        assert np.abs(np.diff(angles)).max() < 0.15  # curvature varies smoothly (no kinks where strands leave the head)


def test_curly_strands_coil(example):
    groom, _ = example
    kinds = np.array(groom.metadata["kinds"])
    ends = groom.points[groom.offsets[1:] - 1] - groom.points[groom.offsets[:-1]]
    straightness = np.linalg.norm(ends, axis=1) / groom.lengths()
    assert straightness[kinds == "curly"].max() < straightness[kinds == "wavy"].min()


def test_deterministic_for_a_seed():
    a, _ = example_groom(n_strands=20, seed=5)
    b, _ = example_groom(n_strands=20, seed=5)
    c, _ = example_groom(n_strands=20, seed=6)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.offsets, b.offsets)
    assert a.offsets.tolist() != c.offsets.tolist() or not np.array_equal(a.points, c.points)


def test_write_example(tmp_path):
    groom_path, head_path = write_example(tmp_path / "quickstart", n_strands=30)
    assert sorted(os.listdir(tmp_path / "quickstart")) == ["example.obj", "head.obj"]
    assert "\nl 1 2 3 " in groom_path.read_text()
    groom, head = example_groom(n_strands=30)
    loaded = load_groom(groom_path)
    np.testing.assert_array_equal(loaded.offsets, groom.offsets)
    np.testing.assert_allclose(loaded.points, groom.points, atol=1e-8)
    loaded_head = load_head(head_path)
    assert len(loaded_head.faces) == len(head.faces)
    np.testing.assert_allclose(loaded_head.bounds, head.bounds, atol=1e-7)
