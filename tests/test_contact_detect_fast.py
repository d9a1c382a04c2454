"""The fast strand/strand and strand/head kernels against the references they replaced (bit for bit):
random strand sets with random per-strand thresholds (the simulator's speculative margins), the
close-pairs kernel resuming when its output arrays fill up, and real grooms."""

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from groomtool.contact import Contacts, HeadSurface, close_segment_pairs, detect_head_contacts, detect_strand_contacts
from groomtool.contact import detect
from groomtool.groom import Groom
from groomtool.io import read_data
from reference import contact as contact_reference
from test_contact_detect import random_groom


def ragged(strands):
    g = Groom.from_strands(strands)
    return g.points, g.offsets, g.arc_lengths()


def assert_same(got, expected):
    for name in Contacts.ARRAYS:
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name), err_msg=name)
    assert got.radius == expected.radius


def assert_same_pairs(pairs, ref):
    for name in ("i", "j", "s", "t", "distance"):
        np.testing.assert_array_equal(getattr(pairs, name), getattr(ref, name), err_msg=name)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10**6), n_strands=st.integers(1, 30), radius=st.floats(1e-5, 1e-3),
       spread=st.sampled_from([1.0, 1.3, 3.0]), capacity=st.sampled_from([1, 7, 4096]),
       self_arc=st.sampled_from([None, 0.5, 3.0]))
def test_strand_contacts_equal_the_reference_with_random_thresholds(seed, n_strands, radius, spread, capacity,
                                                                     self_arc):
    """Random walks, near-parallel copies, U-turns and kinks with one random radius per strand: the
    close pairs and the contacts are the reference's bit for bit, whatever the size of the kernel's
    output arrays (tiny ones make it resume many times)."""
    rng = np.random.default_rng(seed)
    pts, off, arc = ragged(random_groom(rng, n_strands, radius))
    radii = radius * rng.uniform(1.0, spread, size=len(off) - 1)
    r_max = float(radii.max())
    min_self_arc = None if self_arc is None else self_arc * np.pi * r_max
    with pytest.MonkeyPatch.context() as m:
        m.setattr(detect, "_MIN_CAPACITY", capacity)
        m.setattr(detect, "_PAIRS_PER_SEGMENT", [0.0])
        pairs = close_segment_pairs(pts, off, arc, radii, min_self_arc=min_self_arc)
        m.setattr(detect, "_PAIRS_PER_SEGMENT", [0.0])
        got = detect_strand_contacts(pts, off, arc, radii, min_self_arc=min_self_arc)
    assert_same_pairs(pairs, contact_reference.close_segment_pairs_per_strand_reference(
        pts, off, arc, radii, min_self_arc=min_self_arc))
    assert_same(got, contact_reference.detect_strand_contacts_reference(pts, off, arc, radii,
                                                                       min_self_arc=min_self_arc))


def test_resumption_is_exercised_and_changes_nothing():
    """A dense tangle whose pairs overflow a tiny output many times: same pairs as with room for all."""
    rng = np.random.default_rng(3)
    pts, off, arc = ragged([np.cumsum(rng.normal(scale=2e-4, size=(60, 3)), axis=0) for _ in range(12)])
    with pytest.MonkeyPatch.context() as m:
        m.setattr(detect, "_MIN_CAPACITY", 1)
        m.setattr(detect, "_PAIRS_PER_SEGMENT", [0.0])
        calls = []
        kernel = detect._close_pairs_kernel
        m.setattr(detect, "_close_pairs_kernel", lambda *a: calls.append(1) or kernel(*a))
        small = close_segment_pairs(pts, off, arc, 3e-4)
    big = close_segment_pairs(pts, off, arc, 3e-4)
    assert len(calls) > 5 and len(small.i) > 100
    assert_same_pairs(small, big)
    assert (small.n_candidates, small.n_group_pairs) == (big.n_candidates, big.n_group_pairs)


def test_crossing_strands_with_sub_radius_segments():
    """Many segment pairs per contact (segments shorter than the threshold, as in the simulator's
    sagging groom): one contact per crossing, the reference's."""
    s = np.linspace(-5e-3, 5e-3, 41)
    strands = [np.column_stack([s, np.zeros_like(s), np.zeros_like(s)]),
               np.column_stack([np.zeros_like(s), s, np.full_like(s, 3e-4)]),
               np.column_stack([s, np.full_like(s, 1e-3), np.full_like(s, 2e-4)])]
    pts, off, arc = ragged(strands)
    got = detect_strand_contacts(pts, off, arc, 1e-3)
    assert_same(got, contact_reference.detect_strand_contacts_reference(pts, off, arc, 1e-3))
    assert {(a, b) for a, b in zip(got.strand_a, got.strand_b)} >= {(0, 1), (1, 2)}


def test_real_groom_strand_and_head_contacts_equal_the_references(shared_data):
    """A harolongo subset, densified to the inversion's sampling, at the default radius and with
    per-strand radii up to 20 r_c (the simulator's margins): strand/strand contacts equal the
    reference's; head contacts (open harolongo head) the every-vertex reference's."""
    strands = list(read_data(shared_data / "digital-salon" / "harolongo.data", scale=0.01).strands())[::40]
    dense = []
    for p in strands:
        t = np.linspace(0.0, 1.0, 4, endpoint=False)
        d = (p[:-1, None, :] * (1 - t)[None, :, None] + p[1:, None, :] * t[None, :, None]).reshape(-1, 3)
        dense.append(np.vstack([d, p[-1:]]))
    pts, off, arc = ragged(dense)
    rng = np.random.default_rng(0)
    for radii in (5e-5, 5e-5 * rng.uniform(1.0, 20.0, len(off) - 1)):
        got = detect_strand_contacts(pts, off, arc, radii)
        assert len(got) > 50
        assert_same(got, contact_reference.detect_strand_contacts_reference(pts, off, arc, radii))
    mesh = trimesh.load(shared_data / "digital-salon" / "Retopologised_Female_Head_01_mod.obj", process=False)
    mesh.apply_scale(0.01)
    surface = HeadSurface(mesh)
    for rc in (5e-5, 2e-3):
        got = detect_head_contacts(pts, off, arc, surface, rc)
        assert len(got) > 20
        assert_same(got, contact_reference.detect_head_contacts_reference(pts, off, arc, surface, rc))
