"""`groom info` (box, root centroid, strand direction, roots to head), --up with signed axes,
--scale, --version, and CLI errors that name CLI flags."""

import re

import numpy as np
import pytest
import trimesh

from groomtool.cli.main import EXIT_OK, EXIT_USER_ERROR, cli_message, main
from groomtool.groom import Groom
from groomtool.io import save_groom


def _vec(line, label):
    m = re.search(label + r" \[([-\d. ]+)\]", line)
    assert m, line
    return np.array([float(x) for x in m.group(1).split()])


def _field(out, name):
    return next(line for line in out.splitlines() if line.strip().startswith(name))


@pytest.fixture
def hanging(tmp_path):
    """Strands rooted on a sphere of radius 0.1 m centred at c, hanging along -y, in centimetres."""
    c = np.array([0.01, 0.3, -0.02])
    rng = np.random.default_rng(1)
    strands = []
    for _ in range(20):
        n = rng.normal(size=3)
        n[1] = abs(n[1]) + 0.5
        n /= np.linalg.norm(n)
        root = c + 0.1 * n
        strands.append(root + np.linspace(0, 0.2, 6)[:, None] * np.array([0.05, -1.0, 0.0]))
    groom = Groom.from_strands(strands)
    path = save_groom(groom, tmp_path / "hang.obj", units="cm")
    head = trimesh.creation.icosphere(subdivisions=4, radius=10.0)  # cm
    head.apply_translation(c * 100)
    head_path = tmp_path / "head.obj"
    head.export(head_path)
    return groom, path, head_path, c


def test_info_box_centroid_direction_and_head(hanging, capsys):
    groom, path, head_path, c = hanging
    assert main(["info", str(path), "--units", "cm", "--head", str(head_path)]) == EXIT_OK
    out = capsys.readouterr().out
    lo, hi = groom.points.min(axis=0), groom.points.max(axis=0)
    bounds = _field(out, "bounds")
    assert np.allclose(_vec(bounds, "bounds   "), lo, atol=1e-4)
    assert np.allclose(_vec(bounds, r"\.\."), hi, atol=1e-4)
    roots = groom.points[groom.offsets[:-1]]
    assert np.allclose(_vec(_field(out, "roots"), "centroid"), roots.mean(axis=0), atol=1e-4)
    assert "mostly -y" in _field(out, "direction") and "100% of strands" in out
    head = _field(out, "head")
    gaps = re.findall(r"([\d.]+) mm", head)
    # roots lie on the ideal sphere; the icosphere's facets are at most ~0.1 mm inside it
    assert float(gaps[1]) < 0.2 and "0 of 20 roots inside the head" in head
    assert "check" not in out  # nothing suspicious


def test_info_flags_wrong_up_units_and_far_head(hanging, capsys, tmp_path):
    _, path, head_path, _ = hanging
    assert main(["info", str(path), "--units", "cm", "--up", "-y"]) == EXIT_OK
    out = capsys.readouterr().out
    assert "up axis   -y" in out and "gravity [0.00 9.81 0.00]" in out
    assert "is --up right?" in out
    assert main(["info", str(path), "--units", "m"]) == EXIT_OK  # a groom 100x too large
    assert "check --units / --scale" in capsys.readouterr().out
    # --scale shrinks the groom and the head with it: the roots stay on the head
    assert main(["info", str(path), "--units", "cm", "--scale", "0.5", "--head", str(head_path)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "cm x 0.5" in out and "from the head" not in out
    lengths = re.search(r"max ([\d.]+) m", _field(out, "length")).group(1)
    assert float(lengths) == pytest.approx(0.5 * 0.2 * np.hypot(1, 0.05), abs=1e-4)
    far = tmp_path / "far.obj"
    trimesh.creation.icosphere(radius=10.0).apply_translation([500.0, 0, 0]).export(far)
    assert main(["info", str(path), "--units", "cm", "--head", str(far)]) == EXIT_OK
    assert "from the head (median)" in capsys.readouterr().out


@pytest.mark.parametrize("up", ["x", "-x", "-y", "z", "-z"])
def test_signed_up_axes(hanging, capsys, up):
    _, path, _, _ = hanging
    assert main(["info", str(path), "--units", "cm", "--up", up]) == EXIT_OK  # "--up -x" too
    g = _vec(_field(capsys.readouterr().out, "up axis"), "gravity")
    want = np.zeros(3)
    want["xyz".index(up[-1])] = 9.81 if up.startswith("-") else -9.81
    assert np.allclose(g, want)


def test_bad_scale_and_up(hanging, capsys):
    _, path, _, _ = hanging
    assert main(["info", str(path), "--scale", "0"]) == EXIT_USER_ERROR
    assert "--scale must be a positive number" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["info", str(path), "--up", "w"])
    assert exc.value.code == EXIT_USER_ERROR


def test_version(capsys):
    from groomtool import __version__

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"groom (groomtool) {__version__}"


def test_errors_name_cli_flags(tmp_path, capsys):
    bare = tmp_path / "bare.obj"
    bare.write_text("v 0 0 0\nv 0 1 0\nv 0 2 0\nv 1 1 1\n")
    assert main(["info", str(bare)]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert "--strand-length N" in err and "strand_length" not in err
    assert main(["info", str(bare), "--strand-length", "3"]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert "--strand-length 3" in err and "strand_length" not in err
    rep = tmp_path / "rep.obj"
    rep.write_text("v 0 0 0\nv 0 1 0\nv 0 1 0\nl 1 2 3\n")
    assert main(["info", str(rep)]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert "pass --repair" in err and "repair=True" not in err
    assert main(["info", str(rep), "--repair"]) == EXIT_OK
    assert cli_message("x: load with repair=True to drop them") == "x: pass --repair to drop them"


def test_repair_says_what_it_dropped_and_maps_strands_to_the_input(tmp_path, capsys):
    """--repair: counts in the summary and report.json, input strand indices in rest.npz (strand 1 loses a
    repeated point, strand 2 has two identical points only and is dropped)."""
    import json

    import numpy as np

    t = np.linspace(0.0, 0.1, 10)
    strands = [np.stack([0.01 * k + 0 * t, 0.1 - t, 0.002 * np.sin(40 * t)], axis=1) for k in range(4)]
    strands[1] = np.insert(strands[1], 4, strands[1][4], axis=0)
    strands.insert(2, np.array([[0.3, 0.3, 0.3], [0.3, 0.3, 0.3]]))
    lines, v = [], 1
    for p in strands:
        lines += ["v %.9f %.9f %.9f" % tuple(q) for q in p]
        lines.append("l " + " ".join(str(v + i) for i in range(len(p))))
        v += len(p)
    path = tmp_path / "rep.obj"
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    assert main(["invert", str(path), "--repair", "-o", str(out)]) == EXIT_OK
    text = capsys.readouterr().out
    assert "2 repeated points dropped from 2 strands (1, 2)" in text
    assert "1 strand of fewer than 2 distinct points dropped (2)" in text
    report = json.loads((out / "report.json").read_text())
    assert report["repairs"] == {"dropped_points": 2, "deduplicated_strands": [1, 2], "dropped_strands": [2]}
    with np.load(out / "rest.npz") as z:
        assert z["input_strand"].tolist() == [0, 1, 3, 4]
        first = z["root_positions"][2]
    assert np.allclose(first, strands[3][0], atol=1e-9)  # output strand 2 is input strand 3


def test_format_usd_alone_leaves_a_directory_the_other_commands_read(tmp_path, capsys):
    from groomtool.examples import write_example

    groom_path, _ = write_example(tmp_path, n_strands=3, seed=4)
    out = tmp_path / "o"
    assert main(["invert", str(groom_path), "--format", "usd", "-q", "-o", str(out)]) == EXIT_OK
    assert sorted(p.name for p in out.iterdir()) == ["groom.usdc", "report.json", "rest.npz"]
    assert main(["export", str(out), "--format", "vtp", "-o", str(tmp_path / "g.vtp")]) == EXIT_OK
    assert main(["info", str(out / "groom.usdc")]) == EXIT_OK


def test_head_without_contacts_says_what_it_does(tmp_path, capsys):
    from groomtool.examples import write_example

    groom_path, head_path = write_example(tmp_path, n_strands=6, seed=2)
    assert main(["invert", str(groom_path), "--head", str(head_path), "-o", str(tmp_path / "o")]) == EXIT_OK
    err = capsys.readouterr().err
    assert "--head without --contacts" in err and "--contacts head" in err
    assert main(["invert", str(groom_path), "--head", str(head_path), "--contacts", "head",
                 "-o", str(tmp_path / "o2")]) == EXIT_OK
    assert "--head without --contacts" not in capsys.readouterr().err


def test_summary_says_when_roots_are_inside_or_far_from_the_head():
    from groomtool.cli.main import root_notes

    assert root_notes({"mode": "gap_reported", "median_gap_m": 2e-4, "max_gap_m": 3e-4, "inside_head": 0}) == []
    inside = root_notes({"mode": "gap_reported", "median_gap_m": 2e-4, "max_gap_m": 3e-4, "inside_head": 7})
    assert len(inside) == 1 and "7 roots are inside the head" in inside[0] and "--snap-roots" in inside[0]
    assert root_notes({"mode": "snapped", "median_gap_m": 2e-4, "max_gap_m": 3e-4, "inside_head": 7}) == []
    far = root_notes({"mode": "gap_reported", "median_gap_m": 0.05, "max_gap_m": 0.06, "inside_head": 0})
    assert len(far) == 1 and "more than 1 cm" in far[0]


def test_invert_summary_reports_far_roots(tmp_path, capsys):
    from groomtool.examples import write_example

    groom_path, head_path = write_example(tmp_path, n_strands=4, seed=3)
    moved = tmp_path / "far_head.obj"
    trimesh.load(head_path, force="mesh").apply_translation([0.5, 0, 0]).export(moved)
    assert main(["invert", str(groom_path), "--head", str(moved), "-o", str(tmp_path / "o")]) == EXIT_OK
    assert "more than 1 cm from the head" in capsys.readouterr().out
