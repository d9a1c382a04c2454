"""A project-made example groom (no third-party data): an ellipsoidal head and strands that lie on
its upper back, leave it and hang under gravity, wavy or curly.  Deterministic for a seed.

Frame: metres, y up, the face towards +z, the head centred at the origin.  Each strand follows a
meridian of the head (fixed azimuth) from its root, lifted ``LIFT`` (one fibre radius + 0.2 mm)
above the ellipsoid, down to where its slope is ``alpha`` from vertical; there it leaves the head
with continuous curvature that decays as (1 - s/L)^3 to zero once it points straight down, and
then hangs.  Waves (sideways) or helical curls (never towards the head) fade in after it leaves.
The curve is built finely and resampled uniformly in arc length, so the polyline is smooth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from .groom import Groom
from .io.atomic import atomic_path
from .io.dispatch import save_groom
from .material import Material

HEAD_SEMI_AXES = np.array([0.09, 0.11, 0.10])  # x (ear to ear), y (up), z (towards the face)
HEAD_SUBDIVISIONS = 5  # icosphere level: facets sit <= ~0.02 mm inside the ellipsoid
FIBRE_RADIUS = Material().radius
LIFT = FIBRE_RADIUS + 0.2e-3  # centreline height above the head where a strand lies on it
UP = np.array([0.0, 1.0, 0.0])
_STEP = 1e-4  # spacing of the fine curve before resampling (m)
_RAMP = 0.06  # arc length over which waves and curls fade in after the strand leaves the head (m)
_MIN_SEGMENTS_PER_PERIOD = 16


def example_head() -> trimesh.Trimesh:
    """The ellipsoidal head: a scaled icosphere, watertight, outward normals."""
    sphere = trimesh.creation.icosphere(subdivisions=HEAD_SUBDIVISIONS, radius=1.0)
    return trimesh.Trimesh(sphere.vertices * HEAD_SEMI_AXES, sphere.faces, process=False)


def _surface(theta, phi: float) -> tuple[np.ndarray, np.ndarray]:
    """Ellipsoid points and unit normals at polar angle theta (from +y) and azimuth phi (0 = +z)."""
    s = np.sin(theta)
    unit = np.stack([s * np.sin(phi), np.cos(theta), s * np.cos(phi)], axis=-1)
    normal = unit / HEAD_SEMI_AXES
    return unit * HEAD_SEMI_AXES, normal / np.linalg.norm(normal, axis=-1, keepdims=True)


def _lifted(theta: np.ndarray, phi: float) -> np.ndarray:
    """Points LIFT above the ellipsoid along its normal."""
    point, normal = _surface(theta, phi)
    return point + LIFT * normal


def _tangent_and_curvature(theta: float, phi: float) -> tuple[np.ndarray, float]:
    h = 1e-4
    p0, p1, p2 = _lifted(np.array([theta - h, theta, theta + h]), phi)
    d1, d2 = (p2 - p0) / (2 * h), (p2 - 2 * p1 + p0) / h**2
    speed = np.linalg.norm(d1)
    return d1 / speed, float(np.linalg.norm(np.cross(d1, d2)) / speed**3)


def _smootherstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (x * (6 * x - 15) + 10)


def _resample(curve: np.ndarray, length: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n points at equal arc-length spacing over the first ``length`` of ``curve``, and their arc length."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    assert s[-1] >= length, "fine curve shorter than the strand"
    t = np.linspace(0.0, length, n)
    return np.stack([np.interp(t, s, curve[:, k]) for k in range(3)], axis=1), t


def _strand(rng: np.random.Generator, theta0: float, phi: float, curly: bool):
    """One strand: (points (n, 3), number of leading vertices lying on the head)."""
    length = rng.uniform(0.20, 0.30)
    n = int(rng.integers(85, 101) if curly else rng.integers(60, 101))
    alpha = rng.uniform(0.10, 0.20)  # slope from vertical where the strand leaves the head
    a_merid = np.hypot(HEAD_SEMI_AXES[0] * np.sin(phi), HEAD_SEMI_AXES[2] * np.cos(phi))
    theta_off = np.arctan(a_merid / (HEAD_SEMI_AXES[1] * np.tan(alpha)))

    # on the head: along the meridian
    n_on = int(np.ceil((theta_off - theta0) * HEAD_SEMI_AXES.max() / _STEP)) + 1
    on_head = _lifted(np.linspace(theta0, theta_off, n_on), phi)
    s_off = float(np.linalg.norm(np.diff(on_head, axis=0), axis=1).sum())

    # leaving it: curvature kappa0 (1 - s/L)^3 turns the tangent by beta, onto straight down
    tangent, kappa0 = _tangent_and_curvature(theta_off, phi)
    beta = float(np.arccos(np.clip(-tangent[1], -1.0, 1.0)))
    towards_down = -UP + tangent[1] * tangent
    towards_down /= np.linalg.norm(towards_down)
    bend_length = 4.0 * beta / kappa0
    s = np.linspace(0.0, bend_length, int(np.ceil(bend_length / _STEP)) + 1)
    psi = beta * (1.0 - (1.0 - s / bend_length) ** 4)
    direction = np.cos(psi)[:, None] * tangent + np.sin(psi)[:, None] * towards_down
    steps = 0.5 * (direction[1:] + direction[:-1]) * np.diff(s)[:, None]
    bend = on_head[-1] + np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])

    # hanging: straight down, long enough for any waviness
    drop = np.arange(1, int(np.ceil((length + 0.05) / _STEP)) + 1) * _STEP
    hang = bend[-1] - drop[:, None] * UP
    curve = np.concatenate([on_head, bend[1:], hang])

    # waves (sideways) or curls (sideways and outwards, never into the head), faded in after leaving
    sigma = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))]) - s_off
    sigma = np.maximum(sigma, 0.0)
    out = _surface(theta_off, phi)[1] * [1.0, 0.0, 1.0]
    out /= np.linalg.norm(out)
    side = np.cross(UP, out)
    period_min = _MIN_SEGMENTS_PER_PERIOD * length / (n - 1)
    ramp = _smootherstep(sigma / _RAMP)[:, None]
    if curly:
        radius = rng.uniform(0.005, 0.008)
        pitch = max(rng.uniform(0.025, 0.04), np.sqrt(max(period_min**2 - (2 * np.pi * radius) ** 2, 0.0)))
        angle = 2 * np.pi * sigma / pitch
        hand = rng.choice([-1.0, 1.0])
        curve = curve + ramp * radius * ((1 - np.cos(angle))[:, None] * out + hand * np.sin(angle)[:, None] * side)
    else:
        amplitude = rng.uniform(0.003, 0.006)
        wavelength = max(rng.uniform(0.05, 0.08), period_min)
        phase = rng.uniform(0.0, 2 * np.pi)
        curve = curve + ramp * amplitude * np.sin(2 * np.pi * sigma / wavelength + phase)[:, None] * side
    points, t = _resample(curve, length, n)
    return points, int(np.count_nonzero(t <= s_off))


def example_groom(n_strands: int = 200, seed: int = 0) -> tuple[Groom, trimesh.Trimesh]:
    """The example groom and its head mesh.

    Roots lie on the upper back of the head (polar angle 0.3..1.0 rad from +y, azimuth within 1.3
    rad of straight back), one meridian each, so strands never cross while on the head (with up to
    about 300 strands they also stay more than a fibre diameter apart there).  Where they hang,
    curls and waves of neighbours may cross: hair-hair contact is not resolved.  About half are
    wavy, half curly; 20-30 cm long, 60-100 vertices.  ``metadata``: "kinds" ("wavy"/"curly" per
    strand), "on_head" ((V,) bool, vertices lying on the head) and "lift" (their height, m).
    """
    rng = np.random.default_rng(seed)
    cos_theta = rng.uniform(np.cos(1.0), np.cos(0.3), n_strands)
    slots = (np.arange(n_strands) + 0.5 + rng.uniform(-0.3, 0.3, n_strands)) / n_strands
    phis = np.pi + 1.3 * (2.0 * slots - 1.0)
    curly = rng.random(n_strands) < 0.5
    strands, on_head = [], []
    for cos_t, phi, is_curly in zip(cos_theta, phis, curly):
        points, n_on = _strand(rng, float(np.arccos(cos_t)), float(phi), bool(is_curly))
        strands.append(points)
        on_head.append(np.arange(len(points)) < n_on)
    groom = Groom.from_strands(strands, up="y", source=f"example_groom(n_strands={n_strands}, seed={seed})")
    groom.metadata.update(
        kinds=["curly" if c else "wavy" for c in curly],
        on_head=np.concatenate(on_head) if on_head else np.zeros(0, dtype=bool),
        lift=LIFT,
    )
    return groom, example_head()


def write_example(dirpath, n_strands: int = 200, seed: int = 0) -> tuple[Path, Path]:
    """Write ``example.obj`` (strands as ``l`` polylines) and ``head.obj`` into ``dirpath``
    (created if missing), atomically; return their paths."""
    dirpath = Path(dirpath)
    dirpath.mkdir(parents=True, exist_ok=True)
    groom, head = example_groom(n_strands, seed)
    groom_path = save_groom(groom, dirpath / "example.obj")
    head_path = dirpath / "head.obj"
    with atomic_path(head_path) as tmp:
        head.export(tmp, file_type="obj")
    return groom_path, head_path
