"""Isolated inversion and stability: exact equilibrium, and the Greenhill buckling length."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from groomtool.inverse_problem import equilibrium_residuals, isolated_rest_curvatures, rest_curvature_guess
from groomtool.material import Material
from groomtool.rods import superhelix as sh
from groomtool.stability import constrained_top_eigenvalue, stiffness_ratios

MATERIAL = Material()
G = np.array([0.0, -9.81, 0.0])


def _upright_strand(length, n_elements=30):
    """A straight strand rising vertically from the origin (n0 = +y)."""
    frame = np.stack([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]], axis=1)
    return sh.SuperHelix(np.zeros((1, 3)), frame[None], np.full((1, n_elements), length / n_elements),
                         np.zeros((1, n_elements, 3)))


def _random_helix(seed, n_strands=4, n_elements=8):
    rng = np.random.default_rng(seed)
    return sh.SuperHelix(0.05 * rng.normal(size=(n_strands, 3)), Rotation.random(n_strands, random_state=seed).as_matrix(),
                         rng.uniform(0.005, 0.03, size=(n_strands, n_elements)),
                         rng.normal(size=(n_strands, n_elements, 3)) * 30)


@pytest.mark.parametrize("seed", [0, 1])
def test_isolated_rest_curvatures_make_an_exact_equilibrium(seed):
    helix = _random_helix(seed)
    q0 = isolated_rest_curvatures(helix, MATERIAL, G)
    res = equilibrium_residuals(helix, q0, MATERIAL, G)
    assert res.max() < 1e-12
    # and the naive rest shape (q0 = q) is far from one
    assert equilibrium_residuals(helix, helix.curvatures, MATERIAL, G).min() == pytest.approx(1.0)


def test_equilibrium_is_a_stationary_point_of_the_energy():
    """dE/dq = K (q - q0) - F vanishes: check by finite differences of the total energy."""
    helix = _random_helix(3, n_strands=1)
    q0 = isolated_rest_curvatures(helix, MATERIAL, G)

    def energy(q):
        h = helix.with_curvatures(q)
        return (sh.elastic_energy(h, q0, MATERIAL.stiffness_diag)
                + sh.gravity_potential(h, MATERIAL.linear_density, G))[0]

    rng = np.random.default_rng(0)
    direction = rng.normal(size=helix.curvatures.shape)
    eps = 1e-4
    slope = (energy(helix.curvatures + eps * direction) - energy(helix.curvatures - eps * direction)) / (2 * eps)
    scale = np.abs(sh.gravity_force(helix, MATERIAL.linear_density, G) * direction).sum()
    assert abs(slope) < 1e-7 * scale


@pytest.mark.parametrize("factor, stable", [(0.9, True), (0.98, True), (1.02, False), (1.2, False)])
def test_stability_threshold_is_the_greenhill_length(factor, stable):
    """A vertical strand buckles under its own weight beyond 1.986 (EI / rhoS g)^(1/3)."""
    helix = _upright_strand(factor * MATERIAL.greenhill_length())
    ratio = stiffness_ratios(helix, MATERIAL.stiffness_diag, MATERIAL.linear_density, G)[0]
    assert (ratio < 1.0) == stable


def test_critical_length_converges_to_greenhill():
    from scipy.optimize import brentq

    LG = MATERIAL.greenhill_length()

    def crit(n):
        return brentq(lambda L: stiffness_ratios(_upright_strand(L, n), MATERIAL.stiffness_diag,
                                                 MATERIAL.linear_density, G)[0] - 1.0, 0.5 * LG, 2 * LG)

    errors = [abs(crit(n) / LG - 1) for n in (10, 20, 40)]
    assert errors[-1] < 2e-3
    assert errors[0] > errors[1] > errors[2]  # converges with refinement


def test_hanging_strand_is_stable_and_ratio_scales_with_stiffness():
    frame = np.stack([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], axis=1)
    helix = sh.SuperHelix(np.zeros((1, 3)), frame[None], np.full((1, 10), 0.03), np.zeros((1, 10, 3)))
    assert stiffness_ratios(helix, MATERIAL.stiffness_diag, MATERIAL.linear_density, G)[0] <= 1e-12
    up = _upright_strand(0.15)
    r1 = stiffness_ratios(up, MATERIAL.stiffness_diag, MATERIAL.linear_density, G)[0]
    r2 = stiffness_ratios(up, 2 * MATERIAL.stiffness_diag, MATERIAL.linear_density, G)[0]
    assert r2 == pytest.approx(r1 / 2, rel=1e-10)


def test_holding_the_tip_stabilises_a_long_upright_strand():
    """Beyond the Greenhill length the strand is unstable alone, stable once its tip is held."""
    helix = _upright_strand(1.5 * MATERIAL.greenhill_length(), 20)
    dF = sh.gravity_force_jacobian(helix, MATERIAL.linear_density, G)[0]
    scale = 1.0 / np.sqrt(sh.stiffness(helix, MATERIAL.stiffness_diag).reshape(-1))
    A = scale[:, None] * dF * scale[None, :]
    alone = constrained_top_eigenvalue(A, None)
    assert alone == pytest.approx(stiffness_ratios(helix, MATERIAL.stiffness_diag, MATERIAL.linear_density, G)[0],
                                  rel=1e-9)
    J, _ = sh.point_jacobians(helix, [0], [helix.strand_lengths[0]])
    held = constrained_top_eigenvalue(A, J[0].transpose(1, 0, 2).reshape(3, -1) * scale[None, :])
    assert alone > 1.0 > held


def test_tip_guess_copies_the_last_element():
    helix = _random_helix(5, n_strands=2, n_elements=4)
    helix.lengths[1, 3] = 0.0
    helix.curvatures[1, 3] = 0.0
    helix.n_elements = np.array([4, 3])
    guess = rest_curvature_guess(helix, "tip")
    assert np.allclose(guess[0], helix.curvatures[0, 3])
    assert np.allclose(guess[1, :3], helix.curvatures[1, 2]) and np.all(guess[1, 3] == 0)
    assert np.array_equal(rest_curvature_guess(helix, "current"), helix.curvatures)
