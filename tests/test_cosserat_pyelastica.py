"""Interop with PyElastica 1.0: the exported Cosserat rest data holds the groom still in PyElastica.

Needs ``pyelastica==1.0.0`` (a test dependency); skips cleanly without it.

1. Static: PyElastica's own internal forces and torques, plus gravity and point loads, vanish at the
   groomed state for every strand (round-off), including long strands whose equilibrium is unstable.
2. Dynamic: clamped root, gravity, AnalyticalLinearDamper, PositionVerlet for 0.5 s.  The tip stays
   within 0.1 mm, while the naive start (rest shape = groomed shape) sags by more than 10 cm.
   The rotational inertia (mass second moment) is scaled by INERTIA_SCALE: it only shapes the
   dynamics, not the equilibrium, and lifts the explicit step limit of the shear-rotation modes
   (omega^2 ~ 4 alpha G / (rho r^2 scale)) so dt is set by the axial waves, dt < dx / sqrt(E / rho).

Stability: the exact equilibrium of a strand held against gravity by its rest curvature alone is
*statically unstable* beyond about 11 cm horizontally (lateral-torsional: the strand rolls over
through twist), the Greenhill-type length 1.986 (EI / rho S g)^(1/3) = 9 cm for hair.  The 20 cm
horizontal strands below are planar, so round-off never seeds the out-of-plane mode and they stay;
the 3D strands in the dynamic run (8 cm wavy, USC strands cut to their first 10 cm, a 21 cm USC
strand that hangs down) are genuinely stable.  See docs/rest_data.md.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

ea = pytest.importorskip("elastica", reason="pyelastica (test dependency, pinned 1.0.0) not installed")

from elastica.version import VERSION  # noqa: E402

from groomtool import Material  # noqa: E402
from groomtool.io import read_data  # noqa: E402
from groomtool.rods.cosserat import cosserat_rest_data, pyelastica_rod  # noqa: E402

if not VERSION.startswith("1.0"):  # the conventions were read from and checked against 1.0.0
    pytest.skip(f"pyelastica {VERSION} installed, these tests pin 1.0.x", allow_module_level=True)

logging.getLogger().setLevel(logging.ERROR)  # PyElastica logs 'moment of inertia < tolerance' for hair

MAT = Material()
G = np.array([0.0, -9.81, 0.0])
DT = 5e-6                 # axial limit dx / c = 6.6e-6 s for 1 cm edges
INERTIA_SCALE = 1e5       # shear-rotation limit then ~1e-5 s
DAMPING = 2.0             # 1/s, uniform
T_END = 0.5
DX = 0.01                 # target edge length of the simulated rods




def cut(strand, length):
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(strand, axis=0), axis=1))])
    return strand[: np.searchsorted(s, length) + 1]


def polyline_length(p):
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def horizontal(n=21, length=0.2):
    x = np.linspace(0.0, length, n)
    return np.stack([x, 0 * x, 0 * x], axis=1)


def wavy_planar(n=21, length=0.2):
    x = np.linspace(0.0, length, n)
    return np.stack([x, 0.01 * np.sin(40 * x), 0 * x], axis=1)


def wavy_3d(n=41, length=0.2):
    x = np.linspace(0.0, length, n)
    return np.stack([x, 0.01 * np.sin(40 * x), 0.005 * np.cos(25 * x)], axis=1)


def export(strand, point_forces=None, segments=None, stiffness_factor=None):
    """Rest data of one strand, resampled to about DX edges unless ``segments`` is given."""
    n = segments or max(2, int(round(polyline_length(strand) / DX)))
    return cosserat_rest_data(strand, [0, len(strand)], MAT, G, point_forces=point_forces, segments=n,
                              point_force_at="node", stiffness_factor=stiffness_factor)


def cases(shared_dir):
    """(name, strand, node point loads or None) for the dynamic run (each rod costs ~15 us a step)."""
    w = 6.4e-5 * 0.01  # ~ weight of a 1 cm piece of hair, N
    out = [
        ("horizontal 20 cm (planar)", horizontal(), None),
        ("wavy 20 cm (planar)", wavy_planar(), None),
        ("wavy 3D 8 cm", wavy_3d(41, 0.08), None),
        ("wavy 3D 8 cm + loads", wavy_3d(41, 0.08),
         ([0, 0, 0], [3, 5, 8], np.array([[0, 2 * w, w], [w, 0, -w], [0, w, 2 * w]]))),
    ]
    if shared_dir is not None:
        usc = list(read_data(shared_dir / "usc" / "cstrands" / "cstrands00003.data").strands())
        for i in (0, 2, 4):
            out.append((f"USC 00003 #{i} first 10 cm", cut(usc[i], 0.10), None))
        out.append(("USC 00003 #3 (21 cm, hangs)", usc[3], None))
        out.append(("USC 00003 #3 + loads", usc[3],
                    ([0, 0], [7, 15], np.array([[2 * w, 2 * w, 0], [0, w, -2 * w]]))))
    return out


@pytest.fixture(scope="module")
def shared_dir():
    """../shared/data beside the checkout, or None (the USC cases are then left out)."""
    path = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    return path if (path / "usc" / "cstrands" / "cstrands00003.data").is_file() else None


class _ConstantNodeForces(ea.NoForces):
    """Constant external forces at nodes (a stand-in for contact forces)."""

    def __init__(self, forces):
        super().__init__()
        self.forces = np.ascontiguousarray(forces.T)

    def apply_forces(self, system, time=0.0):
        system.external_forces += self.forces


def simulate(rods_and_loads):
    class Sim(ea.BaseSystemCollection, ea.Constraints, ea.Forcing, ea.Damping):
        pass

    sim = Sim()
    for rod, loads in rods_and_loads:
        sim.append(rod)
        sim.constrain(rod).using(ea.OneEndFixedBC, constrained_position_idx=(0,), constrained_director_idx=(0,))
        sim.add_forcing_to(rod).using(ea.GravityForces, acc_gravity=G)
        if loads is not None:
            sim.add_forcing_to(rod).using(_ConstantNodeForces, forces=loads)
        sim.dampen(rod).using(ea.AnalyticalLinearDamper, uniform_damping_constant=DAMPING, time_step=DT)
    sim.finalize()
    start = [rod.position_collection.copy() for rod, _ in rods_and_loads]
    stepper = ea.PositionVerlet()
    steps = int(round(T_END / DT))
    time = np.float64(0.0)
    for _ in range(steps):
        time = stepper.step(sim, time, DT)
    return [np.linalg.norm(rod.position_collection[:, -1] - p[:, -1]) for (rod, _), p in zip(rods_and_loads, start)]


def test_static_balance_in_pyelastica(shared_dir, capsys):
    """PyElastica's internal forces/torques balance the loads at the groomed state, every strand."""
    strands = [("horizontal 20 cm", horizontal(51)), ("wavy 3D 20 cm", wavy_3d(51))]
    if shared_dir is not None:
        usc = list(read_data(shared_dir / "usc" / "cstrands" / "cstrands00003.data").strands())
        strands += [(f"USC 00003 #{i} ({polyline_length(s):.2f} m)", s) for i, s in enumerate(usc)]
    lines = []
    for name, strand in strands:
        n = len(strand)
        pf = ([0, 0], [n // 3, 2 * n // 3], np.array([[0.0, 2e-6, 1e-6], [1e-6, 0.0, -1e-6]]))
        for loads in (None, pf):
            data = cosserat_rest_data(strand, [0, n], MAT, G, point_forces=loads, point_force_at="node")
            rod = pyelastica_rod(data, 0, MAT)
            rod.compute_internal_forces_and_torques(np.float64(0.0))
            f = rod.internal_forces + data["node_forces"].T
            force_rel = np.linalg.norm(f[:, 1:]) / np.linalg.norm(data["node_forces"][1:])
            couple = np.linalg.norm(rod.internal_couple)
            torque_rel = np.linalg.norm(rod.internal_torques[:, 1:]) / couple
            lines.append(f"  {name:28s} {'loads' if loads else 'gravity':8s} force {force_rel:.1e}  "
                         f"torque {torque_rel:.1e}  (ours: {data['cosserat_residual']['force_rel']:.1e}, "
                         f"{data['cosserat_residual']['torque_rel']:.1e})")
            # PyElastica forms the axial strain as Q e / l^ - 1: one rounding of that cancellation is
            # EA eps ~ 3e-15 N, the float64 floor of every nodal force (~1e-8 of a 4 mm piece's weight)
            assert np.abs(f[:, 1:]).max() < 8 * MAT.young_modulus * MAT.area * np.finfo(float).eps, name
            assert torque_rel < 1e-10, name
            assert data["cosserat_residual"]["force_rel"] < 1e-12
            assert data["cosserat_residual"]["torque_rel"] < 1e-12
    with capsys.disabled():
        print("\nPyElastica static residual at the groomed state (relative):")
        print("\n".join(lines))


def test_static_balance_stiffened_strand(shared_dir):
    """A strand solved with moduli f E, f G (``stiffness_factor``): the rod that ``pyelastica_rod``
    builds from its data (the factor read from the data) balances the loads in PyElastica's own
    equations; the same rest data in a rod of the unscaled material does not."""
    strands = [("wavy 3D 20 cm", wavy_3d(51))]
    if shared_dir is not None:
        strands.append(("USC 00003 #3", list(read_data(shared_dir / "usc" / "cstrands" / "cstrands00003.data")
                                             .strands())[3]))
    for name, strand in strands:
        n = len(strand)
        pf = ([0, 0], [n // 3, 2 * n // 3], np.array([[0.0, 2e-6, 1e-6], [1e-6, 0.0, -1e-6]]))
        for f in (3.0, 40.0):
            data = cosserat_rest_data(strand, [0, n], MAT, G, point_forces=pf, point_force_at="node",
                                      stiffness_factor=[f])
            residual = []
            for rod in (pyelastica_rod(data, 0, MAT), pyelastica_rod(data, 0, MAT, stiffness_factor=1.0)):
                rod.compute_internal_forces_and_torques(np.float64(0.0))
                residual.append(rod.internal_forces + data["node_forces"].T)
                if len(residual) == 1:
                    assert rod.shear_matrix[2, 2, 0] == pytest.approx(f * MAT.young_modulus * MAT.area, rel=1e-12)
                    # the stresses' float64 floor is f S eps (PyElastica forms the strains by
                    # cancellation), the couple does not grow with f: the relative floor grows as f
                    torque_rel = np.linalg.norm(rod.internal_torques[:, 1:]) / np.linalg.norm(rod.internal_couple)
                    assert torque_rel < 2e-11 * f, (name, f, torque_rel)
            # the float64 floor of a nodal force is a few roundings of f EA eps (the axial strain)
            assert np.abs(residual[0][:, 1:]).max() < 8 * f * MAT.young_modulus * MAT.area * np.finfo(float).eps, name
            assert np.abs(residual[1][:, 1:]).max() > 0.5 * np.abs(data["node_forces"][1:]).max(), name


def test_drift_in_pyelastica(shared_dir, capsys):
    """0.5 s of damped dynamics: exported rest data < 0.1 mm tip drift, naive rest shape sags > 10 cm.
    A strand stiffened 4x (data solved and rod built with 4 E, 4 G) stays too, while the same data in
    a rod of the unscaled material sags by more than 1 mm."""
    runs, names = [], []
    for name, strand, loads in cases(shared_dir):
        data = export(strand, point_forces=loads)
        nodal = None
        if loads is not None:
            nodal = data["node_forces"] - data["node_mass"][:, None] * G
        runs.append((pyelastica_rod(data, 0, MAT, inertia_scale=INERTIA_SCALE), nodal))
        names.append(name)
    # stiffened: the axial wave speed and the shear-rotation rate grow as sqrt(f), so the edges are
    # sqrt(f) DX long and the rotational inertia f times larger, keeping dt = DT stable
    f = 4.0
    strand = wavy_3d(41, 0.08)
    data = export(strand, segments=int(round(polyline_length(strand) / (DX * np.sqrt(f)))), stiffness_factor=[f])
    runs.append((pyelastica_rod(data, 0, MAT, inertia_scale=f * INERTIA_SCALE), None))
    names.append("wavy 3D 8 cm, stiffened 4x")
    control = pyelastica_rod(data, 0, MAT, inertia_scale=INERTIA_SCALE, stiffness_factor=1.0)
    data = export(horizontal())
    runs.append((pyelastica_rod(data, 0, MAT, inertia_scale=INERTIA_SCALE, rest_sigma=False), None))
    names.append("horizontal 20 cm, rest_sigma = 0")
    naive = pyelastica_rod(data, 0, MAT, inertia_scale=INERTIA_SCALE)
    naive.rest_kappa[:] = 0.0   # rest shape = groomed (straight) shape
    naive.rest_sigma[:] = 0.0
    runs.append((control, None))
    names.append("stiffened 4x data, unscaled rod")
    runs.append((naive, None))
    names.append("naive: rest = groomed, 20 cm")
    drift = simulate(runs)
    with capsys.disabled():
        print(f"\nPyElastica tip drift after {T_END} s (dt {DT:g} s, inertia x{INERTIA_SCALE:g}, "
              f"damping {DAMPING} 1/s):")
        for name, d in zip(names, drift):
            print(f"  {name:36s} {1e3 * d:.3e} mm")
    for name, d in zip(names[:-2], drift[:-2]):
        assert d < 1e-4, (name, d)
    assert drift[-2] > 1e-3
    assert drift[-1] > 0.10
