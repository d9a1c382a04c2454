"""The `groom` command line: the invert contract, error messages and exit codes."""

import json

import numpy as np
import pytest

from groomtool.cli.main import EXIT_NOT_CONVERGED, EXIT_OK, EXIT_USER_ERROR, main
from groomtool.examples import write_example
from groomtool.io import load_groom

NPZ_KEYS = {"strand_offsets", "element_lengths", "root_positions", "root_frames", "curvatures",
            "rest_curvatures", "young_modulus", "shear_modulus", "radius", "density", "gravity"}


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    d = tmp_path_factory.mktemp("example")
    groom_path, head_path = write_example(d, n_strands=12, seed=3)
    return groom_path, head_path


def test_invert_writes_the_contract(example, tmp_path):
    groom_path, _ = example
    out = tmp_path / "out"
    assert main(["invert", str(groom_path), "-o", str(out), "--quiet"]) == EXIT_OK
    report = json.loads((out / "report.json").read_text())
    for key in ("strands", "elements", "fit", "equilibrium", "stability", "timings_s", "input", "parameters"):
        assert key in report
    assert report["strands"] == 12
    assert report["fit"]["max_error_m"] <= 5e-4
    assert report["equilibrium"]["max_relative_residual"] < 1e-9
    assert "total" in report["timings_s"]
    with np.load(out / "rest.npz") as z:
        assert NPZ_KEYS <= set(z.files)
        offsets = z["strand_offsets"]
        assert len(offsets) == 13 and offsets[-1] == len(z["element_lengths"]) == len(z["rest_curvatures"])
        assert z["curvatures"].shape == z["rest_curvatures"].shape
        # gravity pulls the rest shape away from the groomed one
        assert np.abs(z["curvatures"] - z["rest_curvatures"]).max() > 0
    rest = load_groom(out / "rest_shape.obj")
    fitted = load_groom(out / "fitted.obj")
    assert rest.n_strands == fitted.n_strands == 12
    # the fitted curve starts at the input roots and its length agrees within twice the tolerance
    groom = load_groom(groom_path)
    assert np.allclose(fitted.points[fitted.offsets[:-1]], groom.points[groom.offsets[:-1]], atol=1e-9)
    assert np.allclose(fitted.lengths(), groom.lengths(), rtol=0, atol=2 * 5e-4)


def test_units_are_converted(example, tmp_path):
    groom_path, _ = example
    groom = load_groom(groom_path)
    cm = tmp_path / "cm.obj"
    from groomtool.io import save_groom

    save_groom(groom, cm, units="cm")
    out = tmp_path / "out"
    assert main(["invert", str(cm), "--units", "cm", "-o", str(out), "--quiet", "--tolerance", "0.05"]) == EXIT_OK
    report = json.loads((out / "report.json").read_text())
    assert report["fit"]["tolerance_m"] == pytest.approx(5e-4)
    assert report["input_units"] == "cm"
    # without --tolerance the default is 0.5 mm whatever the input units
    out2 = tmp_path / "out2"
    assert main(["invert", str(cm), "--units", "cm", "-o", str(out2), "--quiet"]) == EXIT_OK
    assert json.loads((out2 / "report.json").read_text())["fit"]["tolerance_m"] == pytest.approx(5e-4)
    with np.load(out / "rest.npz") as z:
        assert np.allclose(z["root_positions"], groom.points[groom.offsets[:-1]], atol=1e-7)


def test_missing_input_is_a_user_error(tmp_path, capsys):
    assert main(["invert", str(tmp_path / "nope.obj"), "-o", str(tmp_path / "o")]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert "nope.obj" in err and "Traceback" not in err


def test_bad_material_is_a_user_error(example, tmp_path, capsys):
    groom_path, _ = example
    assert main(["invert", str(groom_path), "--young", "-1", "-o", str(tmp_path / "o"), "-q"]) == EXIT_USER_ERROR
    assert "young_modulus" in capsys.readouterr().err


def test_the_strand_split_admm_can_be_asked_for_and_an_unknown_solver_is_refused(example, tmp_path):
    """--solver admm runs the strand-split ADMM whatever the contacts (auto only takes it for dense ones beyond
    10,000); InversionParams refuses a solver it does not know instead of failing inside the solve."""
    from groomtool.invert import InversionParams

    groom_path, head_path = example
    out = tmp_path / "admm"
    assert main(["invert", str(groom_path), "--head", str(head_path), "--contacts", "all", "--contact-radius", "5e-4",
                 "--solver", "admm", "-q", "-o", str(out)]) == EXIT_OK
    report = json.loads((out / "report.json").read_text())
    assert report["parameters"]["solver"] == "admm" and report["solve"]["solver"] == "admm"
    assert report["contacts"]["total"] > 0 and report["equilibrium"]["max_relative_residual"] < 1e-9
    with pytest.raises(ValueError, match="solver must be one of"):
        InversionParams(solver="admn")


def test_solver_tolerance_and_sweep_budget(example, tmp_path, capsys):
    """--solver-tolerance and --max-sweeps reach the solve; a budget too small for the tolerance is exit 2
    with the residual, nothing written, under --strict, else exit 0 with the feasible forces and a warning;
    a non-positive tolerance is a user error."""
    groom_path, head_path = example
    base = ["invert", str(groom_path), "--head", str(head_path), "--contacts", "all", "--contact-radius", "5e-4",
            "--solver", "gs", "-q"]
    out = tmp_path / "o"
    assert main(base + ["--solver-tolerance", "1e-4", "-o", str(out)]) == EXIT_OK
    report = json.loads((out / "report.json").read_text())
    assert report["parameters"]["solver_tolerance"] == 1e-4
    assert report["solve"]["residual"] <= 1e-4 and report["contacts"]["total"] > 0
    capsys.readouterr()
    assert main(base + ["--solver-tolerance", "1e-14", "--max-sweeps", "3", "--strict", "-o", str(tmp_path / "p")]) \
        == EXIT_NOT_CONVERGED
    err = capsys.readouterr().err
    assert "did not converge" in err and "residual" in err and "target 1e-14" in err
    assert not (tmp_path / "p").exists()
    # without --strict the feasible forces are written (an exact equilibrium), with a one-line warning
    assert main(base + ["--solver-tolerance", "1e-14", "--max-sweeps", "3", "-o", str(tmp_path / "f")]) == EXIT_OK
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "warning" in err and "stopped (max_iter)" in err
    report = json.loads((tmp_path / "f" / "report.json").read_text())
    assert report["solve"]["status"] == "feasible" and report["solve"]["stopped_with"] == "max_iter"
    assert report["solve"]["q0_error_bound"] > 0 and report["equilibrium"]["max_relative_residual"] < 1e-8
    assert main(base + ["--solver-tolerance", "0", "-o", str(tmp_path / "q")]) == EXIT_USER_ERROR
    assert "solver_tolerance" in capsys.readouterr().err


def test_corrupt_data_names_file_and_strand(tmp_path, capsys):
    bad = tmp_path / "bad.data"
    # 2 strands declared, the second is cut short
    payload = np.array([2, 3], "<i4").tobytes() + np.zeros(9, "<f4").tobytes() + np.array([5], "<i4").tobytes()
    bad.write_bytes(payload + np.ones(6, "<f4").tobytes())
    assert main(["info", str(bad)]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert "bad.data" in err and "strand 1" in err


def test_existing_output_survives_a_failed_run(example, tmp_path, monkeypatch):
    groom_path, _ = example
    out = tmp_path / "out"
    assert main(["invert", str(groom_path), "-o", str(out), "-q"]) == EXIT_OK
    before = (out / "rest.npz").read_bytes()

    import sys

    inv = sys.modules["groomtool.invert"]

    def fail(*a, **k):
        raise inv.SolverFailure("contact solver gs did not converge: status max_iter, residual 1.0e-03", "max_iter", 1e-3)

    monkeypatch.setattr(inv, "invert_groom", fail)
    assert main(["invert", str(groom_path), "-o", str(out), "-q"]) == EXIT_NOT_CONVERGED
    assert (out / "rest.npz").read_bytes() == before
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_info_prints_counts(example, capsys):
    groom_path, _ = example
    assert main(["info", str(groom_path)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "strands   12" in out and "bounds" in out


def test_example_writes_the_groom_and_head_and_is_quiet_with_q(tmp_path, capsys):
    assert main(["example", str(tmp_path / "ex"), "--strands", "3"]) == 0
    assert "wrote" in capsys.readouterr().out
    assert (tmp_path / "ex" / "example.obj").is_file() and (tmp_path / "ex" / "head.obj").is_file()
    assert main(["example", str(tmp_path / "ex2"), "--strands", "3", "-q"]) == 0
    assert capsys.readouterr().out == ""
    assert (tmp_path / "ex2" / "example.obj").is_file()


def test_rest_shape_obj_is_sampled_as_documented(example, tmp_path):
    """docs/outputs.md: rest_shape.obj (and fitted.obj) sample the helices 8 times per element, as
    groom export --format obj does."""
    out = tmp_path / "out"
    assert main(["invert", str(example[0]), "-o", str(out), "-q"]) == 0
    with np.load(out / "rest.npz") as z:
        strands, elements = len(z["strand_offsets"]) - 1, len(z["element_lengths"])
    for name in ("rest_shape.obj", "fitted.obj"):
        vertices = sum(1 for line in (out / name).read_text().splitlines() if line.startswith("v "))
        assert vertices == 8 * elements + strands, name
