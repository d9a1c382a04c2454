"""``groom check`` and ``groom simulate``: the report, the files, and the done-criteria on real data."""

import argparse
import json

import meshio
import numpy as np
import pytest

from groomtool.check import check_groom, curvature_profile_change, load_inverted, tip_drifts, write_check
from groomtool.cli import simulate_cmd
from groomtool.groom import Groom
from groomtool.invert import InversionParams, invert_groom
from groomtool.io import save_groom
from groomtool.rods import superhelix as sh


def hanging_groom(n=3, length=0.12, seed=0):
    """Short strands leaving horizontal roots and curving down (stable: well under Greenhill's length)."""
    rng = np.random.default_rng(seed)
    strands = []
    for k in range(n):
        s = np.linspace(0.0, length, 40)
        radius = 0.05 + 0.01 * rng.random()
        angle = s / radius
        pts = np.stack([radius * np.sin(angle), radius * (np.cos(angle) - 1.0), 0.01 * k + 0.002 * np.sin(30 * s)], axis=1)
        strands.append(pts)
    return Groom.from_strands(strands, up="y", source="hanging")


def parser():
    p = argparse.ArgumentParser(prog="groom")
    simulate_cmd.add_parsers(p.add_subparsers(dest="command", required=True))
    return p


@pytest.fixture(scope="module")
def inverted_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("inverted")
    invert_groom(hanging_groom(), None, InversionParams(contacts="none")).save(out)
    return out


def test_check_report_inverted_stays_naive_sags(inverted_dir):
    report = check_groom(inverted_dir, seconds=0.25, dt=1 / 120)
    assert report["steps"] == 30 and report["contacts"] == "none"
    assert report["inverted"]["max_tip_drift_m"] < 1e-9
    assert report["naive"]["max_tip_drift_m"] > 1e-3
    assert report["drift_ratio"] < 1e-6
    assert report["inverted"]["curvature_profile_change"]["max"] < 1e-9
    assert report["naive"]["curvature_profile_change"]["max"] > 1e-3
    path = write_check(inverted_dir, report)
    assert json.loads(path.read_text())["naive"]["mean_tip_drift_m"] > 0


def test_check_command(inverted_dir, capsys):
    args = parser().parse_args(["check", str(inverted_dir), "--seconds", "0.05", "--dt", "0.01"])
    assert simulate_cmd.cmd_check(args) == 0
    out = capsys.readouterr().out
    assert "inverted" in out and "naive" in out
    report = json.loads((inverted_dir / "check.json").read_text())
    for key in ("max_tip_drift_m", "mean_tip_drift_m", "curvature_profile_change", "timings_s"):
        assert key in report["inverted"] and key in report["naive"]
    assert report["steps"] == 5 and report["dt"] == 0.01


def test_simulate_command_from_result_and_from_groom_file(inverted_dir, tmp_path):
    out = tmp_path / "frames"
    args = parser().parse_args(["simulate", str(inverted_dir), "--seconds", "0.1", "--dt", "0.01", "--fps", "20",
                                "-o", str(out), "--format", "obj", "--format", "vtk", "--quiet"])
    assert simulate_cmd.cmd_simulate(args) == 0
    objs = sorted(out.glob("frame_*.obj"))
    assert len(objs) == 3  # t = 0, 0.05, 0.1
    mesh = meshio.read(out / "frame_0002.vtu")
    assert mesh.points.shape[1] == 3 and len(mesh.cells_dict["line"]) > 0
    assert (out / "frames.pvd").read_text().count("<DataSet") == 3
    assert json.loads((out / "simulation.json").read_text())["steps"] == 10

    groom_file = tmp_path / "g.obj"
    save_groom(hanging_groom(2), groom_file)
    out2 = tmp_path / "naive"
    args = parser().parse_args(["simulate", str(groom_file), "--seconds", "0.05", "--dt", "0.01", "-o", str(out2),
                                "--contacts", "none", "--quiet"])
    assert simulate_cmd.cmd_simulate(args) == 0
    assert len(list(out2.glob("frame_*.obj"))) == 3  # t = 0, 0.04 (every 4th step at 24 fps), 0.05 (the end)


def test_measures():
    tips = np.zeros((3, 2, 3))
    tips[1, 0, 0] = 2.0
    tips[2, 0, 0] = 1.0
    drift, excursion = tip_drifts(tips)
    assert drift.tolist() == [1.0, 0.0] and excursion.tolist() == [2.0, 0.0]
    q = np.zeros((1, 3, 3))
    q[0, :, 1] = [10.0, 20.0, 5.0]
    helix = sh.SuperHelix(np.zeros(3), np.eye(3), np.full((1, 3), 0.01), q)
    after = q.copy()
    after[0, 1, 1] = 19.0
    after[0, 0, 0] = 7.0  # twist does not count
    assert curvature_profile_change(helix, after)[0] == pytest.approx(1.0 / 20.0)


def test_usc_curly_style_keeps_its_curls(shared_data, tmp_path):
    """Done-criterion on real data: a curly USC style inverted with all contacts stays put for 1 s."""
    from groomtool import solvers
    from groomtool.io import load_groom, load_head

    if not hasattr(solvers, "solve_contact_problem"):
        pytest.skip("solvers.solve_contact_problem (the inversion's contact solver) is not available yet")
    groom = load_groom(shared_data / "usc" / "cstrands" / "cstrands00014.data")
    head = load_head(shared_data / "usc" / "head_model.obj")
    invert_groom(groom, head, InversionParams(contacts="all")).save(tmp_path)
    report = check_groom(tmp_path, seconds=1.0, dt=1 / 240)
    assert report["inverted"]["max_tip_drift_m"] < 1e-3
    assert report["inverted"]["max_tip_drift_m"] < 0.02 * report["naive"]["max_tip_drift_m"]
    assert report["inverted"]["curvature_profile_change"]["max"] < 0.01
    inv = load_inverted(tmp_path)
    assert inv.head is not None and inv.contacts == "all"
