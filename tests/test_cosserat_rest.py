"""Cosserat rest data without PyElastica: contract, resampling, frames, loads, exact discrete balance."""

from __future__ import annotations

import numpy as np
import pytest

from groomtool import Material
from groomtool.rods import discrete as dr
from groomtool.rods.cosserat import (
    cosserat_rest_data,
    cosserat_static_residual,
    cosserat_stiffness,
    pyelastica_kappa,
    voronoi_lengths,
)

MAT = Material()
G = np.array([0.0, -9.81, 0.0])


def wavy(n, length=0.2, seed=0):
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, length, n)
    a, b = rng.uniform(20, 50, 2)
    return np.stack([x, 0.01 * np.sin(a * x), 0.005 * np.cos(b * x) - 0.005], axis=1) + rng.normal(0, 1e-4, 3)


def groom(counts=(7, 30, 3, 55), seed=1):
    strands = [wavy(n, 0.05 + 0.05 * i, seed + i) for i, n in enumerate(counts)]
    offsets = np.concatenate([[0], np.cumsum([len(s) for s in strands])])
    return np.concatenate(strands), offsets


def test_contract_shapes_and_units():
    P, off = groom()
    S, V = len(off) - 1, len(P)
    pf = ([1, 3], [0.02, 0.1], np.array([[0, 1e-6, 0], [1e-6, 0, 0]]))
    d = cosserat_rest_data(P, off, MAT, G, point_forces=pf)
    assert d["rod_points"].shape == (V, 3) and np.array_equal(d["rod_offsets"], off)
    assert d["cosserat_directors"].shape == (V - S, 3, 3)
    assert d["cosserat_rest_kappa"].shape == (V - 2 * S, 3)
    assert d["cosserat_rest_sigma"].shape == (V - S, 3)
    assert d["cosserat_rest_lengths"].shape == (V - S,)
    assert d["cosserat_rest_voronoi_lengths"].shape == (V - 2 * S,)
    assert d["node_forces"].shape == (V, 3) and d["node_mass"].shape == (V,)
    np.testing.assert_allclose(d["cosserat_rest_lengths"], dr.edge_geometry(P, off)[1])
    # total load = weight of every strand + the point loads
    weight = MAT.linear_density * np.sum(d["cosserat_rest_lengths"]) * G
    np.testing.assert_allclose(d["node_forces"].sum(0), weight + pf[2].sum(0), rtol=1e-12, atol=1e-18)
    d2 = cosserat_rest_data(P, off, MAT, G, segments=12)
    assert d2["rod_points"].shape == (13 * S, 3)
    assert d2["cosserat_rest_kappa"].shape == (11 * S, 3)


def test_exact_discrete_balance():
    """PyElastica's static equations, re-evaluated term by term, vanish at round-off."""
    P, off = groom()
    pf = ([0, 1, 3, 3], [0.01, 0.07, 0.0, 0.19], np.array([[0, 2e-6, 0], [1e-6, 0, -1e-6],
                                                             [5e-6, 5e-6, 5e-6], [0, 0, 3e-6]]))
    for segments in (None, 9, 40):
        d = cosserat_rest_data(P, off, MAT, G, point_forces=pf, segments=segments)
        r = d["cosserat_residual"]
        assert r["force_rel"] < 1e-12 and r["torque_rel"] < 1e-12, (segments, r)
        # the rest shear is the load beyond over the shear/stretch stiffness: ~1e-6 for hair
        assert 1e-8 < r["max_rest_sigma"] < 1e-4
        # perturbing the rest curvature breaks the balance
        k0 = d["cosserat_rest_kappa"].copy()
        k0[len(k0) // 2] *= 1.001
        _, tres = cosserat_static_residual(d["rod_points"], d["rod_offsets"], d["cosserat_directors"], k0,
                                           d["cosserat_rest_sigma"], d["cosserat_rest_lengths"],
                                           d["node_forces"], MAT)
        assert np.abs(tres).max() > 1e3 * np.abs(d["cosserat_internal_couple"]).max() * 1e-12


def test_continuum_shortcut_is_the_coarse_limit():
    """kappa0 = kappa - B^-1 m (m: moment of the loads beyond the node, node frame) is exact for a
    straight strand and differs from the exact discrete solution by O(dx) on a curved one."""
    B, _ = cosserat_stiffness(MAT)
    errs = []
    for n in (21, 41, 81, 161):
        x = np.linspace(0.0, 0.08, n)
        P = np.stack([x, 0.01 * np.sin(40 * x), 0.005 * np.cos(25 * x)], axis=1)
        d = cosserat_rest_data(P, [0, n], MAT, G)
        F, Q = d["node_forces"], d["cosserat_directors"]
        m = np.array([np.cross(P[j + 1:] - P[j], F[j + 1:]).sum(0) for j in range(1, n - 1)])
        m_mat = np.einsum("kab,kb->ka", Q[:-1], m)     # element j's frame (root side of node j)
        tau = d["cosserat_internal_couple"]
        errs.append(np.abs(tau - m_mat).max() / np.abs(m_mat).max())
    assert errs[-1] < 1e-3
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(rates > 0.8), errs
    x = np.linspace(0.0, 0.2, 31)
    P = np.stack([x, 0 * x, 0 * x], axis=1)
    d = cosserat_rest_data(P, [0, 31], MAT, G)
    m = np.array([np.cross(P[j + 1:] - P[j], d["node_forces"][j + 1:]).sum(0) for j in range(1, 30)])
    np.testing.assert_allclose(d["cosserat_internal_couple"],
                               np.einsum("kab,kb->ka", d["cosserat_directors"][:-1], m), rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(d["cosserat_rest_kappa"], -d["cosserat_internal_couple"] / B, rtol=1e-12,
                               atol=1e-9)


def test_frames_are_orthonormal_and_twist_free():
    P, off = groom()
    Q = dr.bishop_frames(P, off)
    np.testing.assert_allclose(np.einsum("kab,kcb->kac", Q, Q), np.broadcast_to(np.eye(3), Q.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(Q), 1.0, atol=1e-14)
    np.testing.assert_allclose(Q[:, 2], dr.edge_geometry(P, off)[2], atol=1e-15)
    kappa = pyelastica_kappa(Q, voronoi_lengths(dr.edge_geometry(P, off)[1], off), off)
    assert np.abs(kappa[:, 2]).max() < 1e-9 * np.abs(kappa).max()      # no twist
    # a given root normal is honoured (projected normal to the root tangent)
    Q2 = dr.bishop_frames(P, off, root_normal=[0.0, 0.0, 1.0])
    eoff = dr.edge_offsets(off)
    assert np.all(Q2[eoff[:-1], 0, 2] > 0.9)
    with pytest.raises(dr.RestDataError):
        dr.bishop_frames(np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0.0]]), [0, 3])


def test_resample_by_arc_length():
    P, off = groom()
    rp, ro, arc = dr.resample(P, off, 10)
    L = dr.arc_lengths(P, off)[off[1:] - 1]
    assert np.array_equal(ro, np.arange(len(off)) * 11)
    np.testing.assert_allclose(rp[ro[:-1]], P[off[:-1]], atol=1e-15)
    np.testing.assert_allclose(rp[ro[1:] - 1], P[off[1:] - 1], atol=1e-15)
    np.testing.assert_allclose(arc.reshape(-1, 11), L[:, None] * np.linspace(0, 1, 11)[None], rtol=1e-13)
    # every rod vertex lies on the input polyline: distance to the nearest input segment is zero
    for s in range(len(off) - 1):
        p = P[off[s]:off[s + 1]]
        for q in rp[ro[s]:ro[s + 1]]:
            a, b = p[:-1], p[1:]
            t = np.clip(np.sum((q - a) * (b - a), 1) / np.sum((b - a) ** 2, 1), 0, 1)
            assert np.min(np.linalg.norm(a + t[:, None] * (b - a) - q, axis=1)) < 1e-15
    same = dr.resample(P, off)
    assert np.array_equal(same[0], P) and np.array_equal(same[1], off)
    with pytest.raises(dr.RestDataError):
        dr.resample(P, [0, 2, len(P)])
    with pytest.raises(dr.RestDataError):
        dr.edge_geometry(np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0.0]]), np.array([0, 3]))


def test_point_forces_keep_force_and_moment():
    P, off = groom()
    rp, ro, arc = dr.resample(P, off, 17)
    rng = np.random.default_rng(3)
    S = len(off) - 1
    strand = rng.integers(0, S, 40)
    L = arc[ro[1:] - 1][strand]
    s = rng.uniform(0, 1, 40) * L
    s[:2] = 0.0
    s[2] = L[2]
    f = rng.normal(size=(40, 3))
    F = dr.point_force_nodes((strand, s, f), ro, arc)
    # application points on the rod polyline at the same resampling parameter
    for k in range(S):
        sel = strand == k
        pts = np.stack([np.interp(s[sel], arc[ro[k]:ro[k + 1]], rp[ro[k]:ro[k + 1], c]) for c in range(3)], 1)
        Fk = F[ro[k]:ro[k + 1]]
        np.testing.assert_allclose(Fk.sum(0), f[sel].sum(0), atol=1e-12)
        np.testing.assert_allclose(np.cross(rp[ro[k]:ro[k + 1]], Fk).sum(0), np.cross(pts, f[sel]).sum(0),
                                   atol=1e-12)
    Fn = dr.point_force_nodes(([0, 0, 2], [0, 4, 2], np.ones((3, 3))), ro, arc, at="node")
    assert np.array_equal(np.flatnonzero(Fn[:, 0]), [0, 4, 2 * 18 + 2])
    with pytest.raises(dr.RestDataError):
        dr.point_force_nodes(([0], [1.0e3], np.ones((1, 3))), ro, arc)
    with pytest.raises(dr.RestDataError):
        dr.point_force_nodes(([0], [18], np.ones((1, 3))), ro, arc, at="node")
    with pytest.raises(dr.RestDataError):
        dr.point_force_nodes(([S], [0.0], np.ones((1, 3))), ro, arc)


# ---------------------------------------------------------------------------------------- per-strand stiffness
STIFF_PF = ([0, 1, 3, 3], [0.01, 0.07, 0.0, 0.19], np.array([[0, 2e-6, 0], [1e-6, 0, -1e-6],
                                                              [5e-6, 5e-6, 5e-6], [0, 0, 3e-6]]))
ARRAYS = ("rod_points", "rod_offsets", "cosserat_directors", "cosserat_rest_kappa", "cosserat_rest_sigma",
          "cosserat_rest_lengths", "cosserat_rest_voronoi_lengths", "node_forces", "node_mass",
          "cosserat_internal_stress", "cosserat_internal_couple")


def scaled(material, f):
    return Material(young_modulus=f * material.young_modulus, shear_modulus=f * material.G,
                    radius=material.radius, density=material.density)


@pytest.mark.parametrize("segments", [None, 9])
def test_per_strand_stiffness_balance(segments):
    """Strand s solved with f_s E, f_s G: PyElastica's balance with the per-strand material vanishes
    at round-off, not with the unscaled one; each strand equals its own solve with Material(f_s E,
    f_s G); loads (hence stress and couple) do not depend on the stiffness, the rest strains do."""
    P, off = groom()
    f = np.random.default_rng(5).uniform(1.0, 40.0, len(off) - 1)
    d = cosserat_rest_data(P, off, MAT, G, point_forces=STIFF_PF, segments=segments, stiffness_factor=f)
    d1 = cosserat_rest_data(P, off, MAT, G, point_forces=STIFF_PF, segments=segments)
    r = d["cosserat_residual"]
    assert r["force_rel"] < 1e-12 and r["torque_rel"] < 1e-12, r
    np.testing.assert_array_equal(d["cosserat_stiffness_factor"], f)
    args = (d["rod_points"], d["rod_offsets"], d["cosserat_directors"], d["cosserat_rest_kappa"],
            d["cosserat_rest_sigma"], d["cosserat_rest_lengths"], d["node_forces"], MAT)
    fres, tres = cosserat_static_residual(*args, stiffness_factor=f)
    couple = np.abs(d["cosserat_internal_couple"]).max()
    assert np.abs(tres).max() < 1e-12 * couple and np.abs(fres).max() < 1e-12 * np.abs(d["node_forces"]).max()
    # with the unscaled material every internal stress and couple is 1 / f_s of the balancing one:
    # the torque balance is homogeneous in them, the force balance against the loads is not
    fres_unscaled, _ = cosserat_static_residual(*args)
    assert np.abs(fres_unscaled).max() > 0.5 * np.abs(d["node_forces"]).max()
    np.testing.assert_array_equal(d["cosserat_internal_couple"], d1["cosserat_internal_couple"])
    np.testing.assert_array_equal(d["cosserat_internal_stress"], d1["cosserat_internal_stress"])
    ro, ioff, eoff = d["rod_offsets"], dr.interior_offsets(d["rod_offsets"]), dr.edge_offsets(d["rod_offsets"])
    point = d["node_forces"] - d["node_mass"][:, None] * G      # the point loads, per rod node
    kappa_all = pyelastica_kappa(d["cosserat_directors"], d["cosserat_rest_voronoi_lengths"], ro)
    for s in range(len(off) - 1):
        n = ro[s + 1] - ro[s]
        one = cosserat_rest_data(d["rod_points"][ro[s]:ro[s + 1]], [0, n], scaled(MAT, f[s]), G,
                                 point_forces=(np.zeros(n, int), np.arange(n), point[ro[s]:ro[s + 1]]),
                                 point_force_at="node")
        for key, sl in (("cosserat_rest_kappa", slice(ioff[s], ioff[s + 1])),
                        ("cosserat_rest_sigma", slice(eoff[s], eoff[s + 1]))):
            np.testing.assert_allclose(d[key][sl], one[key], rtol=1e-12, atol=1e-12 * np.abs(one[key]).max())
        # the rest strain departs from the groom's strain as 1 / f_s
        k = slice(ioff[s], ioff[s + 1])
        kappa = kappa_all[k]
        np.testing.assert_allclose((kappa - d["cosserat_rest_kappa"][k]) * f[s],
                                   kappa - d1["cosserat_rest_kappa"][k], rtol=1e-9,
                                   atol=1e-12 * np.abs(kappa).max())


def test_stiffness_factor_of_ones_is_bit_identical():
    P, off = groom()
    for segments in (None, 9):
        a = cosserat_rest_data(P, off, MAT, G, point_forces=STIFF_PF, segments=segments)
        b = cosserat_rest_data(P, off, MAT, G, point_forces=STIFF_PF, segments=segments,
                               stiffness_factor=np.ones(len(off) - 1))
        for key in ARRAYS + ("cosserat_stiffness_factor",):
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        assert a["cosserat_residual"] == b["cosserat_residual"]
        np.testing.assert_array_equal(a["cosserat_stiffness_factor"], 1.0)


def test_uniform_stiffness_factor_is_the_scaled_material():
    """f for every strand = Material(young_modulus=f E, shear_modulus=f G), to round-off."""
    P, off = groom()
    for f in (2.5, 100.0):
        a = cosserat_rest_data(P, off, MAT, G, point_forces=STIFF_PF, stiffness_factor=np.full(len(off) - 1, f))
        b = cosserat_rest_data(P, off, scaled(MAT, f), G, point_forces=STIFF_PF)
        for key in ARRAYS:
            np.testing.assert_allclose(a[key], b[key], rtol=1e-13, atol=1e-13 * np.abs(b[key]).max(), err_msg=key)
        # and differs from the unscaled material
        c = cosserat_rest_data(P, off, MAT, G, point_forces=STIFF_PF)
        change = np.abs(a["cosserat_rest_kappa"] - c["cosserat_rest_kappa"]).max()
        assert change > 1e-3 * np.abs(c["cosserat_rest_kappa"]).max()


@pytest.mark.parametrize("bad, match", [(np.ones(3), "shape"), (np.ones((4, 1)), "shape"), (2.0, "shape"),
                                        ([1, 0, 1, 1], "positive"), ([1, -2, 1, 1], "positive"),
                                        ([1, np.nan, 1, 1], "finite"), ([1, 1, np.inf, 1], "finite")])
def test_stiffness_factor_is_validated(bad, match):
    P, off = groom()
    with pytest.raises(dr.RestDataError, match=match):
        cosserat_rest_data(P, off, MAT, G, stiffness_factor=bad)
    d = cosserat_rest_data(P, off, MAT, G)
    with pytest.raises(dr.RestDataError, match=match):
        cosserat_static_residual(d["rod_points"], d["rod_offsets"], d["cosserat_directors"], d["cosserat_rest_kappa"],
                                 d["cosserat_rest_sigma"], d["cosserat_rest_lengths"], d["node_forces"], MAT,
                                 stiffness_factor=bad)
