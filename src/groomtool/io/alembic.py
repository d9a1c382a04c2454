"""Alembic grooms (.abc) in Unreal's groom conventions, through the optional ``alembic3d`` package.

``pip install 'groomtool[alembic]'`` (or ``pip install alembic3d``: unofficial PyAlembic wheels,
BSD-3-Clause; docs/formats.md has the judgement).  Without it, reading or writing ``.abc`` is a
``GroomError`` that says what to install.

Written (docs/formats.md, "Alembic")::

    /groom            Xform (identity)
    /groom/strands    Curves (linear, non-periodic), centimetres: the strands polyline of the USD
                      export (the discrete rods' vertices, or the fitted rods -- helices or clothoids -- sampled
                      ``per_element`` times per element), widths and Unreal's groom_* attributes,
                      rest data per vertex (rest_position, rest_length, cm) and material per strand;
                      a Super Space Clothoid result also groomtool_darboux / groomtool_rest_darboux
                      (q and q0 at each vertex, 1/m)
    /groom/guides     (``guides=True``) the same curves with groom_guide = 1: every strand a
                      simulation guide

``read_alembic`` reads the curves of any Alembic file (ours, Unreal's, Blender's, Maya's, Houdini's):
render strands (groom_guide 0 or absent), else the guides; points of the first sample, moved by
their Xforms; cubic curves as their control points.  Alembic has no units: ``scale`` (metres per
unit, ``--units``) applies; grooms in Unreal's convention are in cm (``--units cm``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..groom import Groom, GroomError
from ..material import Material
from .atomic import atomic_path
from .formats import suffixes
from .validate import validate

CM = 100.0  # Unreal's grooms are in centimetres
INSTALL = "pip install 'groomtool[alembic]' (the alembic3d package, unofficial PyAlembic wheels)"
MATERIAL = ("young_modulus", "shear_modulus", "density", "friction", "radius")


def _modules(path):
    try:
        import imath  # noqa: F401  (bundled with alembic3d)
        from alembic3d import Abc, AbcGeom
    except ImportError as exc:
        raise GroomError(f"{path}: Alembic (.abc) support needs the optional alembic3d package: {INSTALL}") from exc
    return Abc, AbcGeom, imath


# ------------------------------------------------------------------------------------- writing
def write_alembic(source, path, per_element: int = 8, guides: bool = False) -> Path:
    """Write a result (``InversionResult``, output directory, rest.npz or its arrays) as an Alembic
    groom in centimetres with Unreal's ``groom_*`` attributes; written atomically, returns the path."""
    from . import fields
    from .results import load_arrays
    from .fields import consumer_rest_data, rod_polyline_data

    path = Path(path)
    Abc, AbcGeom, imath = _modules(path)
    if path.suffix.lower() not in suffixes("abc"):
        raise GroomError(f"{path}: Alembic files end in .abc")
    arrays = load_arrays(source)
    samples = fields.sample(arrays, per_element)
    points, offsets, rod_data, _, arc = rod_polyline_data(arrays, samples)
    rest = consumer_rest_data(arrays, points, offsets, arc, rod_data)
    S = len(offsets) - 1
    radius = float(arrays.get("radius", Material.radius))  # rest.npz before it held the radius
    material = {}
    for key in MATERIAL:
        if key in arrays:
            material[key] = np.full(S, float(arrays[key]))
    for key, name in (("strand_young_modulus", "young_modulus"), ("strand_shear_modulus", "shear_modulus"),
                      ("stiffness_factor", "stiffness_factor")):
        if key in arrays and np.asarray(arrays[key]).shape == (S,):
            material[name] = np.asarray(arrays[key], dtype=np.float64)
    with atomic_path(path) as tmp:
        archive = Abc.OArchive(str(tmp))
        archive.setCompressionHint(1)
        xform = AbcGeom.OXform(archive.getTop(), "groom")
        _write_curves(AbcGeom, imath, xform, "strands", points, offsets, radius, rest, material, guide=0)
        if guides:
            _write_curves(AbcGeom, imath, xform, "guides", points, offsets, radius, rest, material, guide=1)
        del xform, archive  # the archive is written when its last object goes
    return path


def _float_array(imath, values):
    return imath.FloatArrayFromBuffer(np.ascontiguousarray(values, dtype=np.float32).ravel())


def _geom_param(AbcGeom, imath, arb, name, values, scope):
    """One arbGeomParam: int32, float or V3f by the values' dtype and shape."""
    values = np.asarray(values)
    if values.dtype.kind in "iub":
        param = AbcGeom.OInt32GeomParam(arb, name, False, scope, 1)
        param.set(AbcGeom.OInt32GeomParamSample(
            imath.IntArrayFromBuffer(np.ascontiguousarray(values, dtype=np.int32).ravel()), scope))
    elif values.ndim == 2 and values.shape[1] == 3:
        param = AbcGeom.OV3fGeomParam(arb, name, False, scope, 1)
        param.set(AbcGeom.OV3fGeomParamSample(
            imath.V3fArrayFromBuffer(np.ascontiguousarray(values, dtype=np.float32)), scope))
    else:
        param = AbcGeom.OFloatGeomParam(arb, name, False, scope, 1)
        param.set(AbcGeom.OFloatGeomParamSample(_float_array(imath, values), scope))
    return param


def _write_curves(AbcGeom, imath, parent, name, points, offsets, radius, rest, material, guide: int):
    S = len(offsets) - 1
    uniform, vertex, constant = (AbcGeom.GeometryScope.kUniformScope, AbcGeom.GeometryScope.kVertexScope,
                                 AbcGeom.GeometryScope.kConstantScope)
    curves = AbcGeom.OCurves(parent, name)
    schema = curves.getSchema()
    # per-vertex widths (Blender reads widths per point) and no basis (linear: Blender otherwise
    # takes the default Bezier basis and regroups the points into Bezier segments)
    widths = AbcGeom.OFloatGeomParamSample(_float_array(imath, np.full(len(points), 2.0 * radius * CM)), vertex)
    sample = AbcGeom.OCurvesSchemaSample(
        imath.V3fArrayFromBuffer(np.ascontiguousarray(points * CM, dtype=np.float32)),
        imath.IntArrayFromBuffer(np.diff(offsets).astype(np.int32)),
        AbcGeom.CurveType.kLinear, AbcGeom.CurvePeriodicity.kNonPeriodic, widths)
    sample.setBasis(AbcGeom.BasisType.kNoBasis)
    schema.set(sample)
    arb = schema.getArbGeomParams()
    version = AbcGeom.OStringGeomParam(arb, "groom_version", False, constant, 1)
    strings = imath.StringArray(1)
    strings[0] = "1.0"
    version.set(AbcGeom.OStringGeomParamSample(strings, constant))
    keep = [version]
    keep.append(_geom_param(AbcGeom, imath, arb, "groom_guide", np.array([guide]), constant))
    keep.append(_geom_param(AbcGeom, imath, arb, "groom_id", np.arange(S), uniform))
    keep.append(_geom_param(AbcGeom, imath, arb, "groom_group_id", np.zeros(S, dtype=np.int32), uniform))
    keep.append(_geom_param(AbcGeom, imath, arb, "groom_width", np.full(S, 2.0 * radius * CM), uniform))
    keep.append(_geom_param(AbcGeom, imath, arb, "rest_position", rest["points"] * CM, vertex))
    keep.append(_geom_param(AbcGeom, imath, arb, "rest_length", rest["length"] * CM, vertex))
    for key, values in material.items():  # SI values, per strand
        keep.append(_geom_param(AbcGeom, imath, arb, f"groomtool_{key}", values, uniform))
    for key in ("darboux", "rest_darboux"):  # clothoid results: q, q0 (1/m, SI) at each vertex
        if key in rest:
            keep.append(_geom_param(AbcGeom, imath, arb, f"groomtool_{key}", rest[key], vertex))
    return curves, keep


# ------------------------------------------------------------------------------------- reading
def read_alembic(path, scale: float = 1.0, up: str = "y", repair: bool = False) -> Groom:
    """Read the curves of an Alembic file as a validated ``Groom`` in metres (``scale`` metres per
    file unit: Unreal's grooms are in cm).  Render strands (``groom_guide`` 0 or absent) when there
    are any, else the guides.  ``metadata["alembic"]``: object paths, curve types, which were guides,
    and the groom_* / rest attributes found (``metadata["rest_data"]``: ``rest_position`` (m),
    ``rest_length`` (m), ``groom_id`` and, from a clothoid result, ``groomtool_darboux`` /
    ``groomtool_rest_darboux`` (1/m, not scaled) when one curves object was read)."""
    source = str(path)
    Abc, AbcGeom, _ = _modules(source)
    try:
        archive = Abc.IArchive(source)
    except Exception as exc:  # PyAlembic raises RuntimeError / its own types on unreadable files
        raise GroomError(f"{source}: cannot open as Alembic: {str(exc).strip().splitlines()[-1] if str(exc) else exc}") \
            from exc
    found = []
    _collect(Abc, AbcGeom, archive.getTop(), np.eye(4), found)
    if not found:
        raise GroomError(f"{source}: no curves in this Alembic file")
    render = [f for f in found if not f["guide"]]
    chosen = render or found
    strands = [f["points"] for f in chosen]
    counts = [f["counts"] for f in chosen]
    points = np.concatenate(strands) * float(scale)
    counts = np.concatenate(counts)
    if np.any(counts < 0) or counts.sum() != len(points):
        raise GroomError(f"{source}: curve vertex counts add up to {int(counts.sum())} but there are "
                         f"{len(points)} points")
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    metadata = {"format": "alembic", "alembic": {
        "objects": [f["path"] for f in chosen], "curve_types": sorted({f["type"] for f in chosen}),
        "guides": bool(chosen and not render), "attributes": sorted({a for f in chosen for a in f["params"]})}}
    groom = Groom(points, offsets, up=up, source=source, metadata=metadata)
    groom = validate(groom, repair=repair, stored_dtype=np.float32)
    rest = {}
    if len(chosen) == 1 and "repairs" not in groom.metadata:
        params = chosen[0]["params"]
        for key, unit in (("rest_position", float(scale)), ("rest_length", float(scale)), ("groom_id", None),
                          ("groomtool_darboux", None), ("groomtool_rest_darboux", None)):
            if key in params:
                rest[key] = params[key] * unit if unit is not None else params[key]
    groom.metadata["rest_data"] = rest
    return groom


def _collect(Abc, AbcGeom, obj, parent_matrix, found) -> None:
    for child in obj.children:
        matrix = parent_matrix
        meta = child.getMetaData()
        if AbcGeom.IXform.matches(meta):
            xform = AbcGeom.IXform(child, Abc.WrapExistingFlag.kWrapExisting)
            local = np.array(xform.getSchema().getValue().getMatrix(), dtype=np.float64).reshape(4, 4)
            matrix = local @ parent_matrix  # row vectors: p' = p M (Alembic, like USD)
        elif AbcGeom.ICurves.matches(meta):
            found.append(_read_curves(Abc, AbcGeom, child, parent_matrix))
        _collect(Abc, AbcGeom, child, matrix, found)


def _read_curves(Abc, AbcGeom, obj, matrix) -> dict:
    curves = AbcGeom.ICurves(obj, Abc.WrapExistingFlag.kWrapExisting)
    schema = curves.getSchema()
    sample = schema.getValue()
    points = np.array(sample.getPositions(), dtype=np.float64).reshape(-1, 3)
    counts = np.array(sample.getCurvesNumVertices(), dtype=np.int64).reshape(-1)
    if not np.allclose(matrix, np.eye(4)):
        points = points @ matrix[:3, :3] + matrix[3, :3]
    params = {}
    arb = schema.getArbGeomParams()
    if arb.valid():
        for i in range(arb.getNumProperties()):
            name = arb.getPropertyHeader(i).getName()
            value = _read_param(AbcGeom, arb, name)
            if value is not None:
                params[name] = value
    guide = "groom_guide" in params and np.size(params["groom_guide"]) and bool(np.ravel(params["groom_guide"])[0])
    return {"path": obj.getFullName(), "points": points, "counts": counts, "params": params,
            "type": str(sample.getType()).replace("kLinear", "linear").replace("kCubic", "cubic"),
            "guide": bool(guide)}


def _read_param(AbcGeom, arb, name):
    """The value of a scalar / V3f arbGeomParam as numpy (None for other types)."""
    header = arb.getPropertyHeader(name)
    pod = header.getMetaData().get("podName")
    extent = header.getMetaData().get("podExtent")
    kinds = {("float32_t", "1"): AbcGeom.IFloatGeomParam, ("int32_t", "1"): AbcGeom.IInt32GeomParam,
             ("int16_t", "1"): AbcGeom.IInt16GeomParam, ("float32_t", "3"): AbcGeom.IV3fGeomParam}
    kind = kinds.get((pod, extent))
    if kind is None:
        return None
    try:
        param = kind(arb, name)
        values = np.array(param.getExpandedValue().getVals())
    except Exception:  # a param of a compatible pod but another interpretation (e.g. color)
        try:
            param = getattr(AbcGeom, "IC3fGeomParam")(arb, name)
            values = np.array(param.getExpandedValue().getVals())
        except Exception:
            return None
    return values.reshape(-1, 3) if extent == "3" else values
