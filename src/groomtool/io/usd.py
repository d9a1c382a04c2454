"""USD (usd-core): grooms as UsdGeom.BasisCurves, with the rest data hair simulators need.

``write_usd(result, "groom.usdc")`` writes (docs/usd.md lists every primvar, its interpolation,
type and unit)::

    /Groom            Xform, the default prim
    /Groom/Strands    BasisCurves (linear): the groomed strands; per-vertex rest data under the
                      names simulators read (``physics:restShapePoints``, ``physics:restNormals``,
                      ``primvars:rest_position``, ``rest_rotation``, ``rest_bend_rotation``,
                      ``rest_length``, ``orient``), float material and discrete-rod primvars
                      ``primvars:groom:*`` and the exact double data as plain ``groomtool:*``
                      attributes (not primvars: DCCs drop double primvars)
    /Groom/RestShape  BasisCurves (linear, purpose "guide"): the rest shape, vertex for vertex
                      the points of Strands, with its ``orient``
    /Groom/Contacts   Points: contact points and forces (when there are contacts)
    /Groom/Head       Mesh: the head (when the result has one)

Stage metadata: metersPerUnit 1, kilogramsPerUnit 1, upAxis Y or Z as the groom.  A Super Space
Clothoid result (rest.npz ``model`` "clothoid") is written the same way from its clothoids, plus
``groomtool:model`` and its nodal ``groomtool:clothoid_*`` data and the per-vertex Darboux vectors
``primvars:groom:darboux`` / ``groom:rest_darboux`` (docs/usd.md).
``read_usd`` reads our files back (with their rest data) and plain BasisCurves from other tools,
applying the stage's metersPerUnit, upAxis and the prims' transforms.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdUtils, Vt

from ..groom import Groom, GroomError
from ..material import Material
from ..version import __version__
from . import fields
from .atomic import atomic_path
from .fields import consumer_rest_data, frames_to_quaternions, quaternions_to_frames, rod_polyline_data
from .formats import suffixes
from .results import CLOTHOID_KEYS, head_mesh, load_arrays, result_model
from .validate import validate

SCHEMA_VERSION = 2
NS = "groom:"  # float primvar namespace: primvars:groom:<rest.npz key>
EXACT = "groomtool:"  # exact (double / int) data as plain attributes groomtool:<rest.npz key>
ENCODING_KEY = "groomtool:encoding"  # customData: "quaternion" for frames stored as quatf
LAYOUT_KEY = "groomtool:layout"  # customData of per-vertex rod primvars: vertex | edge | interior
SHAPE_KEY = "groomtool:shape"  # customData: trailing shape of matrix-valued primvars, e.g. [3, 3]
MATERIAL_KEYS = ("young_modulus", "shear_modulus", "radius", "density", "friction")
# per-strand material arrays (S,) a result may carry; written as float primvars named after the
# scalar they refine (strand_young_modulus -> primvars:groom:young_modulus), exact as groomtool:<key>
STRAND_MATERIAL = {"strand_young_modulus": "young_modulus", "strand_shear_modulus": "shear_modulus",
                   "stiffness_factor": "stiffness_factor"}
HELIX_CONSTANT = ("element_lengths", "curvatures", "rest_curvatures")
HELIX_UNIFORM = ("root_positions", "root_frames", "fit_max_error", "stiffness_ratio")
CONTACT_KEYS = ("contact_strand_a", "contact_strand_b", "contact_s_a", "contact_s_b", "contact_points_b",
                "contact_normals", "contact_frames", "contact_forces")
GROOM, STRANDS, REST, CONTACTS, HEAD = "/Groom", "/Groom/Strands", "/Groom/RestShape", "/Groom/Contacts", "/Groom/Head"


# ------------------------------------------------------------------------------------- writing
def write_usd(source, path, per_element: int = 8, head=None) -> Path:
    """Write a result (``InversionResult``, output directory, rest.npz or its arrays) as USD.

    The format follows the extension: .usda (text), .usdc or .usd (binary crate), .usdz (package).
    ``per_element``: samples per rod element (helix or clothoid) of the sampled shapes; ``head``: a trimesh used when
    the result holds no head.  Written atomically; returns the path.
    """
    arrays = load_arrays(source)
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in suffixes("usd"):
        raise GroomError(f"{path}: USD files end in .usda, .usdc, .usd or .usdz")
    stage = build_stage(arrays, per_element, head)
    with atomic_path(path) as tmp:
        if suffix == ".usdz":
            crate = tmp.with_suffix(".usdc")
            try:
                stage.GetRootLayer().Export(str(crate))
                if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(crate)), str(tmp)):
                    raise GroomError(f"{path}: could not package the usdz")
            finally:
                crate.unlink(missing_ok=True)
        elif not stage.GetRootLayer().Export(str(tmp)):
            raise GroomError(f"{path}: USD export failed")
    return path


def build_stage(arrays: dict, per_element: int = 8, head=None) -> Usd.Stage:
    """The in-memory stage that :func:`write_usd` saves."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    up = _signed_up(arrays)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up.endswith("z") else UsdGeom.Tokens.y)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, GROOM).GetPrim()
    stage.SetDefaultPrim(root)
    samples = fields.sample(arrays, per_element)
    radius = float(arrays.get("radius", Material.radius))  # rest.npz before it held the radius
    rod_points, rod_offsets, rod_data, origin, arc = rod_polyline_data(arrays, samples)
    clothoid = result_model(arrays) == "clothoid"
    layer_data = {"version": __version__, "schema_version": SCHEMA_VERSION, "up": up,
                  "source": str(arrays.get("source", "")), "discrete_rest_data": origin}
    if clothoid:  # Super-Helix files stay as they were: no "model" means Super-Helices, as in rest.npz
        layer_data["model"] = "clothoid"
    stage.GetRootLayer().customLayerData = {"groomtool": layer_data}

    curves = _curves(stage, STRANDS, rod_points, rod_offsets, radius, (0.45, 0.3, 0.15))
    prim = curves.GetPrim()
    pv = UsdGeom.PrimvarsAPI(curves)
    S = len(rod_offsets) - 1
    # material: float primvars per strand (what DCCs import), exact values as groomtool:* attributes
    for key in MATERIAL_KEYS:
        if key in arrays:
            _exact(prim, key, np.asarray(arrays[key], dtype=np.float64))
            _primvar(pv, key, np.full(S, float(arrays[key])), UsdGeom.Tokens.uniform)
    for key, name in STRAND_MATERIAL.items():
        if key in arrays and np.asarray(arrays[key]).shape == (S,):
            _exact(prim, key, np.asarray(arrays[key], dtype=np.float64))
            _primvar(pv, name, np.asarray(arrays[key]), UsdGeom.Tokens.uniform)
    _exact(prim, "strand_offsets", np.asarray(arrays["strand_offsets"]))
    for key in HELIX_CONSTANT:
        _exact(prim, key, np.asarray(arrays[key]))
    if clothoid:  # the nodal Darboux vectors: the clothoid itself (its per-element values are element means)
        model = prim.CreateAttribute(EXACT + "model", Sdf.ValueTypeNames.String, custom=True)
        model.Set("clothoid")
        for key in CLOTHOID_KEYS:
            _exact(prim, key, np.asarray(arrays[key]))
    for key in HELIX_UNIFORM:
        if key in arrays and len(arrays[key]) == S:
            _exact(prim, key, np.asarray(arrays[key]))
            if np.asarray(arrays[key]).ndim == 1:  # fit_max_error, stiffness_ratio: shown in DCCs
                _primvar(pv, key, np.asarray(arrays[key]), UsdGeom.Tokens.uniform)
    if "gravity" in arrays:
        _exact(prim, "gravity", np.asarray(arrays["gravity"], dtype=np.float64).reshape(3))
    for key, (values, layout) in rod_data.items():
        _primvar(pv, key, _pad(values, layout, rod_offsets), UsdGeom.Tokens.vertex, layout=layout)

    rest = consumer_rest_data(arrays, rod_points, rod_offsets, arc, rod_data)
    _write_consumer_rest(curves, rest)
    rest_curves = _curves(stage, REST, rest["points"], rod_offsets, radius, (0.2, 0.5, 0.9))
    rest_curves.CreatePurposeAttr(UsdGeom.Tokens.guide)
    _quat_primvar(UsdGeom.PrimvarsAPI(rest_curves), "orient", rest["rotation"])
    _write_contacts(stage, arrays, radius)
    mesh = head_mesh(arrays)
    if mesh is None and head is not None:
        mesh = (np.asarray(head.vertices), np.asarray(head.faces))
    if mesh is not None:
        _write_head(stage, *mesh)
    return stage


def _signed_up(arrays: dict) -> str:
    """The groom's up direction (x, y, z, -x, -y, -z): opposite to ``gravity``, "y" when unknown."""
    g = np.asarray(arrays.get("gravity", np.zeros(3)), dtype=np.float64).reshape(-1)
    if g.size != 3 or not np.any(g):
        return "y"
    axis = int(np.argmax(np.abs(g)))
    return ("" if g[axis] < 0 else "-") + "xyz"[axis]


def _write_consumer_rest(curves: UsdGeom.BasisCurves, rest: dict) -> None:
    prim = curves.GetPrim()
    points = prim.CreateAttribute("physics:restShapePoints", Sdf.ValueTypeNames.Point3fArray, custom=False)
    points.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(rest["points"], dtype=np.float32)))
    normals = prim.CreateAttribute("physics:restNormals", Sdf.ValueTypeNames.Normal3fArray, custom=False)
    normals.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(rest["normals"], dtype=np.float32)))
    pv = UsdGeom.PrimvarsAPI(curves)
    position = pv.CreatePrimvar("rest_position", Sdf.ValueTypeNames.Point3fArray, UsdGeom.Tokens.vertex)
    position.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(rest["points"], dtype=np.float32)))
    length = pv.CreatePrimvar("rest_length", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
    length.Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(rest["length"], dtype=np.float32)))
    _quat_primvar(pv, "rest_rotation", rest["rotation"])
    _quat_primvar(pv, "rest_bend_rotation", rest["bend_rotation"])
    _quat_primvar(pv, "orient", rest["orient"])
    for key in ("darboux", "rest_darboux"):  # clothoid results: q and q0 at each vertex (linear per element)
        if key in rest:
            _primvar(pv, key, rest[key], UsdGeom.Tokens.vertex, layout="vertex")


def _quat_primvar(pv: UsdGeom.PrimvarsAPI, name: str, q: np.ndarray) -> UsdGeom.Primvar:
    """A quatf[] vertex primvar from (n, 4) quaternions (x, y, z, w), USD's memory order."""
    primvar = pv.CreatePrimvar(name, Sdf.ValueTypeNames.QuatfArray, UsdGeom.Tokens.vertex)
    primvar.Set(Vt.QuatfArray.FromNumpy(np.ascontiguousarray(q, dtype=np.float32)))
    return primvar


def _pad(values: np.ndarray, layout: str, offsets: np.ndarray) -> np.ndarray:
    """Per-edge / per-interior-vertex values stored at vertices: edge j at its first vertex,
    interior vertex at itself; the strand's tip (edges) and root and tip (interior) hold zeros."""
    from ..rods.discrete import edge_start_vertices, interior_vertices

    if layout == "vertex":
        return values
    out = np.zeros((int(offsets[-1]),) + values.shape[1:], dtype=values.dtype)
    out[edge_start_vertices(offsets) if layout == "edge" else interior_vertices(offsets)] = values
    return out


def _unpad(values: np.ndarray, layout: str, offsets: np.ndarray) -> np.ndarray:
    from ..rods.discrete import edge_start_vertices, interior_vertices

    if layout == "edge":
        return values[edge_start_vertices(offsets)]
    if layout == "interior":
        return values[interior_vertices(offsets)]
    return values


_FLOAT = {1: (Sdf.ValueTypeNames.FloatArray, Vt.FloatArray), 2: (Sdf.ValueTypeNames.Float2Array, Vt.Vec2fArray),
          3: (Sdf.ValueTypeNames.Float3Array, Vt.Vec3fArray)}
_DOUBLE = {1: (Sdf.ValueTypeNames.DoubleArray, Vt.DoubleArray), 2: (Sdf.ValueTypeNames.Double2Array, Vt.Vec2dArray),
           3: (Sdf.ValueTypeNames.Double3Array, Vt.Vec3dArray)}


def _primvar(pv: UsdGeom.PrimvarsAPI, key: str, values: np.ndarray, interpolation, double: bool = False,
             layout: str | None = None) -> UsdGeom.Primvar:
    """Create primvars:groom:<key>.  Ints as int[]; floats as float or double, (n, 2) and (n, 3) as
    2- and 3-vectors; (n, 3, 3) rotations (frames, rows d1 d2 d3) as quatf (customData
    ``groomtool:encoding = "quaternion"``, DCCs read quaternions but zero 9-value elements); other
    trailing shapes flattened with elementSize = components (the shape, e.g. [3, 3], in customData).
    A constant array primvar gets elementSize = its length (one value)."""
    values = np.asarray(values)
    n, trailing = len(values), values.shape[1:]
    if trailing == (3, 3) and values.dtype.kind == "f" and _are_rotations(values):
        live = np.any(values.reshape(n, 9) != 0, axis=1)  # padding (tips, roots): identity
        q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        q[live] = frames_to_quaternions(values[live].astype(np.float64))
        primvar = _quat_primvar(pv, NS + key, q)
        primvar.SetInterpolation(interpolation)
        attr = primvar.GetAttr()
        attr.SetCustomDataByKey(ENCODING_KEY, "quaternion")
        attr.SetCustomDataByKey(SHAPE_KEY, Vt.IntArray([3, 3]))
        if layout is not None:
            attr.SetCustomDataByKey(LAYOUT_KEY, layout)
        return primvar
    k = int(np.prod(trailing)) if trailing else 1
    if values.dtype.kind in "iub":
        (type_name, vt), flat = (Sdf.ValueTypeNames.IntArray, Vt.IntArray), values.astype(np.int32).reshape(n, k)
        vector = False
    else:
        table, dtype = (_DOUBLE, np.float64) if double else (_FLOAT, np.float32)
        flat = values.astype(dtype).reshape(n, k)
        vector = k in (2, 3) and len(trailing) == 1
        type_name, vt = table[k] if vector else table[1]
    primvar = pv.CreatePrimvar(NS + key, type_name, interpolation)
    primvar.Set(vt.FromNumpy(np.ascontiguousarray(flat if vector else flat.ravel())))
    element_size = 1 if vector else k
    if interpolation == UsdGeom.Tokens.constant:
        element_size *= n
    if element_size > 1:
        primvar.SetElementSize(element_size)
    attr = primvar.GetAttr()
    if layout is not None:
        attr.SetCustomDataByKey(LAYOUT_KEY, layout)
    if len(trailing) > 1:
        attr.SetCustomDataByKey(SHAPE_KEY, Vt.IntArray([int(d) for d in trailing]))
    return primvar


def _are_rotations(m: np.ndarray, tol: float = 1e-6) -> bool:
    """True when every (3, 3) matrix (rows) is orthonormal and right-handed (padding zeros allowed)."""
    m = np.asarray(m, dtype=np.float64)
    live = np.any(m.reshape(len(m), 9) != 0, axis=1)
    m = m[live]
    gram = np.einsum("nij,nkj->nik", m, m)
    return bool(np.all(np.abs(gram - np.eye(3)) <= tol) and np.all(np.linalg.det(m) > 0))


def _exact(prim, key: str, values: np.ndarray):
    """Plain attribute groomtool:<key> with the exact value: double / double3 scalars, int[],
    double[] and double3[] arrays; other trailing shapes flattened with the shape in customData."""
    values = np.asarray(values)
    name = EXACT + key
    if values.ndim == 0:
        attr = prim.CreateAttribute(name, Sdf.ValueTypeNames.Double, custom=True)
        attr.Set(float(values))
        return attr
    if values.ndim == 1 and values.shape == (3,) and key == "gravity":
        attr = prim.CreateAttribute(name, Sdf.ValueTypeNames.Double3, custom=True)
        attr.Set(Gf.Vec3d(*map(float, values)))
        return attr
    trailing = values.shape[1:]
    if values.dtype.kind in "iub":
        attr = prim.CreateAttribute(name, Sdf.ValueTypeNames.IntArray, custom=True)
        attr.Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(values.astype(np.int32).ravel())))
    elif trailing == (3,):
        attr = prim.CreateAttribute(name, Sdf.ValueTypeNames.Double3Array, custom=True)
        attr.Set(Vt.Vec3dArray.FromNumpy(np.ascontiguousarray(values, dtype=np.float64)))
    else:
        attr = prim.CreateAttribute(name, Sdf.ValueTypeNames.DoubleArray, custom=True)
        attr.Set(Vt.DoubleArray.FromNumpy(np.ascontiguousarray(values, dtype=np.float64).ravel()))
    if len(trailing) > 1 or (trailing and trailing != (3,)):
        attr.SetCustomDataByKey(SHAPE_KEY, Vt.IntArray([int(d) for d in trailing]))
    return attr


def _curves(stage, prim_path: str, points, offsets, radius: float, color) -> UsdGeom.BasisCurves:
    curves = UsdGeom.BasisCurves.Define(stage, prim_path)
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32)))
    curves.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(np.diff(offsets).astype(np.int32)))
    curves.CreateWidthsAttr(Vt.FloatArray([2.0 * radius]))
    curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    if len(points):
        lo, hi = np.min(points, axis=0), np.max(points, axis=0)
        curves.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*(lo - radius)), Gf.Vec3f(*(hi + radius))]))
    curves.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*color)]))
    return curves


def _write_contacts(stage, arrays: dict, radius: float) -> None:
    points = np.asarray(arrays.get("contact_points", np.zeros((0, 3)))).reshape(-1, 3)
    if len(points) == 0:
        return
    prim = UsdGeom.Points.Define(stage, CONTACTS)
    prim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32)))
    prim.CreateWidthsAttr(Vt.FloatArray([8.0 * radius]))
    prim.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    prim.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(0.9, 0.1, 0.1)]))
    pv = UsdGeom.PrimvarsAPI(prim)
    for key in CONTACT_KEYS:
        if key in arrays and len(arrays[key]) == len(points):
            value = np.asarray(arrays[key])
            if value.dtype.kind in "iub":  # strand ids: int primvars, DCCs read them
                _primvar(pv, key, value, UsdGeom.Tokens.vertex)
            else:
                _exact(prim.GetPrim(), key, value)
    _primvar(pv, "contact_force_world", fields.contact_forces_world(arrays), UsdGeom.Tokens.vertex)


def _write_head(stage, vertices: np.ndarray, faces: np.ndarray) -> None:
    mesh = UsdGeom.Mesh.Define(stage, HEAD)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(vertices, dtype=np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, dtype=np.int32).ravel()))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*lo), Gf.Vec3f(*hi)]))
    mesh.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(0.85, 0.7, 0.6)]))


# ------------------------------------------------------------------------------------- reading
def read_usd(path, scale: float = 1.0, up: str = "y", repair: bool = False, *, prim: str | None = None,
             all_curves: bool = False) -> Groom:
    """Read the strands of a USD file as a validated ``Groom`` in metres.

    Which curves: ``prim`` (a prim path), else every non-guide BasisCurves prim (``all_curves``)
    or the first one in stage order (for our files, /Groom/Strands).  Points are taken at the
    default time (else the earliest time sample), moved by the prim's world transform and scaled
    by the stage's metersPerUnit; ``scale`` (metres per unit) and ``up`` apply only when the stage
    does not author metersPerUnit / upAxis.  Cubic curves are read as their control polygons.

    ``metadata["usd"]``: prim paths, metersPerUnit, upAxis, curve type.  ``metadata["rest_data"]``:
    for a single curves prim, its ``primvars:groom:*`` arrays (unpadded, rest.npz names), and for
    our files ``rest_points``/``rest_offsets``, the contact arrays and ``head_vertices``/``head_faces``.
    """
    source = str(path)
    stage = _open(source)
    chosen = _select_curves(stage, source, prim, all_curves)
    meters = UsdGeom.GetStageMetersPerUnit(stage) if UsdGeom.StageHasAuthoredMetersPerUnit(stage) else float(scale)
    if stage.HasAuthoredMetadata("upAxis"):
        up = str(UsdGeom.GetStageUpAxis(stage)).lower()
        ours = dict(stage.GetRootLayer().customLayerData.get("groomtool", {}))
        if str(ours.get("up", "")).lstrip("-") in ("x", "y", "z"):
            up = str(ours["up"])  # ours: the signed direction (USD's upAxis is only Y or Z)
    strands, counts, kinds = [], [], set()
    for p in chosen:
        pts, cnt = _curve_points(p, source)
        strands.append(pts)
        counts.append(cnt)
        kinds.add(str(UsdGeom.BasisCurves(p).GetTypeAttr().Get() or "cubic"))
    points = np.concatenate(strands) * meters
    counts = np.concatenate(counts)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    metadata = {"format": "usd", "usd": {"prims": [str(p.GetPath()) for p in chosen], "meters_per_unit": meters,
                                         "up_axis": up, "curve_types": sorted(kinds)}}
    groom = Groom(points, offsets, up=up, source=source, metadata=metadata)
    groom = validate(groom, repair=repair, stored_dtype=np.float32)  # points are point3f[]
    try:
        rest = _rest_data(stage, chosen[0], offsets) if len(chosen) == 1 else {}
    except (TypeError, ValueError, IndexError) as exc:  # primvars of the wrong type or length
        raise GroomError(f"{source}: {chosen[0].GetPath()}: malformed groom primvars or rest data ({exc})") from None
    groom.metadata["rest_data"] = {} if "repairs" in groom.metadata else rest
    return groom


def _open(source: str) -> Usd.Stage:
    try:
        stage = Usd.Stage.Open(source)
    except Exception as exc:  # pxr raises Tf.ErrorException for unreadable layers
        raise GroomError(f"{source}: cannot open as USD: {_pxr_message(exc)}") from None
    if stage is None:
        raise GroomError(f"{source}: cannot open as USD")
    return stage


def _pxr_message(exc) -> str:
    """The last line of a pxr error, which may itself fail to decode (a non-UTF-8 file)."""
    try:
        lines = str(exc).strip().splitlines()
    except Exception:  # noqa: BLE001 - UnicodeDecodeError inside Tf.ErrorException.__str__
        return "not UTF-8 text, or a corrupt file"
    return lines[-1].strip() if lines else type(exc).__name__


def _select_curves(stage, source: str, prim: str | None, all_curves: bool) -> list:
    if prim is not None:
        p = stage.GetPrimAtPath(prim)
        if not p or not p.IsA(UsdGeom.BasisCurves):
            raise GroomError(f"{source}: no BasisCurves prim at {prim}")
        return [p]
    curves = [p for p in stage.Traverse() if p.IsA(UsdGeom.BasisCurves)]
    if not curves:
        types = sorted({str(p.GetTypeName()) for p in stage.Traverse() if p.GetTypeName()})
        raise GroomError(f"{source}: no BasisCurves prim (found: {', '.join(types) or 'no typed prims'})")
    rendered = [p for p in curves if UsdGeom.Imageable(p).ComputePurpose() != UsdGeom.Tokens.guide] or curves
    return rendered if all_curves else rendered[:1]


def _attr_value(attr):
    value = attr.Get(Usd.TimeCode.Default())
    if value is None and attr.GetNumTimeSamples():
        value = attr.Get(Usd.TimeCode.EarliestTime())
    return value


def _curve_points(prim, source: str):
    """World-space points (n, 3) and vertex counts of one BasisCurves prim, unscaled."""
    curves = UsdGeom.BasisCurves(prim)
    points_attr = curves.GetPointsAttr()
    pts = _attr_value(points_attr)
    cnt = _attr_value(curves.GetCurveVertexCountsAttr())
    where = f"{source}: {prim.GetPath()}"
    if pts is None or cnt is None:
        raise GroomError(f"{where}: BasisCurves without points or curveVertexCounts")
    try:
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        cnt = np.asarray(cnt, dtype=np.int64).reshape(-1)
    except (TypeError, ValueError) as exc:  # an unregistered value type, a ragged array
        raise GroomError(f"{where}: points or curveVertexCounts are not numeric arrays ({exc})") from None
    if np.any(cnt < 0) or cnt.sum() != len(pts):
        raise GroomError(f"{where}: curveVertexCounts add up to {int(cnt.sum())} but there are {len(pts)} points")
    time = Usd.TimeCode.Default() if points_attr.HasAuthoredValue() and not points_attr.GetNumTimeSamples() \
        else Usd.TimeCode.EarliestTime()
    m = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time))
    if not np.allclose(m, np.eye(4)):
        pts = pts @ m[:3, :3] + m[3, :3]
    return pts, cnt


def _primvar_array(primvar, offsets=None):
    """A groom primvar as numpy, matrix shape restored, per-vertex rod data unpadded."""
    value = primvar.Get()
    if value is None:
        return None
    arr = np.asarray(value)
    if arr.dtype.kind == "i":
        arr = arr.astype(np.int64)
    attr = primvar.GetAttr()
    k = primvar.GetElementSize() if primvar.GetInterpolation() != UsdGeom.Tokens.constant else 1
    shape = attr.GetCustomDataByKey(SHAPE_KEY)
    if attr.GetCustomDataByKey(ENCODING_KEY) == "quaternion":
        q = np.asarray(arr, dtype=np.float64).reshape(-1, 4)
        live = np.any(q != 0, axis=1)  # padding (tips, roots) stays zero
        arr = np.zeros((len(q), 3, 3))
        arr[live] = quaternions_to_frames(q[live])
    elif shape is not None:
        arr = arr.reshape((-1,) + tuple(int(d) for d in shape))
    elif k > 1 and arr.ndim == 1:
        arr = arr.reshape(-1, k)
    layout = attr.GetCustomDataByKey(LAYOUT_KEY)
    if layout is not None and offsets is not None:
        arr = _unpad(arr, str(layout), offsets)
    return arr


def _groom_primvars(prim, offsets=None) -> dict:
    """primvars:groom:<key> (float data, unpadded) overridden by the exact groomtool:<key>
    attributes (schema 2; schema 1 files hold their double data as primvars)."""
    out = {}
    for primvar in UsdGeom.PrimvarsAPI(prim).GetPrimvars():
        name = primvar.GetPrimvarName()
        if name.startswith(NS):
            value = _primvar_array(primvar, offsets)
            if value is not None:
                out[name[len(NS):]] = value
    for attr in prim.GetAttributes():
        name = attr.GetName()
        if name.startswith(EXACT) and attr.HasAuthoredValue():
            value = np.asarray(attr.Get())
            if value.dtype.kind in "USO":  # groomtool:model
                out[name[len(EXACT):]] = np.array(str(attr.Get()))
                continue
            if value.dtype.kind == "i":
                value = value.astype(np.int64)
            shape = attr.GetCustomDataByKey(SHAPE_KEY)
            if shape is not None:
                value = value.reshape((-1,) + tuple(int(d) for d in shape))
            key = name[len(EXACT):]
            out[key] = np.float64(value) if value.ndim == 0 else value
    return out


def _rest_data(stage, prim, offsets: np.ndarray) -> dict:
    """The groom primvars of ``prim`` (unpadded by ``offsets``) and, for our files, the rest shape,
    contacts and head; material constants come back as scalars."""
    data = _groom_primvars(prim, offsets)
    for key in MATERIAL_KEYS:
        if key in data and np.ndim(data[key]) and len(data[key]):
            data[key] = np.float64(data[key][0])
    if "gravity" in data:
        data["gravity"] = data["gravity"].reshape(3)
    if str(prim.GetPath()) != STRANDS:
        return data
    rest = stage.GetPrimAtPath(REST)
    if rest and rest.IsA(UsdGeom.BasisCurves):
        pts, cnt = _curve_points(rest, "")
        data["rest_points"] = pts
        data["rest_offsets"] = np.concatenate([[0], np.cumsum(cnt)]).astype(np.int64)
    contacts = stage.GetPrimAtPath(CONTACTS)
    if contacts and contacts.IsA(UsdGeom.Points):
        data["contact_points"] = np.asarray(UsdGeom.Points(contacts).GetPointsAttr().Get(), dtype=np.float64)
        data.update(_groom_primvars(contacts))
    head = stage.GetPrimAtPath(HEAD)
    if head and head.IsA(UsdGeom.Mesh):
        mesh = UsdGeom.Mesh(head)
        data["head_vertices"] = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
        data["head_faces"] = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
    return data
