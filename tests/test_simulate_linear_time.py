"""The simulator on the block-semiseparable step matrix (simulate_linalg.factor_step_generators: no dense M, O(N)
factors) against the dense path (every strand dense: simulate_linalg.DENSE_BELOW above every strand's size): the same
trajectories to round-off, with and without contacts, on strands that need unstable-mode corrections and on an
inverted groom."""

import numpy as np
import pytest

from groomtool import simulate_linalg
from groomtool.check import load_inverted
from groomtool.examples import example_groom
from groomtool.invert import InversionParams, invert_groom
from groomtool.material import Material
from groomtool.rods import superhelix as sh
from groomtool.simulate import SimulationParams, Simulator
from test_simulate_partial import stacked_strands

GRAVITY = np.array([0.0, -9.81, 0.0])
ALL_DENSE = 10**9


def run(monkeypatch, dense_below, steps, make):
    """(tips after ``steps`` steps, start tips, the simulator) with strands of fewer than ``dense_below`` elements
    dense."""
    monkeypatch.setattr(simulate_linalg, "DENSE_BELOW", dense_below)
    sim = make()
    start = sim.tips()
    structured = False
    for _ in range(steps):
        sim.step()
        structured |= bool(sim._factors.structured.any())
    assert structured == (dense_below == 0 and not sim._factors.corrected.all())
    return sim.tips(), start, sim


@pytest.mark.parametrize("contacts", ["none", "all"])
def test_sagging_strands_follow_the_dense_trajectory(monkeypatch, contacts):
    """Straight-rest strands sagging over a sphere (naive), 40 steps at 1/240 s: the tips of the structured and the
    dense step agree to round-off without contacts (1.7e-17 m of 6 cm measured) and, with contacts solved to 1e-10,
    to the solve's tolerance (3e-12 m)."""
    helix, sphere = stacked_strands()
    rest = np.zeros_like(helix.curvatures)
    params = SimulationParams(dt=1 / 240, contacts=contacts, solver_tolerance=1e-10, max_sweeps=5000)

    def make():
        return Simulator(helix, rest, Material(friction=0.3), GRAVITY, head=sphere, params=params)

    got, start, _ = run(monkeypatch, 0, 40, make)
    want, _, _ = run(monkeypatch, ALL_DENSE, 40, make)
    motion = np.abs(want - start).max()
    assert motion > 0.01
    assert np.abs(got - want).max() <= (1e-14 if contacts == "none" else 1e-9) * motion


def test_floppy_strands_with_unstable_mode_corrections_follow_the_dense_trajectory(monkeypatch):
    """Long strands at dt = 1/24 s: some need the unstable-mode correction (dense, kept) while the others are
    structured; 30 steps, the same modified count and tips to round-off."""
    rng = np.random.default_rng(2)
    S, N = 6, 24
    counts = np.array([24, 6, 18, 3, 24, 12])
    lengths = np.full((S, N), 0.01) * (np.arange(N)[None, :] < counts[:, None])
    q = rng.normal(size=(S, N, 3)) * 10.0 * (lengths > 0)[..., None]
    frames = np.repeat(np.eye(3)[None], S, axis=0)
    helix = sh.SuperHelix(rng.normal(size=(S, 3)) * 0.05, frames, lengths, q, counts)

    def make():
        return Simulator(helix, np.zeros_like(q), Material(), GRAVITY, params=SimulationParams(dt=1 / 24))

    got, start, sim = run(monkeypatch, 0, 30, make)
    want, _, dense = run(monkeypatch, ALL_DENSE, 30, make)
    assert sim.modified_strands == dense.modified_strands > 0
    motion = np.abs(want - start).max()
    assert motion > 0.01
    assert np.abs(got - want).max() <= 1e-12 * motion


def test_an_inverted_groom_stays_put_on_either_path(monkeypatch, tmp_path):
    """example_groom(16) inverted with every contact, 30 steps: the structured and the dense run both stay put and
    their tips agree to round-off."""
    groom, head = example_groom(16, seed=1)
    invert_groom(groom, head, InversionParams(contacts="all", contact_radius=5e-4)).save(tmp_path)
    inv = load_inverted(tmp_path)
    params = SimulationParams(dt=1 / 240, contacts=inv.contacts, contact_radius=inv.contact_radius)

    def make():
        return Simulator(inv.helix, inv.rest_curvatures, inv.material, inv.gravity, head=inv.head, params=params,
                         stiffness=inv.stiffness(), warm_start=inv.contact_forces, external_force=inv.boundary_force)

    got, start, _ = run(monkeypatch, 0, 30, make)
    want, _, _ = run(monkeypatch, ALL_DENSE, 30, make)
    assert np.abs(want - start).max() < 1e-9 and np.abs(got - start).max() < 1e-9
    assert np.abs(got - want).max() <= 1e-14


def test_a_shaken_head_gives_the_dense_trajectory(monkeypatch):
    """Strands on a head that turns and shakes (the root motion's inertial forces in A, a full assembly every step),
    30 steps at 1/240 s: the structured and the dense step's tips agree to round-off."""
    helix, sphere = stacked_strands()

    def motion(t):
        angle = 2.0 * np.sin(8.0 * t)
        c, s = np.cos(angle), np.sin(angle)
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]), np.array([0.0, 0.02 * np.sin(20.0 * t), 0.0])

    def make():
        return Simulator(helix, helix.curvatures, Material(), GRAVITY, params=SimulationParams(dt=1 / 240),
                         head_motion=motion)

    got, start, _ = run(monkeypatch, 0, 30, make)
    want, _, _ = run(monkeypatch, ALL_DENSE, 30, make)
    motion_size = np.abs(want - start).max()
    assert motion_size > 0.01
    assert np.abs(got - want).max() <= 1e-12 * motion_size
