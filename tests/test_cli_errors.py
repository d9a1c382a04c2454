"""No traceback anywhere: bad options, bad heads, corrupt or tampered output directories give one
line on stderr and exit 1 (before any computation for options); an unexpected exception is one line
and exit 3."""

import json
import shutil
import sys

import numpy as np
import pytest

from groomtool.cli import main as cli
from groomtool.cli.main import EXIT_INTERNAL_ERROR, EXIT_OK, EXIT_USER_ERROR, main
from groomtool.examples import write_example


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    d = tmp_path_factory.mktemp("example")
    return write_example(d, n_strands=6, seed=7)


@pytest.fixture(scope="module")
def result_dir(example, tmp_path_factory):
    groom_path, head_path = example
    out = tmp_path_factory.mktemp("result") / "out"
    assert main(["invert", str(groom_path), "--head", str(head_path), "-o", str(out), "-q"]) == EXIT_OK
    return out


def one_line_error(capsys, *needles) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [line for line in err.strip().splitlines() if line and "warning" not in line]
    assert len(lines) == 1 and "error" in lines[0], err
    for needle in needles:
        assert needle in lines[0], err
    return lines[0]


@pytest.mark.parametrize("options, needle", [
    (["--contact-radius", "0", "--contacts", "all"], "--contact-radius"),
    (["--contact-radius", "nan", "--contacts", "all"], "--contact-radius"),
    (["--relative-tolerance", "-1"], "--relative-tolerance"),
    (["--relative-tolerance", "2"], "--relative-tolerance"),
    (["--rod-segments", "100000000"], "--rod-segments"),
    (["--rod-segments", "1e8"], "--rod-segments"),
    (["--tolerance", "inf"], "--tolerance"),
    (["--gamma", "inf", "--contacts", "all"], "--gamma"),
])
def test_bad_options_are_one_line_before_computing(example, tmp_path, capsys, monkeypatch, options, needle):
    groom_path, head_path = example
    inv = sys.modules["groomtool.invert"]
    monkeypatch.setattr(inv, "invert_groom", lambda *a, **k: pytest.fail("computed with a bad option"))
    argv = ["invert", str(groom_path), "--head", str(head_path), "-o", str(tmp_path / "o"), "-q"] + options
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse: usage, then the one-line error
        assert exc.code == EXIT_USER_ERROR
        err = capsys.readouterr().err
        assert "Traceback" not in err and "error" in err.splitlines()[-1] and needle in err.splitlines()[-1]
    else:
        assert code == EXIT_USER_ERROR
        one_line_error(capsys, needle)
    assert not (tmp_path / "o").exists()


def test_head_in_other_units_is_an_error(example, tmp_path, capsys):
    import trimesh

    groom_path, head_path = example
    big = trimesh.load(head_path, force="mesh")
    big.apply_scale(100.0)
    big_path = tmp_path / "big_head.obj"
    big.export(big_path)
    code = main(["invert", str(groom_path), "--head", str(big_path), "--contacts", "head", "-o", str(tmp_path / "o"),
                 "-q"])
    assert code == EXIT_USER_ERROR
    one_line_error(capsys, "big_head.obj", "different units")


def test_absurd_coordinates_are_an_error(example, tmp_path, capsys):
    from groomtool.io import load_groom, save_groom

    groom = load_groom(example[0])
    far = tmp_path / "far.data"
    save_groom(groom, far, units=1e-30)  # coordinates x 1e30 in the file
    assert main(["invert", str(far), "-o", str(tmp_path / "o"), "-q"]) == EXIT_USER_ERROR
    one_line_error(capsys, "far.data", "from the origin")


def tampered(result_dir, tmp_path, **changes):
    out = tmp_path / "t"
    shutil.copytree(result_dir, out)
    with np.load(out / "rest.npz") as z:
        arrays = {k: z[k] for k in z.files}
    for key, value in changes.items():
        if value is None:
            arrays.pop(key)
        else:
            arrays[key] = value
    np.savez(out / "rest.npz", **arrays)
    return out


def corruptions(result_dir):
    with np.load(result_dir / "rest.npz") as z:
        q = z["rest_curvatures"].copy()
        faces = z["head_faces"].copy()
        offsets = z["strand_offsets"].copy()
    q[0, 1] = np.nan
    faces[0, 0] = 10**9
    offsets[-1] += 5
    return {
        "nan_rest_curvature": (dict(rest_curvatures=q), "rest_curvatures"),
        "head_face_out_of_range": (dict(head_faces=faces), "head_faces"),
        "inconsistent_offsets": (dict(strand_offsets=offsets), "shape"),
        "missing_key": (dict(curvatures=None), "curvatures"),
        "empty": ({k: None for k in ("strand_offsets",)}, "strand_offsets"),
    }


@pytest.mark.parametrize("case", ["nan_rest_curvature", "head_face_out_of_range", "inconsistent_offsets",
                                  "missing_key", "empty", "garbage"])
@pytest.mark.parametrize("command", ["export", "check", "view"])
def test_corrupt_rest_npz_is_one_line(result_dir, tmp_path, capsys, case, command):
    if case == "garbage":
        out = tmp_path / "t"
        shutil.copytree(result_dir, out)
        (out / "rest.npz").write_bytes(b"PK\x03\x04 not a zip at all")
        needle = "rest.npz"
    else:
        changes, needle = corruptions(result_dir)[case]
        out = tampered(result_dir, tmp_path, **changes)
    argv = {"export": ["export", str(out), "--format", "hair"],
            "check": ["check", str(out), "--seconds", "0.01", "--dt", "0.01", "-q"],
            "view": ["view", str(out), "--screenshot", str(tmp_path / "shot.png")]}[command]
    assert main(argv) == EXIT_USER_ERROR
    one_line_error(capsys, needle)
    assert not (out / "rest_shape.hair").exists() and not (tmp_path / "shot.png").exists()


def test_invalid_report_json_is_one_line(result_dir, tmp_path, capsys):
    out = tmp_path / "t"
    shutil.copytree(result_dir, out)
    for text in ("{not json", "[1, 2]", json.dumps({"parameters": 5}), "\xff\xfe"):
        (out / "report.json").write_bytes(text.encode("latin-1"))
        assert main(["check", str(out), "--seconds", "0.01", "--dt", "0.01", "-q"]) == EXIT_USER_ERROR
        one_line_error(capsys, "report.json")


def test_unexpected_exception_is_one_line(example, capsys, monkeypatch):
    def boom(args):
        raise RuntimeError("a bug")

    monkeypatch.setitem(cli.COMMANDS, "info", boom)
    monkeypatch.delenv("GROOM_DEBUG", raising=False)
    assert main(["info", str(example[0])]) == EXIT_INTERNAL_ERROR
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error: RuntimeError: a bug" in err and len(err.splitlines()) == 1
    monkeypatch.setenv("GROOM_DEBUG", "1")
    with pytest.raises(RuntimeError):
        main(["info", str(example[0])])


@pytest.mark.parametrize("command, options, needle", [
    ("simulate", ["--air-drag", "-1"], "--air-drag"),
    ("simulate", ["--damping", "nan"], "--damping"),
    ("check", ["--contact-radius", "0"], "--contact-radius"),
])
def test_bad_simulation_options_are_one_line(result_dir, tmp_path, capsys, command, options, needle):
    argv = [command, str(result_dir), "--seconds", "0.01", "--dt", "0.01", "-q", *options]
    if command == "simulate":
        argv += ["-o", str(tmp_path / "frames")]
    assert main(argv) == EXIT_USER_ERROR
    one_line_error(capsys, needle)
