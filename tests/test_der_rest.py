"""Discrete Elastic Rods: the energy gradient against finite differences, and the exported rest data
making grad E = f_ext at the groomed state (residual printed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from groomtool import Material
from groomtool.io import read_data
from groomtool.rods import discrete as dr
from groomtool.rods.cosserat import cosserat_rest_data
from groomtool.rods.der import (
    der_energy,
    der_gradient,
    der_residual,
    der_rest_data,
    der_strain_jacobian,
)
from reference import rods as rods_reference

MAT = Material()
G = np.array([0.0, -9.81, 0.0])
USC = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "usc" / "cstrands" / "cstrands00003.data"




def random_state(seed, n=12):
    """Two random 3D strands, material frames twisted by random theta away from the transport frame,
    and random rest values (so every energy term and every gradient block is nonzero)."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 0.05, n)
    a = np.stack([x, 0.004 * np.sin(150 * x), 0.003 * np.cos(90 * x)], 1) + 1e-4 * rng.standard_normal((n, 3))
    b = a[::-1] * 1.1 + 0.1 + 3e-4 * rng.standard_normal((n, 3))
    P, off = np.concatenate([a, b]), np.array([0, n, 2 * n])
    _, length, t = dr.edge_geometry(P, off)
    m1 = rods_reference.rotate_about(dr.bishop_frames(P, off)[:, 0], t, 0.4 * rng.standard_normal(len(length)))
    J = der_strain_jacobian(P, off, m1)
    rest = (length * (1 + 1e-3 * rng.standard_normal(len(length))),
            J["kappa"] + 0.05 * rng.standard_normal(J["kappa"].shape),
            J["twist"] + 0.05 * rng.standard_normal(len(J["twist"])))
    return P, off, m1, t, rest


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("stretch", [True, False])
def test_gradient_matches_finite_differences(seed, stretch):
    """dE/dx with frames time-parallel transported along the perturbation, dE/dtheta by rotating
    one material frame about its tangent; central differences.  Without stretch (rest lengths =
    lengths) the bending/twisting part is tested on its own scale."""
    P, off, m1, t, (rl, rk, rt) = random_state(seed)
    if not stretch:
        rl = dr.edge_geometry(P, off)[1]

    def energy(Q, frames=None):
        if frames is None:
            frames = rods_reference.transport(m1, t, dr.edge_geometry(Q, off)[2])
        return der_energy(Q, off, frames, rl, rk, rt, MAT)

    gx, gt = der_gradient(P, off, m1, rl, rk, rt, MAT)
    h = 2e-9
    fd = np.zeros_like(P)
    for v in range(len(P)):
        for c in range(3):
            d = np.zeros_like(P)
            d[v, c] = h
            fd[v, c] = (energy(P + d) - energy(P - d)) / (2 * h)
    np.testing.assert_allclose(gx, fd, atol=2e-6 * np.abs(gx).max())
    ht = 1e-6
    fdt = np.zeros(len(gt))
    for j in range(len(gt)):
        a = np.zeros(len(gt))
        a[j] = ht
        fdt[j] = (energy(P, rods_reference.rotate_about(m1, t, a))
                  - energy(P, rods_reference.rotate_about(m1, t, -a))) / (2 * ht)
    np.testing.assert_allclose(gt, fdt, atol=2e-7 * np.abs(gt).max())


def strands():
    x = np.linspace(0.0, 0.2, 51)
    out = [("horizontal 20 cm", np.stack([x, 0 * x, 0 * x], 1)),
           ("wavy 3D 20 cm", np.stack([x, 0.01 * np.sin(40 * x), 0.005 * np.cos(25 * x)], 1)),
           ("hanging curl 30 cm", np.stack([0.01 * np.cos(60 * x), -1.5 * x, 0.01 * np.sin(60 * x)], 1))]
    if USC.is_file():
        out += [(f"USC 00003 #{i}", s) for i, s in enumerate(read_data(USC).strands())]
    return out


def test_rest_data_residual(capsys):
    """grad E = f_ext at the groom with the exported rest data (< 1e-8), re-evaluated from scratch:
    masses from the exported rest lengths, strains and gradient recomputed, free dofs x_2.., theta^1..."""
    names, pts = zip(*strands())
    off = np.concatenate([[0], np.cumsum([len(p) for p in pts])])
    P = np.concatenate(pts)
    S = len(off) - 1
    rng = np.random.default_rng(0)
    L = dr.arc_lengths(P, off)[off[1:] - 1]
    k = rng.integers(0, S, 3 * S)
    pf = (k, rng.uniform(0.1, 0.9, 3 * S) * L[k], 2e-6 * rng.standard_normal((3 * S, 3)))
    lines = []
    for loads in (None, pf):
        for stretching in ("stiff", "inextensible"):
            d = der_rest_data(P, off, MAT, G, point_forces=loads, stretching=stretching)
            V, E = len(d["rod_points"]), len(d["der_rest_lengths"])
            assert d["der_rest_kappa"].shape == (V - 2 * S, 2) and d["der_rest_twist"].shape == (V - 2 * S,)
            assert E == V - S
            mass = dr.lumped_masses(d["der_rest_lengths"], off, MAT.linear_density)
            f = mass[:, None] * G + dr.point_force_nodes(loads, off, dr.arc_lengths(P, off))
            tension = d["der_tension"] if stretching == "inextensible" else None
            r = der_residual(P, off, d["der_frames"][:, 0], d["der_rest_lengths"], d["der_rest_kappa"],
                             d["der_rest_twist"], MAT, f, tension=tension)
            lines.append(f"  {'loads' if loads else 'gravity':8s} {stretching:13s} ||grad E - f|| / ||f|| = "
                         f"{r['force_rel']:.2e} (worst strand {r['per_strand_max']:.2e}), twist "
                         f"{r['torque_rel']:.1e}")
            # float64 floor of stiff stretching: the consumer forms EA (|e| / e~ - 1) by cancellation,
            # one rounding is EA eps ~ 3e-15 N against ~1e-7 N of weight on a 2 mm edge (USC #3)
            assert r["force_rel"] < 1e-8 and r["per_strand_max"] < 5e-8, r
            assert r["torque_rel"] < 1e-12
            if stretching == "inextensible":
                assert r["force_rel"] < 1e-12
                np.testing.assert_array_equal(d["der_rest_lengths"], dr.edge_geometry(P, off)[1])
            else:   # rest lengths shorten under tension: strain = tension / EA ~ 1e-6
                strain = dr.edge_geometry(P, off)[1] / d["der_rest_lengths"] - 1
                np.testing.assert_allclose(strain * MAT.young_modulus * MAT.area, d["der_tension"],
                                           rtol=1e-6, atol=1e-15)
    with capsys.disabled():
        print(f"\nDER residual at the groomed state ({S} strands: {', '.join(names)}):")
        print("\n".join(lines))


def test_der_and_cosserat_curvatures_agree_when_fine():
    """(kappa1, kappa2)_DER ~ D (kappa_2, -kappa_1)_Cosserat for the same frames, and the rest values
    agree to O(dx): the two exports describe the same rod."""
    x = np.linspace(0.0, 0.1, 401)
    P = np.stack([x, 0.01 * np.sin(40 * x), 0.005 * np.cos(25 * x)], 1)
    c = cosserat_rest_data(P, [0, len(P)], MAT, G)
    d = der_rest_data(P, [0, len(P)], MAT, G)
    D = d["der_voronoi_lengths"][:, None]
    cos_as_der = D * np.stack([c["cosserat_rest_kappa"][:, 1], -c["cosserat_rest_kappa"][:, 0]], 1)
    scale = np.abs(d["der_rest_kappa"]).max()
    assert np.abs(d["der_rest_kappa"] - cos_as_der).max() < 0.02 * scale
    assert np.abs(d["der_rest_twist"] - D[:, 0] * c["cosserat_rest_kappa"][:, 2]).max() \
        < 0.02 * np.abs(d["der_rest_twist"]).max()
    np.testing.assert_allclose(d["der_frames"], c["cosserat_directors"])


# ---------------------------------------------------------------------------------------- per-strand stiffness
DER_ARRAYS = ("rod_points", "rod_offsets", "der_rest_lengths", "der_rest_kappa", "der_rest_twist",
              "der_voronoi_lengths", "der_frames", "der_tension", "der_vertex_mass", "node_forces")


def scaled(material, f):
    return Material(young_modulus=f * material.young_modulus, shear_modulus=f * material.G,
                    radius=material.radius, density=material.density)


def small_groom():
    """The three synthetic strands of :func:`strands` (no data files needed) and random point loads."""
    pts = [p for _, p in strands()[:3]]
    off = np.concatenate([[0], np.cumsum([len(p) for p in pts])])
    P = np.concatenate(pts)
    L = dr.arc_lengths(P, off)[off[1:] - 1]
    rng = np.random.default_rng(4)
    k = rng.integers(0, 3, 9)
    return P, off, (k, rng.uniform(0.1, 0.9, 9) * L[k], 2e-6 * rng.standard_normal((9, 3)))


@pytest.mark.parametrize("stretching", ["stiff", "inextensible"])
def test_per_strand_stiffness_residual(stretching):
    """Strand s solved with f_s E, f_s G: grad E = f at round-off with the per-strand material (not
    with the unscaled one); each strand equals its own solve with Material(f_s E, f_s G)."""
    P, off, pf = small_groom()
    S = len(off) - 1
    f = np.array([7.0, 1.0, 35.0])
    d = der_rest_data(P, off, MAT, G, point_forces=pf, stretching=stretching, stiffness_factor=f)
    r = d["der_residual"]
    tension = d["der_tension"] if stretching == "inextensible" else None
    args = (P, off, d["der_frames"][:, 0], d["der_rest_lengths"], d["der_rest_kappa"], d["der_rest_twist"], MAT,
            d["node_forces"])
    again = der_residual(*args, tension=tension, stiffness_factor=f)
    unscaled = der_residual(*args, tension=tension)
    # the stiff floor is EA eps per node (module doc of the test above): it scales with f_s
    floor = 1e-12 if stretching == "inextensible" else 1e-8 * f.max()
    for res in (r, again):
        assert res["force_rel"] < floor and res["torque_rel"] < 1e-12, res
    assert unscaled["force_rel"] > 0.1
    eoff, ioff = dr.edge_offsets(off), dr.interior_offsets(off)
    for s in range(S):
        sel = pf[0] == s
        one = der_rest_data(P[off[s]:off[s + 1]], [0, off[s + 1] - off[s]], scaled(MAT, f[s]), G,
                            point_forces=(np.zeros(sel.sum(), int), pf[1][sel], pf[2][sel]), stretching=stretching)
        for key, sl in (("der_rest_lengths", slice(eoff[s], eoff[s + 1])),
                        ("der_rest_kappa", slice(ioff[s], ioff[s + 1])),
                        ("der_rest_twist", slice(ioff[s], ioff[s + 1])),
                        ("der_tension", slice(eoff[s], eoff[s + 1]))):
            np.testing.assert_allclose(d[key][sl], one[key], rtol=1e-12, atol=1e-12 * np.abs(one[key]).max(),
                                       err_msg=f"{key} strand {s}")
    # the rest curvature departs from the groom's as 1 / f_s (inextensible: same D_i for every f)
    if stretching == "inextensible":
        d1 = der_rest_data(P, off, MAT, G, point_forces=pf, stretching=stretching)
        kappa = der_strain_jacobian(P, off, d["der_frames"][:, 0])["kappa"]
        fi = np.repeat(f, np.diff(off) - 2)[:, None]
        np.testing.assert_allclose((kappa - d["der_rest_kappa"]) * fi, kappa - d1["der_rest_kappa"], rtol=1e-9,
                                   atol=1e-12 * np.abs(kappa - d1["der_rest_kappa"]).max())


def test_der_stiffness_factor_of_ones_is_bit_identical():
    P, off, pf = small_groom()
    for stretching in ("stiff", "inextensible"):
        for segments in (None, 17):
            kw = dict(point_forces=pf, stretching=stretching, segments=segments)
            a = der_rest_data(P, off, MAT, G, **kw)
            b = der_rest_data(P, off, MAT, G, **kw, stiffness_factor=np.ones(len(off) - 1))
            for key in DER_ARRAYS:
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
            assert a["der_residual"] == b["der_residual"]


def test_der_uniform_stiffness_factor_is_the_scaled_material():
    P, off, pf = small_groom()
    for stretching in ("stiff", "inextensible"):
        for f in (2.5, 100.0):
            a = der_rest_data(P, off, MAT, G, point_forces=pf, stretching=stretching,
                              stiffness_factor=np.full(len(off) - 1, f))
            b = der_rest_data(P, off, scaled(MAT, f), G, point_forces=pf, stretching=stretching)
            for key in DER_ARRAYS:
                np.testing.assert_allclose(a[key], b[key], rtol=1e-12, atol=1e-12 * np.abs(b[key]).max(),
                                           err_msg=key)
            c = der_rest_data(P, off, MAT, G, point_forces=pf, stretching=stretching)
            assert np.abs(a["der_rest_kappa"] - c["der_rest_kappa"]).max() > 1e-3 * np.abs(c["der_rest_kappa"]).max()


def test_energy_and_gradient_with_stiffness_factor():
    """E with per-strand factors = sum_s f_s E_s (strand energies, unscaled material), and its gradient
    matches central differences (the factors enter every term)."""
    P, off, m1, t, (rl, rk, rt) = random_state(3)
    f = np.array([3.0, 0.5])
    E = der_energy(P, off, m1, rl, rk, rt, MAT, stiffness_factor=f)
    eoff, ioff = dr.edge_offsets(off), dr.interior_offsets(off)
    parts = [der_energy(P[off[s]:off[s + 1]], [0, off[s + 1] - off[s]], m1[eoff[s]:eoff[s + 1]],
                        rl[eoff[s]:eoff[s + 1]], rk[ioff[s]:ioff[s + 1]], rt[ioff[s]:ioff[s + 1]], MAT)
             for s in range(2)]
    np.testing.assert_allclose(E, f @ parts, rtol=1e-13)
    gx, gt = der_gradient(P, off, m1, rl, rk, rt, MAT, stiffness_factor=f)
    h = 2e-9
    fd = np.zeros_like(P)
    for v in range(len(P)):
        for c in range(3):
            dP = np.zeros_like(P)
            dP[v, c] = h
            e = [der_energy(Q, off, rods_reference.transport(m1, t, dr.edge_geometry(Q, off)[2]), rl, rk, rt, MAT,
                            stiffness_factor=f) for Q in (P + dP, P - dP)]
            fd[v, c] = (e[0] - e[1]) / (2 * h)
    np.testing.assert_allclose(gx, fd, atol=2e-6 * np.abs(gx).max())
    ht = 1e-6
    fdt = np.zeros(len(gt))
    for j in range(len(gt)):
        a = np.zeros(len(gt))
        a[j] = ht
        e = [der_energy(P, off, rods_reference.rotate_about(m1, t, s * a), rl, rk, rt, MAT, stiffness_factor=f)
             for s in (1, -1)]
        fdt[j] = (e[0] - e[1]) / (2 * ht)
    np.testing.assert_allclose(gt, fdt, atol=2e-7 * np.abs(gt).max())


@pytest.mark.parametrize("bad", [np.ones(2), [1.0, 0.0, 1.0], [1.0, np.nan, 1.0], [np.inf, 1.0, 1.0]])
def test_der_stiffness_factor_is_validated(bad):
    P, off, _ = small_groom()
    with pytest.raises(dr.RestDataError, match="stiffness_factor"):
        der_rest_data(P, off, MAT, G, stiffness_factor=bad)
