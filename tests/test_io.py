"""Readers, writers, the dispatcher, head meshes and atomic writes (errors: test_io_errors.py)."""

import os
import struct
import sys
import time

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from groomtool import Groom, GroomError
from groomtool.io import (
    atomic_open,
    atomic_path,
    atomic_write,
    load_groom,
    load_head,
    read_hair,
    read_obj,
    save_groom,
)


def random_groom(seed: int, n_strands: int, max_vertices: int = 30, size: float = 1.0) -> Groom:
    """Random walks (steps >= 1 mm x size) starting anywhere in a box of side ``size``."""
    rng = np.random.default_rng(seed)
    strands = []
    for _ in range(n_strands):
        n = int(rng.integers(2, max_vertices + 1))
        steps = rng.normal(size=(n - 1, 3))
        steps *= (rng.uniform(1e-3, 1e-2, n - 1) / np.linalg.norm(steps, axis=1))[:, None]
        root = rng.uniform(-0.5, 0.5, 3)
        strands.append(size * np.vstack([root, root + np.cumsum(steps, axis=0)]))
    return Groom.from_strands(strands)


def assert_same(a: Groom, b: Groom, rtol: float = 1e-6) -> None:
    np.testing.assert_array_equal(a.offsets, b.offsets)
    np.testing.assert_allclose(a.points, b.points, rtol=0, atol=rtol * np.abs(a.points).max())


def write_ply(path, points, edges, fmt="ascii", vertex_type="float", extra_face=False):
    """A small PLY writer for tests: vertex (x, y, z, an extra property) and edge elements."""
    points, edges = np.asarray(points), np.asarray(edges)
    header = ["ply", f"format {fmt} 1.0", "comment made by the groomtool tests",
              f"element vertex {len(points)}"]
    header += [f"property {vertex_type} {c}" for c in "xyz"] + ["property uchar red"]
    if extra_face:
        header += ["element face 1", "property list uchar int vertex_indices"]
    header += [f"element edge {len(edges)}", "property int vertex1", "property int vertex2", "end_header"]
    head = ("\n".join(header) + "\n").encode()
    if fmt == "ascii":
        rows = [f"{x!r} {y!r} {z!r} 7" for x, y, z in points.tolist()]
        rows += ["3 0 1 2"] if extra_face else []
        rows += [f"{a} {b}" for a, b in edges]
        path.write_bytes(head + ("\n".join(rows) + "\n").encode())
        return
    order = "<" if fmt == "binary_little_endian" else ">"
    f = "f4" if vertex_type == "float" else "f8"
    vertex = np.zeros(len(points), dtype=[("x", order + f), ("y", order + f), ("z", order + f), ("red", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = points.T
    face = struct.pack(order + "B3i", 3, 0, 1, 2) if extra_face else b""
    edge = np.asarray(edges, dtype=order + "i4")
    path.write_bytes(head + vertex.tobytes() + face + edge.tobytes())


def strand_edges(groom: Groom) -> np.ndarray:
    ids = np.arange(groom.n_points)
    keep = np.ones(groom.n_points - 1, dtype=bool)
    keep[groom.offsets[1:-1] - 1] = False
    return np.stack([ids[:-1][keep], ids[1:][keep]], axis=1)


# ---------------------------------------------------------------------------- round trips
@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 12),
       suffix=st.sampled_from([".obj", ".data", ".hair"]), units=st.sampled_from(["m", "cm", "mm", 0.0254]))
def test_round_trip(tmp_path_factory, seed, n, suffix, units):
    groom = random_groom(seed, n)
    path = tmp_path_factory.mktemp("rt") / f"g{suffix}"
    save_groom(groom, path, units=units)
    back = load_groom(path, units=units)
    assert_same(groom, back)
    assert back.source == str(path) and back.up == "y"
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temp file left


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 10),
       fmt=st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]),
       vertex_type=st.sampled_from(["float", "double"]), shuffle=st.booleans())
def test_ply_edges(tmp_path_factory, seed, n, fmt, vertex_type, shuffle):
    groom = random_groom(seed, n)
    if vertex_type == "float":
        groom = Groom(groom.points.astype(np.float32), groom.offsets)
    edges, expected = strand_edges(groom), groom
    if shuffle:  # edge order must not matter, only their direction
        edges = edges[np.random.default_rng(seed).permutation(len(edges))]
        first_edge = [np.flatnonzero(edges[:, 0] == root)[0] for root in groom.offsets[:-1]]
        expected = groom.subset(np.argsort(first_edge))  # strands come in the order of their first edge
    path = tmp_path_factory.mktemp("ply") / "g.ply"
    write_ply(path, groom.points, edges, fmt, vertex_type, extra_face=True)
    assert_same(expected, load_groom(path), rtol=1e-12)


def test_same_groom_in_every_format(tmp_path):
    groom = random_groom(7, 20, size=0.3)
    loaded = []
    for suffix in (".obj", ".data", ".hair"):
        loaded.append(load_groom(save_groom(groom, tmp_path / f"g{suffix}")))
    write_ply(tmp_path / "g.ply", groom.points, strand_edges(groom))
    loaded.append(load_groom(tmp_path / "g.ply"))
    for g in loaded:
        assert_same(loaded[0], g)


# ---------------------------------------------------------------------------- OBJ variants
STRAND_A = [[0, 0, 0], [0, -1, 0], [0, -2, 0.5]]
STRAND_B = [[1, 0, 0], [1, -1, 0], [1, -2, 0], [1, -3, 1]]


def obj_text(body: str) -> str:
    vs = "".join(f"v {x} {y} {z}\n" for x, y, z in STRAND_A + STRAND_B)
    return "# test\no hair\n" + vs + body


@pytest.mark.parametrize("body", [
    "l 1 2 3\nl 4 5 6 7\n",                       # one record per strand
    "l 1 2\nl 2 3\nl 4 5\nl 5 6\nl 6 7\n",        # chained one segment at a time
    "l 4 5\nl 1 2\nl 6 7\nl 2 3\nl 5 6\n",        # chained, out of order: strand order = first record
    "l -7 -6 -5\nl -4/1 -3/2 -2/3 -1/4\n",        # relative indices, v/vt pairs
    "l 1 2 \\\n 3\ng strands\nl 4 5 5 6\\\n 7\n",  # line continuations, a repeated index collapsed
])
def test_obj_polylines(tmp_path, body):
    path = tmp_path / "g.obj"
    path.write_text(obj_text(body))
    groom = read_obj(path, scale=0.01)
    expected = [STRAND_B, STRAND_A] if body.startswith("l 4 5") else [STRAND_A, STRAND_B]
    assert_same(Groom.from_strands(np.array(s) * 0.01 for s in expected), groom, rtol=1e-15)


def test_obj_relative_indices_interleaved(tmp_path):
    path = tmp_path / "g.obj"
    path.write_text("v 0 0 0\nv 0 1 0\nl -2 -1\nv 1 0 0 1.0\nv 1 1 0 0.5 0.5 0.5\nl -2 -1\n")
    groom = read_obj(path)
    assert groom.n_strands == 2
    np.testing.assert_array_equal(groom.strand(1), [[1, 0, 0], [1, 1, 0]])


def test_obj_vertices_only_with_strand_length(tmp_path):
    strands = [random_groom(3, 1, max_vertices=2).points + [i, 0, 0] for i in range(4)]
    path = tmp_path / "v.obj"
    path.write_text("".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in np.concatenate(strands).tolist()))
    groom = read_obj(path, strand_length=2)
    assert_same(Groom.from_strands(strands), groom, rtol=1e-15)
    # l records win over strand_length
    path.write_text(path.read_text() + "l 1 2 3 4\nl 5 6 7 8\n")
    assert read_obj(path, strand_length=2).n_strands == 2


def test_obj_writer_format(tmp_path):
    groom = Groom.from_strands([STRAND_A, STRAND_B])
    path = save_groom(groom, tmp_path / "g.obj", units="cm")
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#")
    assert lines[1] == "v 0 0 0" and lines[3] == "v 0 -200 50"
    assert lines[-2:] == ["l 1 2 3", "l 4 5 6 7"]


# ---------------------------------------------------------------------------- .hair variants
def hair_bytes(counts, points, flags=0b11, default_segments=0, extra=b""):
    info = b"hand made".ljust(88, b"\0")
    header = b"HAIR" + struct.pack("<IIII", len(counts), len(points), flags, default_segments)
    header += struct.pack("<ff3f", 0.5, 0.0, 1.0, 1.0, 1.0) + info
    segments = np.asarray(counts, dtype="<u2") - 1 if flags & 1 else np.zeros(0, "<u2")
    return header + segments.tobytes() + np.asarray(points, dtype="<f4").tobytes() + extra


def test_hair_header_layout(tmp_path):
    groom = random_groom(1, 3)
    path = save_groom(groom, tmp_path / "g.hair")
    data = path.read_bytes()
    assert data[:4] == b"HAIR"
    n_hairs, n_points, flags = struct.unpack_from("<III", data, 4)
    assert (n_hairs, n_points, flags) == (3, groom.n_points, 0b11)
    assert len(data) == 128 + 2 * 3 + 12 * groom.n_points


def test_hair_default_segments_and_optional_arrays(tmp_path):
    pts = np.arange(36, dtype=float).reshape(12, 3) ** 1.5
    path = tmp_path / "d.hair"
    path.write_bytes(hair_bytes([4, 4, 4], pts, flags=0b10, default_segments=3))  # no segments array
    groom = read_hair(path)
    np.testing.assert_array_equal(groom.counts, [4, 4, 4])
    np.testing.assert_allclose(groom.points, pts.astype(np.float32))
    assert groom.metadata["info"] == "hand made"
    # thickness, transparency and colour arrays follow the points and are skipped
    per_point = np.ones(12 * 5, dtype="<f4").tobytes()
    path.write_bytes(hair_bytes([5, 7], pts, flags=0b11111, extra=per_point))
    np.testing.assert_array_equal(read_hair(path).counts, [5, 7])


# ---------------------------------------------------------------------------- dispatcher and options
def test_dispatch_options(tmp_path):
    groom = random_groom(2, 4)
    path = save_groom(groom, tmp_path / "G.DATA")  # extensions are case-insensitive
    z_up = load_groom(path, units=0.5, up="z")
    assert z_up.up == "z"
    np.testing.assert_allclose(z_up.points, 0.5 * groom.points, atol=1e-6)
    assert load_groom(path, up="-x").up == "-x"  # any signed axis
    with pytest.raises(GroomError, match="up axis"):
        load_groom(path, up="w")
    with pytest.raises(GroomError, match="unknown units"):
        load_groom(path, units="furlong")
    with pytest.raises(GroomError, match="positive"):
        load_groom(path, units=-1)


def test_unknown_formats(tmp_path):
    (tmp_path / "g.fbx").write_text("")  # (.abc is read, with alembic3d: tests/test_alembic.py)
    with pytest.raises(GroomError, match=r"unknown groom format '\.fbx'.*\.obj"):
        load_groom(tmp_path / "g.fbx")
    with pytest.raises(GroomError, match="cannot write '.ply'"):
        save_groom(random_groom(0, 1), tmp_path / "g.ply")


def test_one_format_table(capsys):
    """io/formats.py is the one table of suffixes: dispatch's maps, the result exporters, the writers'
    own suffix checks and `groom invert --help` (every readable suffix) agree with it."""
    from groomtool.cli.export_cmd import FORMATS as CLI_FORMATS
    from groomtool.cli.main import build_parser
    from groomtool.io import READERS, WRITERS, export, formats

    assert sorted(READERS) == sorted(s for f in formats.FORMATS if f.reads for s in f.suffixes)
    assert sorted(WRITERS) == sorted(s for f in formats.FORMATS if f.writes for s in f.suffixes)
    exported = {f.name: f.suffixes for f in formats.FORMATS if f.exports}
    assert exported == export.SUFFIXES and tuple(exported) == CLI_FORMATS
    every = [suffix for f in formats.FORMATS for suffix in f.suffixes]
    assert len(set(every)) == len(every) and all(suffix == suffix.lower() and suffix[0] == "." for suffix in every)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["invert", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())  # argparse wraps the lines
    assert all(suffix in help_text for suffix in READERS)


def test_usd_without_usd_core(tmp_path, monkeypatch):
    import groomtool.io

    monkeypatch.delattr(groomtool.io, "usd", raising=False)
    monkeypatch.setitem(sys.modules, "groomtool.io.usd", None)  # as if pxr (usd-core) were missing
    (tmp_path / "g.usdc").write_bytes(b"PXR-USDC")
    with pytest.raises(GroomError, match="g.usdc: USD support needs usd-core"):
        load_groom(tmp_path / "g.usdc")


def test_data_reads_10k_strands_fast(tmp_path):
    rng = np.random.default_rng(0)
    counts = rng.integers(2, 200, 10_000)
    steps = rng.uniform(1e-3, 2e-3, (counts.sum(), 3))
    groom = Groom(np.cumsum(steps, axis=0), np.concatenate([[0], np.cumsum(counts)]))
    path = save_groom(groom, tmp_path / "big.data")
    cpu_seconds = []
    for _ in range(2):  # CPU time, best of two: the machine may be shared
        start = time.process_time()
        back = load_groom(path)
        cpu_seconds.append(time.process_time() - start)
    assert back.n_strands == 10_000 and back.n_points == groom.n_points
    assert min(cpu_seconds) < 0.5, f"reading 10k strands took {min(cpu_seconds):.2f} s"


# ---------------------------------------------------------------------------- heads
@pytest.mark.parametrize("suffix", ["obj", "ply", "stl"])
def test_load_head(tmp_path, suffix):
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    path = tmp_path / f"head.{suffix}"
    mesh.export(path)
    head = load_head(path, units="cm")
    assert isinstance(head, trimesh.Trimesh) and len(head.faces) == len(mesh.faces)
    np.testing.assert_allclose(head.bounds, mesh.bounds * 0.01, atol=1e-6)


def test_load_head_errors(tmp_path):
    with pytest.raises(GroomError, match="no such file"):
        load_head(tmp_path / "missing.obj")
    (tmp_path / "empty.obj").write_text("")
    with pytest.raises(GroomError, match="empty.obj: no triangles"):
        load_head(tmp_path / "empty.obj")
    save_groom(random_groom(0, 3), tmp_path / "lines.obj")
    with pytest.raises(GroomError, match="lines.obj: no triangles"):
        load_head(tmp_path / "lines.obj")
    (tmp_path / "junk.xyz").write_text("junk junk\n")
    with pytest.raises(GroomError, match="junk.xyz"):
        load_head(tmp_path / "junk.xyz")


# ---------------------------------------------------------------------------- atomic writes
def test_atomic_write_kinds(tmp_path):
    target = tmp_path / "out.txt"
    atomic_write(target, b"bytes")
    assert target.read_bytes() == b"bytes"
    atomic_write(target, "text \u00e9")
    assert target.read_text(encoding="utf-8") == "text \u00e9"
    seen = []
    atomic_write(target, lambda tmp: (seen.append(tmp), tmp.write_text("by writer")))
    assert target.read_text() == "by writer"
    assert seen[0].parent == tmp_path and seen[0].suffix == ".txt" and not seen[0].exists()
    with atomic_open(target, "w") as f:
        f.write("opened")
    assert target.read_text() == "opened"
    assert os.listdir(tmp_path) == ["out.txt"]


def test_atomic_failure_keeps_old_file(tmp_path):
    target = tmp_path / "out.obj"
    target.write_text("old content\n")
    os.chmod(target, 0o640)
    with pytest.raises(RuntimeError, match="midway"):
        with atomic_open(target, "w") as f:
            f.write("half of the new")
            f.flush()
            raise RuntimeError("midway")
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_text("partial")
            raise KeyboardInterrupt
    assert target.read_text() == "old content\n"
    assert os.listdir(tmp_path) == ["out.obj"]
    atomic_write(target, b"new")
    assert target.stat().st_mode & 0o777 == 0o640  # permissions of the replaced file are kept


def test_writer_failing_midway_keeps_old_groom(tmp_path, monkeypatch):
    path = save_groom(random_groom(0, 3), tmp_path / "g.obj")
    old = path.read_bytes()

    import contextlib

    import groomtool.io.obj as obj_module

    real_atomic_open = obj_module.atomic_open

    @contextlib.contextmanager
    def disk_full_after_first_write(target, *args, **kwargs):
        with real_atomic_open(target, *args, **kwargs) as f:
            class FailingFile:
                writes = 0

                def write(self, text):
                    f.write(text)  # the header reaches the temporary file, then the disk is full
                    self.writes += 1
                    if self.writes == 2:
                        raise OSError("disk full")

            yield FailingFile()

    monkeypatch.setattr(obj_module, "atomic_open", disk_full_after_first_write)
    with pytest.raises(OSError, match="disk full"):
        save_groom(random_groom(1, 5), path)
    assert path.read_bytes() == old
    assert os.listdir(tmp_path) == ["g.obj"]


def test_atomic_open_rejects_read_modes(tmp_path):
    with pytest.raises(ValueError, match="mode"):
        with atomic_open(tmp_path / "x", "r"):
            pass
    assert os.listdir(tmp_path) == []
