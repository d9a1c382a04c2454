"""The viewer: an off-screen screenshot without a display (PNG of the asked size, not blank),
the rest/groomed toggle, and ``groom view`` argument checks."""

import argparse
import subprocess
import sys

import numpy as np
import pytest

pv = pytest.importorskip("pyvista", reason="pyvista is not installed")

from groomtool.groom import GroomError  # noqa: E402
from groomtool.viz import viewer  # noqa: E402
from test_viz_fields import synthetic_result  # noqa: E402

PROBE = ("import pyvista as pv; p = pv.Plotter(off_screen=True, window_size=(64, 64)); "
         "p.add_mesh(pv.Sphere()); img = p.screenshot(); assert img.std() > 0, 'blank render'")


@pytest.fixture(scope="session")
def can_render():
    """Off-screen rendering probed in a subprocess (a VTK without any GL back end may abort)."""
    try:
        proc = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        pytest.skip("off-screen rendering probe timed out")
    if proc.returncode != 0:
        pytest.skip(f"pyvista/vtk cannot render off-screen here: {proc.stderr.strip().splitlines()[-1:]}")


@pytest.fixture(scope="module")
def outdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("result")
    synthetic_result().save(d, formats=("npz", "json"))
    return d


def image_stats(path):
    from PIL import Image

    with Image.open(path) as im:
        size = im.size
        a = np.asarray(im.convert("RGB"))
    colours = len(np.unique(a.reshape(-1, 3), axis=0))
    return size, float(a.std()), colours


@pytest.mark.parametrize("color", list(viewer.COLORS))
def test_screenshot_headless(can_render, outdir, tmp_path, monkeypatch, color):
    monkeypatch.delenv("DISPLAY", raising=False)
    path = viewer.screenshot(outdir, tmp_path / f"{color}.png", size=(320, 240), color=color)
    size, spread, colours = image_stats(path)
    assert size == (320, 240)
    assert spread > 10.0 and colours > 100, "blank screenshot"
    assert [p.name for p in tmp_path.iterdir()] == [f"{color}.png"]


def test_rest_toggle_and_head(can_render, outdir):
    plotter = viewer.build_plotter(outdir, rest=True, off_screen=True, size=(200, 150))
    try:
        assert plotter.actors["rest"].GetVisibility() and not plotter.actors["groomed"].GetVisibility()
        assert "head" in plotter.actors and "contact_forces" in plotter.actors
        assert not plotter.actors["contact_points"].GetVisibility()
    finally:
        plotter.close()


def test_head_from_argument_when_the_result_has_none(can_render, tmp_path):
    r = synthetic_result(contacts=False)
    head = r.head
    r.head = None
    r.save(tmp_path, formats=("npz",))
    plotter = viewer.build_plotter(tmp_path, off_screen=True, size=(200, 150), head=head)
    try:
        assert "head" in plotter.actors and "contact_points" not in plotter.actors
    finally:
        plotter.close()


def parse(argv):
    from groomtool.cli import view_cmd

    parser = argparse.ArgumentParser(prog="groom")
    view_cmd.add_parser(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


def test_view_command_screenshot(can_render, outdir, tmp_path, capsys):
    png = tmp_path / "shot.png"
    args = parse(["view", str(outdir), "--color", "stability", "--screenshot", str(png), "--size", "300", "200"])
    assert args.func(args) == 0
    assert image_stats(png)[0] == (300, 200)
    assert "wrote" in capsys.readouterr().out


def test_view_command_errors(outdir, tmp_path, monkeypatch):
    args = parse(["view", str(outdir), "--size", "0", "10", "--screenshot", str(tmp_path / "x.png")])
    with pytest.raises(GroomError, match="--size"):
        args.func(args)
    args = parse(["view", str(tmp_path / "missing"), "--screenshot", str(tmp_path / "x.png")])
    with pytest.raises(GroomError, match="no such file"):
        args.func(args)
    args = parse(["view", str(outdir), "--screenshot", str(tmp_path / "x.jpg")])
    with pytest.raises(GroomError, match="PNG"):
        args.func(args)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    args = parse(["view", str(outdir)])
    with pytest.raises(GroomError, match="no display"):
        args.func(args)


def test_key_toggles(can_render, outdir):
    """The interactive toggles, driven through their key callbacks on an off-screen plotter."""
    plotter = viewer.build_plotter(outdir, off_screen=True, size=(200, 150))
    try:
        a = plotter.actors
        viewer.add_toggles(plotter, {k: a[k] for k in ("groomed", "rest", "head")},
                            [a["contact_points"], a["contact_forces"]])
        keys = plotter.iren._key_press_event_callbacks
        keys["t"][0]()
        assert a["rest"].GetVisibility() and not a["groomed"].GetVisibility()
        assert not a["contact_points"].GetVisibility()  # contacts belong to the groomed shape
        keys["t"][0]()
        assert a["groomed"].GetVisibility() and not a["rest"].GetVisibility()
        assert a["contact_points"].GetVisibility()
        keys["c"][0]()
        assert not a["contact_points"].GetVisibility() and not a["contact_forces"].GetVisibility()
        keys["h"][0]()
        assert not a["head"].GetVisibility()
    finally:
        plotter.close()
