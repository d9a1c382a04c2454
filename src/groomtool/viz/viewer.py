"""The pyvista viewer of ``groom view``: head, strands coloured by a result field, contact forces.

Interactive keys: ``t`` rest shape / groomed shape, ``c`` contacts on/off, ``h`` head on/off (also
check boxes, bottom left).  ``screenshot`` renders off-screen (no display needed: VTK's EGL or
OSMesa window) and writes a PNG of the requested size.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..groom import GroomError


@dataclass(frozen=True)
class ColorBy:
    field: str  # vertex field of io.fields
    title: str  # scalar bar title, with the unit
    scale: float  # display value = field * scale
    cmap: str  # a matplotlib colour map ...
    top: float = 1.0  # ... of which the part [0, top] is used (drop pale ends on a light background)
    diverging: bool = False

    def colormap(self):
        import matplotlib
        from matplotlib.colors import ListedColormap

        base = matplotlib.colormaps[self.cmap]
        return base if self.top >= 1.0 else ListedColormap(base(np.linspace(0.0, self.top, 256)))


COLORS = {
    "curvature-change": ColorBy("curvature_change", "curvature change norm(q0 - q)  (1/m)", 1.0, "viridis"),
    "contact-force": ColorBy("contact_force_magnitude", "contact force at the vertex  (uN)", 1e6, "inferno", 0.82),
    "stability": ColorBy("stability_margin", "stability margin 1 - rho  (< 0: unstable alone)", 1.0, "RdYlBu",
                         diverging=True),
    "fit-error": ColorBy("fit_error", "fit error of the strand  (mm)", 1e3, "plasma"),
}
REST_COLOR, HEAD_COLOR, CONTACT_COLOR = "#3c78c8", "#b8b2aa", "#3a3a3a"
ARROW_MIN = 0.05  # arrows are drawn for forces above this fraction of the largest
BACKGROUND = ("#f4f4f2", "#c9d6e3")  # bottom, top


def _clim(values: np.ndarray, spec: ColorBy) -> tuple[float, float]:
    """Colour range: 0 .. 99th percentile (sequential), symmetric about 0 (diverging)."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    if spec.diverging:
        m = float(np.percentile(np.abs(finite), 99)) or 1.0
        return -m, m
    positive = finite[finite > 0]
    hi = float(np.percentile(positive, 99)) if positive.size else 0.0
    return 0.0, hi if hi > 0 else 1.0


def _camera(plotter, bounds_points: np.ndarray, centre: np.ndarray, hair_centre: np.ndarray, up: str) -> None:
    """A three-quarter view from the side the hair is on, slightly from above, framing everything."""
    up_vec = np.eye(3)[1 if up == "y" else 2]
    lo, hi = bounds_points.min(axis=0), bounds_points.max(axis=0)
    size = float(np.linalg.norm(hi - lo)) or 1.0
    side = hair_centre - centre
    side -= side.dot(up_vec) * up_vec
    if np.linalg.norm(side) < 0.05 * size:  # hair all around: look from the front
        side = np.eye(3)[2] if up == "y" else -np.eye(3)[1]
    side /= np.linalg.norm(side)
    across = np.cross(up_vec, side)
    view = np.cos(0.6) * side + np.sin(0.6) * across + 0.35 * up_vec
    view /= np.linalg.norm(view)
    focal = 0.5 * (lo + hi)
    plotter.camera_position = [tuple(focal + 2.5 * size * view), tuple(focal), tuple(up_vec)]
    plotter.reset_camera(bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]))
    camera = plotter.camera
    # lift the picture by 6% of the view height: the scalar bar sits along the bottom
    height = 2.0 * camera.distance * np.tan(np.radians(camera.view_angle) / 2.0)
    shift = -0.06 * height * np.asarray(camera.up)
    camera.position = tuple(np.asarray(camera.position) + shift)
    camera.focal_point = tuple(np.asarray(camera.focal_point) + shift)


def build_plotter(source, color: str = "curvature-change", rest: bool = False, head=None, per_element: int = 8,
                  off_screen: bool = False, size=(1280, 960)):
    """A ready ``pyvista.Plotter`` showing ``source`` (result, output directory, rest.npz or arrays).

    ``color``: one of COLORS; ``rest``: start on the rest shape; ``head``: a trimesh used when the
    result holds none.  Widgets and key bindings are added only when not ``off_screen``.
    """
    import pyvista as pv

    from ..io import fields  # io (0.2 s): this module is imported on the CLI's start for COLORS
    from ..io.results import load_arrays, up_axis
    from ..io.vtp import head_polydata

    if color not in COLORS:
        raise GroomError(f"--color must be one of {', '.join(COLORS)}, got {color!r}")
    spec = COLORS[color]
    arrays = load_arrays(source)
    samples = fields.sample(arrays, per_element)
    vfields = fields.vertex_fields(arrays, samples)
    scalars = np.asarray(vfields[spec.field], dtype=np.float64) * spec.scale
    clim = _clim(scalars, spec)

    plotter = pv.Plotter(off_screen=off_screen, window_size=[int(size[0]), int(size[1])])
    k = min(size[0] / 1280, size[1] / 960)  # text and line sizes follow the window size

    def fs(points: float) -> int:
        return max(5, round(points * k))

    plotter.set_background(BACKGROUND[0], top=BACKGROUND[1])
    plotter.enable_anti_aliasing("ssaa" if off_screen else "fxaa")
    actors = _add_strands(plotter, samples, scalars, spec, clim, rest, k)
    head_poly = head_polydata(arrays, head)
    if head_poly is not None:
        actors["head"] = plotter.add_mesh(head_poly, color=HEAD_COLOR, smooth_shading=True, specular=0.2,
                                          ambient=0.15, name="head")
    contact_actors = _add_contacts(plotter, arrays, samples, (spec, clim) if color == "contact-force" else None, k)
    for actor in contact_actors:  # contacts belong to the groomed shape
        actor.SetVisibility(not rest)
    _shape_label(plotter, rest, fs(12))
    n_contacts = len(np.asarray(arrays.get("contact_forces", np.zeros((0, 3)))))
    plotter.add_text(f"{samples.offsets.size - 1} strands, {n_contacts} contacts   colour: {color}",
                     position="upper_right", font_size=fs(9), color="#333333", name="summary")

    shown = samples.rest_points if rest else samples.points
    all_points = [shown] + ([head_poly.points] if head_poly is not None else [])
    centre = head_poly.center if head_poly is not None else samples.points.mean(axis=0)
    _camera(plotter, np.concatenate(all_points), np.asarray(centre), shown.mean(axis=0), up_axis(arrays))
    if not off_screen:
        add_toggles(plotter, actors, contact_actors, fs(12))
    return plotter


def _add_strands(plotter, samples, scalars, spec: ColorBy, clim, rest: bool, k: float) -> dict:
    """The groomed and the rest polylines (one of them hidden), coloured alike, and the scalar bar
    along the bottom with its title below the labels (VTK's own title would overlap them)."""
    import pyvista as pv

    from ..io.vtp import lines_connectivity

    lines = lines_connectivity(samples.offsets)
    bar = dict(title=spec.title, color="black", n_labels=5, fmt="%.3g", vertical=False, position_x=0.3,
               position_y=0.06, width=0.4, height=0.05, label_font_size=max(5, round(13 * k)))
    actors = {}
    for name, pts in (("groomed", samples.points), ("rest", samples.rest_points)):
        poly = pv.PolyData(np.ascontiguousarray(pts), lines=lines)
        poly.point_data[spec.title] = scalars
        actors[name] = plotter.add_mesh(
            poly, scalars=spec.title, cmap=spec.colormap(), clim=clim, line_width=max(1.0, 3 * k),
            render_lines_as_tubes=True, show_scalar_bar=name == "groomed", scalar_bar_args=bar,
            smooth_shading=True, name=name)
    actors["groomed" if rest else "rest"].SetVisibility(False)
    bar_actor = plotter.scalar_bars[spec.title]
    bar_actor.SetTextPositionToPrecedeScalarBar()
    bar_actor.SetTitle("")
    title = plotter.add_text(spec.title, position=(0.5, 0.02), viewport=True, font_size=max(5, round(11 * k)),
                             color="black", name="bar_title")
    title.GetTextProperty().SetJustificationToCentered()
    return actors


def _add_contacts(plotter, arrays: dict, samples, colouring=None, k: float = 1.0) -> list:
    """Contact points (spheres) and the force on strand a (arrows, the largest 8% of the groom size,
    none below ARROW_MIN of it): small and dark grey, or coloured by force magnitude with
    ``colouring = (ColorBy, clim)``."""
    import pyvista as pv

    from ..io import fields

    points = np.asarray(arrays.get("contact_points", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return []
    forces = fields.contact_forces_world(arrays)
    mag = np.linalg.norm(forces, axis=1)
    size = float(np.linalg.norm(np.ptp(samples.points, axis=0))) or 1.0
    cloud = pv.PolyData(points)
    cloud["force"] = forces
    cloud["magnitude"] = mag
    style, point_size = dict(color=CONTACT_COLOR, opacity=0.6), max(2.0, 4 * k)
    if colouring is not None:
        spec, clim = colouring
        cloud[spec.title] = mag * spec.scale
        style = dict(scalars=spec.title, cmap=spec.colormap(), clim=clim, show_scalar_bar=False)
        point_size = max(3.0, 6 * k)
    out = [plotter.add_mesh(cloud, point_size=point_size, render_points_as_spheres=True, name="contact_points",
                            **style)]
    big = cloud.extract_points(mag >= ARROW_MIN * mag.max(), adjacent_cells=False) if mag.max() > 0 else None
    if big is not None and big.n_points:
        arrows = big.glyph(orient="force", scale="magnitude", factor=0.08 * size / mag.max(),
                           geom=pv.Arrow(tip_length=0.3, tip_radius=0.12, shaft_radius=0.04))
        out.append(plotter.add_mesh(arrows, name="contact_forces", **style))
    return out


def _shape_label(plotter, rest: bool, font_size: int = 12) -> None:
    plotter.add_text("rest shape" if rest else "groomed shape", position="upper_left", font_size=font_size,
                     color="black", name="shape_label")


def add_toggles(plotter, actors: dict, contact_actors: list, label_size: int = 12) -> None:
    """Check boxes (bottom left) and keys: t rest/groomed, c contacts, h head (VTK keeps r, s, w, ...)."""
    state = {"rest": bool(actors["rest"].GetVisibility()), "contacts": True}

    def set_rest(on: bool) -> None:
        actors["rest"].SetVisibility(on)
        actors["groomed"].SetVisibility(not on)
        for a in contact_actors:  # contacts belong to the groomed shape
            a.SetVisibility(state["contacts"] and not on)
        _shape_label(plotter, on, label_size)

    def set_visible(items, on: bool) -> None:
        if items is contact_actors:
            state["contacts"] = on
            on = on and not state["rest"]
        for a in items:
            a.SetVisibility(on)

    def toggle_rest(on=None):  # check box: on = its new state; key: flip
        state["rest"] = (not state["rest"]) if on is None else bool(on)
        set_rest(state["rest"])
        rest_box.GetRepresentation().SetState(state["rest"])
        plotter.render()

    rest_box = plotter.add_checkbox_button_widget(toggle_rest, value=state["rest"], position=(10, 60), size=28,
                                                  color_on=REST_COLOR)
    plotter.add_text("rest shape (t)", position=(44, 64), font_size=9, color="black")
    plotter.add_key_event("t", toggle_rest)
    head = [actors["head"]] if "head" in actors else []
    for label, key, items, y in (("contacts (c)", "c", contact_actors, 100), ("head (h)", "h", head, 140)):
        if not items:
            continue
        cb = plotter.add_checkbox_button_widget(lambda on, items=items: set_visible(items, on), value=True,
                                                position=(10, y), size=28)
        plotter.add_text(label, position=(44, y + 4), font_size=9, color="black")

        def flip(items=items, cb=cb):
            on = not bool(cb.GetRepresentation().GetState())
            set_visible(items, on)
            cb.GetRepresentation().SetState(on)
            plotter.render()

        plotter.add_key_event(key, flip)


def has_display() -> bool:
    """False on Linux without an X or Wayland display (then only off-screen rendering works)."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def show(source, **options) -> None:
    """Open the interactive window (needs a display)."""
    if not has_display():
        raise GroomError("no display (DISPLAY is not set): use --screenshot FILE.png to render off-screen")
    build_plotter(source, off_screen=False, **options).show(title="groom view")


def screenshot(source, path, size=(1280, 960), **options) -> Path:
    """Render off-screen into the PNG ``path`` (written atomically); returns the path."""
    from ..io.atomic import atomic_path

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise GroomError(f"{path}: the screenshot is written as PNG: use a .png name")
    plotter = build_plotter(source, off_screen=True, size=size, **options)
    try:
        with atomic_path(path) as tmp:
            plotter.screenshot(str(tmp), window_size=[int(size[0]), int(size[1])])
    finally:
        plotter.close()
    return path
