"""The Python API: load a groom and a head, invert, export.  Tutorial: docs/tutorial.md.

    >>> import groomtool
    >>> groom = groomtool.load("strands.obj", units="cm")            # doctest: +SKIP
    >>> head = groomtool.load_head("head.obj", units="cm")           # doctest: +SKIP
    >>> result = groomtool.invert(groom, head, contacts="all", young_modulus=2.5e9)  # doctest: +SKIP
    >>> result.save("out")                                          # doctest: +SKIP
    >>> groomtool.export(result, "out/groom.usdc")                  # doctest: +SKIP

Everything is SI inside (metres, pascals, kilograms per cubic metre); ``units`` only states the
unit of the files read.  The forward simulator is ``groomtool.simulate`` (its own module).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .groom import Groom
from .invert import InversionParams, InversionResult, invert_groom
from .material import Material
from .rods import clothoid as cl
from .rods import superhelix as sh

MATERIAL_FIELDS = tuple(f.name for f in dataclasses.fields(Material))
PARAM_FIELDS = tuple(f.name for f in dataclasses.fields(InversionParams) if f.name != "material")


def load(path, units="m", up: str = "y", repair: bool = False, strand_length=None) -> Groom:
    """Read a groom file (.obj, .ply, .data, .hair, .usd/.usda/.usdc/.usdz) into metres.

    units: "m", "cm", "mm" or metres per file unit; up: "y" or "z" (USD files carry their own
    metersPerUnit and upAxis, which win); repair: drop repeated points and strands of fewer than 2
    vertices instead of failing; strand_length: vertices per strand for OBJ/PLY without lines.
    """
    from .io import load_groom

    return load_groom(path, units=units, up=up, repair=repair, strand_length=strand_length)


def load_head(path, units="m"):
    """Read a head mesh (.obj, .ply, .stl, ...) as a ``trimesh.Trimesh`` in metres."""
    from .io import load_head as _load_head

    return _load_head(path, units=units)


def inversion_params(**params) -> InversionParams:
    """``InversionParams`` from keyword arguments: its own fields (tolerance, contacts, guess, gamma,
    solver, ...) and the material's (young_modulus, shear_modulus, radius, density, friction,
    gravity), or ``material=Material(...)``.  Unknown names raise TypeError."""
    # max_iterations: InversionParams' deprecated alias of max_sweeps (it warns)
    unknown = sorted(set(params) - set(MATERIAL_FIELDS) - set(PARAM_FIELDS) - {"material", "max_iterations"})
    if unknown:
        raise TypeError(f"unknown parameter(s) {', '.join(unknown)}; material: {', '.join(MATERIAL_FIELDS)}; "
                        f"inversion: {', '.join(PARAM_FIELDS)}")
    material_kw = {k: params.pop(k) for k in MATERIAL_FIELDS if k in params}
    material = params.pop("material", None) or Material()
    if material_kw:
        material = dataclasses.replace(material, **material_kw)
    return InversionParams(material=material, **params)


def invert(groom, head=None, *, units="m", quiet: bool = True, **params) -> InversionResult:
    """Rest curvatures that make ``groom`` an equilibrium under gravity (and contact).

    groom: a ``Groom`` or a file path (read with ``units``); head: a trimesh, a mesh path or None.
    params: see :func:`inversion_params`, e.g. ``contacts="all", young_modulus=2.5e9, radius=35e-6``;
    ``model="clothoid"`` fits Super Space Clothoids instead of Super-Helices (docs/clothoid.md).
    Returns an ``InversionResult``: ``.rest_curvatures`` (S, N, 3) 1/m, ``.rest_shape()``,
    ``.contacts``, ``.forces``, ``.report`` and ``.save(outdir, formats=("npz", "obj", "json"))``.
    Raises ``groomtool.invert.SolverFailure`` when the contact solver does not converge.
    """
    if isinstance(groom, (str, Path)):
        groom = load(groom, units=units)
    if isinstance(head, (str, Path)):
        head = load_head(head, units=units)
    return invert_groom(groom, head=head, params=inversion_params(**params), quiet=quiet)


def export(result, path, shape: str = "rest", per_element: int = 8) -> Path:
    """Write a result (``InversionResult``, output directory or its rest.npz) by extension.

    .usd/.usda/.usdc/.usdz: the groom with rest data (docs/usd.md); .vtp: strands with their fields
    (``shape`` "fitted" or "rest"); .obj/.hair/.data: the ``shape`` polylines ("rest" or "fitted"),
    sampled ``per_element`` times per helix element.  Returns the path.
    """
    from .io.export import export_path

    return export_path(result, path, shape=shape, per_element=per_element)


def simulate(result, seconds: float = 1.0, **options):
    """Simulate a result forward from its groomed state (a thin wrapper of ``groomtool.simulate.simulate``).

    result: an ``InversionResult``, an output directory or its rest.npz (helices, rest curvatures,
    material, gravity and head are taken from it).  options: those of ``groomtool.simulate.simulate``
    (dt, contacts, frames_per_second, params, ...).  Returns its ``SimulationResult``.
    """
    from .simulate import simulate as _simulate

    if isinstance(result, InversionResult):
        helix, rest, material, gravity, head = (result.helix, result.rest_curvatures, result.material,
                                                result.gravity, result.head)
        factor = result.stiffness_factor
    else:
        helix, rest, material, gravity, head, factor = _simulation_inputs(result)
    options.setdefault("head", head)
    if factor is not None and np.any(np.asarray(factor) != 1.0):  # stiffened strands (docs/stability.md)
        if isinstance(helix, sh.SuperHelix):
            K = sh.stiffness(helix, material.stiffness_diag) * np.asarray(factor)[:, None, None]
        else:  # a Super Space Clothoid: K banded (diagonal, off-diagonal blocks)
            K = tuple(x * np.asarray(factor)[:, None, None] for x in cl.stiffness(helix, material.stiffness_diag))
        options.setdefault("stiffness", K)
    return _simulate(helix, rest, material, gravity, seconds=seconds, **options)


def _simulation_inputs(source):
    """(helix, rest curvatures (S, N, 3), material, gravity, head trimesh or None, per-strand stiffness factors
    or None) of a saved result."""
    from .io.results import read_result

    saved = read_result(source)
    return saved.rod(), saved.rest_curvatures, saved.material, saved.gravity, saved.head(), saved.stiffness_factor
