"""PLY polylines: a ``vertex`` element (x, y, z) and an ``edge`` element (vertex1, vertex2),
ASCII or binary (either byte order).  Edges sharing an end vertex join into strands as OBJ ``l``
records do; without edges, ``strand_length`` splits the vertices into strands.  Other elements
and properties are skipped.
"""

from __future__ import annotations

import numpy as np

from ..groom import Groom, GroomError
from .chain import chain_segments, split_fixed
from .common import read_input
from .validate import validate

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


class _Element:
    def __init__(self, name: str, count: int):
        self.name, self.count = name, count
        self.props: list[tuple[str, str, str | None]] = []  # (name, type, list-count type or None)

    @property
    def has_lists(self) -> bool:
        return any(p[2] is not None for p in self.props)


def _type(name: str, source: str, no: int) -> str:
    if name not in _TYPES:
        raise GroomError(f"{source}: header line {no}: unknown PLY type {name!r}")
    return _TYPES[name]


def _parse_header(data: bytes, source: str):
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise GroomError(f"{source}: not a PLY file (no 'ply' ... 'end_header' header)")
    body = data.find(b"\n", end) + 1 or len(data)
    fmt, elements = None, []
    for no, line in enumerate(data[:end].decode("latin-1").splitlines()[1:], 2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
                if fmt not in _FORMATS:
                    raise GroomError(f"{source}: header line {no}: unknown PLY format {fmt!r}")
            elif words[0] == "element":
                count = int(words[2])
                if count < 0:
                    raise GroomError(f"{source}: header line {no}: element {words[1]!r} has a negative count {count}")
                if any(el.name == words[1] for el in elements):
                    raise GroomError(f"{source}: header line {no}: element {words[1]!r} declared twice")
                elements.append(_Element(words[1], count))
            elif words[0] == "property":
                if words[1] == "list":
                    prop = (words[4], _type(words[3], source, no), _type(words[2], source, no))
                else:
                    prop = (words[2], _type(words[1], source, no), None)
                if any(p[0] == prop[0] for p in elements[-1].props):
                    raise GroomError(f"{source}: header line {no}: property {prop[0]!r} of element "
                                     f"{elements[-1].name!r} declared twice")
                elements[-1].props.append(prop)
            else:
                raise ValueError
        except GroomError:
            raise
        except (IndexError, ValueError):
            raise GroomError(f"{source}: header line {no}: cannot parse {line.strip()!r}") from None
    if fmt is None:
        raise GroomError(f"{source}: PLY header has no format line")
    return fmt, elements, body


def _read_ascii(body: bytes, elements, source: str) -> dict:
    tokens = body.split()
    pos, out = 0, {}
    for el in elements:
        if el.has_lists and el.count * len(el.props) > len(tokens) - pos:  # a token per property at least
            raise GroomError(f"{source}: element {el.name!r} declares {el.count} records but the file ends after "
                             f"{len(tokens) - pos} more values")
        if not el.props:  # nothing to read
            out[el.name] = {}
            continue
        if not el.has_lists:
            k = len(el.props)
            if pos + k * el.count > len(tokens):
                raise GroomError(f"{source}: the file ends inside element {el.name!r} ({el.count} records declared)")
            try:
                table = np.array(tokens[pos : pos + k * el.count], dtype=np.float64).reshape(el.count, k)
            except ValueError:
                raise GroomError(f"{source}: element {el.name!r} holds a value that is not a number") from None
            out[el.name] = {p[0]: table[:, j] for j, p in enumerate(el.props)}
            pos += k * el.count
            continue
        for record in range(el.count):  # list properties: skip record by record
            for _, _, list_type in el.props:
                try:
                    n = int(tokens[pos]) if list_type is not None else 0
                except (IndexError, ValueError):
                    raise GroomError(f"{source}: element {el.name!r}, record {record}: cut off or malformed") from None
                if n < 0:
                    raise GroomError(f"{source}: element {el.name!r}, record {record}: a list of {n} items")
                pos += 1 + n
        if pos > len(tokens):
            raise GroomError(f"{source}: the file ends inside element {el.name!r}")
    return out


def _read_binary(body: bytes, elements, order: str, source: str) -> dict:
    pos, out = 0, {}
    for el in elements:
        least = sum(np.dtype(p[2] if p[2] is not None else p[1]).itemsize for p in el.props)  # bytes per record
        if el.has_lists and el.count * least > len(body) - pos:  # before looping over the records
            raise GroomError(f"{source}: element {el.name!r} declares {el.count} records of at least {least} bytes "
                             f"but {len(body) - pos} bytes are left")
        if not el.props:  # nothing to read
            out[el.name] = {}
            continue
        if not el.has_lists:
            dtype = np.dtype([(p[0], order + p[1]) for p in el.props])
            if pos + dtype.itemsize * el.count > len(body):
                got = (len(body) - pos) // max(dtype.itemsize, 1)
                raise GroomError(
                    f"{source}: the file ends inside element {el.name!r} after {got} of {el.count} records"
                )
            table = np.frombuffer(body, dtype=dtype, count=el.count, offset=pos)
            out[el.name] = {p[0]: table[p[0]] for p in el.props}
            pos += dtype.itemsize * el.count
            continue
        for record in range(el.count):  # list properties: skip record by record
            for _, item, list_type in el.props:
                item_size = np.dtype(item).itemsize
                if list_type is None:
                    pos += item_size
                    continue
                count_dtype = np.dtype(order + list_type)
                if pos + count_dtype.itemsize > len(body):
                    raise GroomError(f"{source}: the file ends inside element {el.name!r}, record {record}")
                n = int(np.frombuffer(body, dtype=count_dtype, count=1, offset=pos)[0])
                if n < 0:
                    raise GroomError(f"{source}: element {el.name!r}, record {record}: a list of {n} items")
                pos += count_dtype.itemsize + n * item_size
        if pos > len(body):
            raise GroomError(f"{source}: the file ends inside element {el.name!r}")
    return out


def read_ply(path, scale: float = 1.0, up: str = "y", repair: bool = False, strand_length=None) -> Groom:
    """Read PLY polylines; coordinates times ``scale`` give metres.

    ``strand_length`` (vertices per strand) is used only when the file has no edges.
    """
    source = str(path)
    data = read_input(path)
    fmt, elements, body = _parse_header(data, source)
    if fmt == "ascii":
        tables = _read_ascii(data[body:], elements, source)
    else:
        tables = _read_binary(data[body:], elements, _FORMATS[fmt], source)
    vertex = tables.get("vertex")
    if vertex is None or not {"x", "y", "z"} <= vertex.keys():
        raise GroomError(f"{source}: no vertex element with x, y, z properties")
    coords = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)
    n_vertices = len(coords)
    edge = tables.get("edge")
    if edge is not None and not {"vertex1", "vertex2"} <= edge.keys():
        raise GroomError(f"{source}: the edge element needs vertex1 and vertex2 properties")

    if edge is not None and len(edge["vertex1"]):
        a, b = (np.asarray(edge[k]).astype(np.int64) for k in ("vertex1", "vertex2"))
        bad = np.flatnonzero((a < 0) | (a >= n_vertices) | (b < 0) | (b >= n_vertices))
        if len(bad):
            raise GroomError(
                f"{source}: edge {bad[0]} joins vertices {a[bad[0]]} and {b[bad[0]]} "
                f"but there are {n_vertices} vertices"
            )
        order, offsets = chain_segments(a, b, n_vertices, lambda i: f"edge {i}", source, base=0)
        points = coords[order]
    elif n_vertices and strand_length is not None:
        offsets, points = split_fixed(n_vertices, strand_length, source), coords
    elif any(el.name == "face" and el.count for el in elements):
        raise GroomError(f"{source}: has faces but no edges: a mesh, not a groom (a head?)")
    else:
        raise GroomError(
            f"{source}: has {n_vertices} vertices but no edges: pass strand_length=N "
            "(vertices per strand) to split them into strands"
        )
    x_type = next(p[1] for el in elements if el.name == "vertex" for p in el.props if p[0] == "x")
    stored = np.float64 if x_type == "f8" else np.float32  # what the file's precision can resolve
    groom = Groom(points * scale, offsets, up=up, source=source, metadata={"format": "ply"})
    return validate(groom, repair=repair, stored_dtype=stored)
