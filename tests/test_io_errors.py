"""Bad input: every problem is a GroomError naming the file, the strand (or line) and what is wrong."""

import re
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groomtool import Groom, GroomError
from groomtool.io import load_groom, read_data, read_hair, read_obj, read_ply, save_groom, validate


def data_bytes(strands) -> bytes:
    """USC .data bytes for a list of (n, 3) arrays, written by hand (not by our writer)."""
    out = struct.pack("<i", len(strands))
    for s in strands:
        s = np.asarray(s, dtype="<f4").reshape(-1, 3)
        out += struct.pack("<i", len(s)) + s.tobytes()
    return out


def walk(n: int, start=(0.0, 0.0, 0.0), step=0.01) -> np.ndarray:
    return np.asarray(start) + np.outer(np.arange(n), [0.3, -1.0, 0.2]) * step


STRANDS = [walk(4), walk(6, (1, 0, 0)), walk(5, (2, 0, 0))]


def write(tmp_path, name, content) -> str:
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    return str(path)


# ---------------------------------------------------------------------------- truncation
@settings(max_examples=60, deadline=None)
@given(cut_fraction=st.floats(0.0, 1.0, exclude_max=True), suffix=st.sampled_from([".data", ".hair"]),
       seed=st.integers(0, 1000))
def test_truncated_files(tmp_path_factory, cut_fraction, suffix, seed):
    rng = np.random.default_rng(seed)
    groom = Groom.from_strands([walk(int(rng.integers(2, 9)), rng.uniform(-1, 1, 3)) for _ in range(5)])
    path = tmp_path_factory.mktemp("cut") / f"g{suffix}"
    save_groom(groom, path)
    data = path.read_bytes()
    cut = int(cut_fraction * len(data))
    path.write_bytes(data[:cut])
    with pytest.raises(GroomError) as err:
        load_groom(path)
    message = str(err.value)
    assert str(path) in message
    header = 4 if suffix == ".data" else 128
    if cut >= header:
        assert re.search(r"strand \d+", message), message


def test_data_truncation_message(tmp_path):
    data = data_bytes(STRANDS)
    cut = len(data) - 12 * 3 - 2  # inside strand 2 (5 vertices): 1 whole vertex left plus 10 bytes
    path = write(tmp_path, "cut.data", data[:cut])
    with pytest.raises(GroomError, match=re.escape(f"{path}: strand 2 declares 5 vertices but the file ends after 1")):
        read_data(path)
    path = write(tmp_path, "header.data", data[: 4 + 4 + 48 + 2])  # inside strand 1's vertex count
    with pytest.raises(GroomError, match=r"strand 1: the file ends .* before its vertex count"):
        read_data(path)
    with pytest.raises(GroomError, match="too short for the 4-byte strand count"):
        read_data(write(tmp_path, "tiny.data", b"\x01\x00"))


def test_data_trailing_bytes_and_bad_counts(tmp_path):
    path = write(tmp_path, "t.data", data_bytes(STRANDS) + b"\0" * 7)
    with pytest.raises(GroomError, match=re.escape(f"{path}: 7 trailing bytes after the last strand (strand 2")):
        read_data(path)
    with pytest.raises(GroomError, match="negative strand count"):
        read_data(write(tmp_path, "n.data", struct.pack("<i", -3)))
    bad = bytearray(data_bytes(STRANDS))
    bad[4:8] = struct.pack("<i", -1)
    with pytest.raises(GroomError, match="strand 0 declares a negative vertex count"):
        read_data(write(tmp_path, "v.data", bytes(bad)))


def test_hair_structure_errors(tmp_path):
    groom = Groom.from_strands(STRANDS)
    good = save_groom(groom, tmp_path / "g.hair").read_bytes()
    with pytest.raises(GroomError, match="shorter than the 128-byte .hair header"):
        read_hair(write(tmp_path, "short.hair", good[:100]))
    with pytest.raises(GroomError, match="not a .hair file"):
        read_hair(write(tmp_path, "sig.hair", b"HAIX" + good[4:]))
    with pytest.raises(GroomError, match="no points array"):
        read_hair(write(tmp_path, "flags.hair", good[:12] + struct.pack("<I", 1) + good[16:]))
    with pytest.raises(GroomError, match="declares 14 points but .* add up to 15"):
        read_hair(write(tmp_path, "count.hair", good[:8] + struct.pack("<I", 14) + good[12:]))
    with pytest.raises(GroomError, match="3 trailing bytes"):
        read_hair(write(tmp_path, "trail.hair", good + b"abc"))
    path = write(tmp_path, "cut.hair", good[: 128 + 6 + 12 * 7 + 5])
    message = f"{path}: the file ends inside the points array: strand 1 has 3 of its 6"
    with pytest.raises(GroomError, match=re.escape(message)):
        read_hair(path)
    with pytest.raises(GroomError, match=r"segments array: strand 1 has no segment count"):
        read_hair(write(tmp_path, "seg.hair", good[:130]))


# ---------------------------------------------------------------------------- content problems
def test_nan_names_file_strand_vertex(tmp_path):
    strands = [s.copy() for s in STRANDS]
    strands[1][3, 2] = np.nan
    strands[2][0, 0] = np.inf
    path = write(tmp_path, "nan.data", data_bytes(strands))
    for repair in (False, True):  # never repairable
        with pytest.raises(GroomError, match=re.escape(f"{path}: strand 1, vertex 3 has a non-finite")) as err:
            read_data(path, repair=repair)
        assert "2 such vertices in 2 strands" in str(err.value)
    obj = write(tmp_path, "nan.obj", "v 0 0 0\nv nan 1 0\nl 1 2\n")
    with pytest.raises(GroomError, match="nan.obj: strand 0, vertex 1 has a non-finite"):
        read_obj(obj)


@pytest.mark.parametrize("short", [0, 1])
def test_short_strand(tmp_path, short):
    strands = [STRANDS[0], walk(short, (5, 5, 5)), STRANDS[1]]
    path = write(tmp_path, "short.data", data_bytes(strands))
    with pytest.raises(GroomError, match=re.escape(f"{path}: strand 1 has {short} vert")):
        read_data(path)
    groom = read_data(path, repair=True)
    assert groom.n_strands == 2
    np.testing.assert_allclose(groom.strand(1), STRANDS[1].astype(np.float32))
    assert groom.metadata["repairs"] == {"dropped_points": 0, "deduplicated_strands": [], "dropped_strands": [1]}


def test_duplicate_points(tmp_path):
    strands = [s.copy() for s in STRANDS]
    strands[1] = np.insert(strands[1], [2, 2, 4], strands[1][[1, 1, 3]], axis=0)  # vertex 1 x3, vertex 3 x2
    strands[2][1] = strands[2][0] + 1e-12  # within 1e-9 of the strand's size
    path = write(tmp_path, "dup.data", data_bytes(strands))
    message = re.escape(f"{path}: strand 1, vertex 2 repeats vertex 1") + r".*4 repeated points in 2 strands"
    with pytest.raises(GroomError, match=message):
        read_data(path)
    groom = read_data(path, repair=True)
    np.testing.assert_array_equal(groom.counts, [4, 6, 4])
    np.testing.assert_allclose(groom.strand(1), STRANDS[1].astype(np.float32))
    assert groom.metadata["repairs"] == {"dropped_points": 4, "deduplicated_strands": [1, 2], "dropped_strands": []}


def test_float32_noise_counts_as_repeated(tmp_path):
    """A strand that collapses to a point with float32 jitter (as in USC cstrands00356)."""
    base = np.float32(1.7)
    jitter = np.array([base, np.nextafter(base, np.float32(2)), base, np.nextafter(base, np.float32(0))])
    strand = np.concatenate([walk(5, (0, 1.6, 0)), np.stack([np.zeros(4), jitter, np.zeros(4)], axis=1)])
    strand[5:, 0] = strand[4, 0]
    strand[5:, 2] = strand[4, 2]
    strand[4, 1] = base  # the walk ends where the jitter starts
    path = write(tmp_path, "jitter.data", data_bytes([STRANDS[0], strand]))
    with pytest.raises(GroomError, match="strand 1, vertex 5 repeats vertex 4"):
        read_data(path)
    groom = read_data(path, repair=True)
    assert groom.counts.tolist() == [4, 5]
    assert groom.metadata["repairs"]["dropped_points"] == 4


def test_repair_drops_strands_that_collapse(tmp_path):
    collapsed = np.repeat([[3.0, 3.0, 3.0]], 4, axis=0)
    path = write(tmp_path, "c.data", data_bytes([STRANDS[0], collapsed]))
    groom = read_data(path, repair=True)
    assert groom.n_strands == 1
    assert groom.metadata["repairs"] == {"dropped_points": 3, "deduplicated_strands": [1], "dropped_strands": [1]}
    with pytest.raises(GroomError, match="nothing left after repair"):
        read_data(write(tmp_path, "all.data", data_bytes([collapsed])), repair=True)


def test_validate_direct():
    with pytest.raises(GroomError, match="<memory>: contains no strands"):
        validate(Groom.from_strands([]))
    groom = Groom.from_strands(STRANDS)
    assert validate(groom) is groom and validate(groom, repair=True) is groom
    # a creeping cluster: each step within tolerance of the previous point
    end = walk(3)[-1]
    creep = np.concatenate([walk(3), end + np.outer(np.arange(1, 6), [1e-13, 0, 0]), [end + [0.0, -0.1, 0]]])
    repaired = validate(Groom.from_strands([creep]), repair=True)
    assert repaired.counts.tolist() == [4]
    assert np.all(repaired.segment_lengths() > 1e-3)


# ---------------------------------------------------------------------------- OBJ and PLY structure
@pytest.mark.parametrize("body, message", [
    ("l 1 0\n", r"line 4: vertex index 0"),
    ("l 1 9\n", r"line 4: vertex index 9 but the file has 3 vertices"),
    ("l -4 -1\n", r"line 4: relative index -4 points before the first vertex"),
    ("l 1 x\n", r"line 4: bad vertex index 'x'"),
    ("l 2\n", r"line 4: an l record needs at least 2 distinct vertices"),
    ("l 1 2\nl 1 3\n", r"line 5: vertex 1 continues in two directions"),
    ("l 1 3\nl 2 3\n", r"line 5: vertex 3 is reached from two vertices"),
    ("l 1 2 3\nl 3 1\n", r"line [45]: segments form a closed loop through vertex [13]"),
    ("", r"has 3 vertices but no l polylines: pass strand_length"),
    ("f 1 2 3\n", r"has 1 faces but no l polylines: a mesh"),
])
def test_obj_structure_errors(tmp_path, body, message):
    path = write(tmp_path, "bad.obj", "v 0 0 0\nv 0 1 0\nv 0 2 1\n" + body)
    with pytest.raises(GroomError, match=re.escape(path) + ": " + message):
        read_obj(path)


def test_obj_bad_numbers_and_lengths(tmp_path):
    path = write(tmp_path, "num.obj", "v 0 0 0\nv 0 1 zero\nl 1 2\n")
    with pytest.raises(GroomError, match="num.obj: line 2: a v record needs 3 numbers"):
        read_obj(path)
    path = write(tmp_path, "few.obj", "v 0 0 0\nv 0 1\nl 1 2\n")
    with pytest.raises(GroomError, match="few.obj: line 2"):
        read_obj(path)
    path = write(tmp_path, "v.obj", "".join(f"v {i} 0 0\n" for i in range(7)))
    message = f"{path}: 7 vertices is not a whole number of strands of strand_length=3"
    with pytest.raises(GroomError, match=re.escape(message)):
        read_obj(path, strand_length=3)
    with pytest.raises(GroomError, match="no vertices"):
        read_obj(write(tmp_path, "empty.obj", "# nothing\n"))


def test_ply_errors(tmp_path):
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n" \
             "property float z\nelement edge 2\nproperty int vertex1\nproperty int vertex2\nend_header\n"
    body = np.arange(9, dtype="<f4").tobytes() + np.array([0, 1, 1, 5], dtype="<i4").tobytes()
    with pytest.raises(GroomError, match="e.ply: edge 1 joins vertices 1 and 5 but there are 3 vertices"):
        read_ply(write(tmp_path, "e.ply", header.encode() + body))
    with pytest.raises(GroomError, match="cut.ply: the file ends inside element 'edge' after 1 of 2"):
        read_ply(write(tmp_path, "cut.ply", header.encode() + body[:-5]))
    with pytest.raises(GroomError, match="not a PLY file"):
        read_ply(write(tmp_path, "x.ply", b"solid stl\n"))
    with pytest.raises(GroomError, match="unknown PLY type 'quad'"):
        read_ply(write(tmp_path, "t.ply", header.replace("float z", "quad z")))
    ascii_header = header.replace("binary_little_endian", "ascii")
    with pytest.raises(GroomError, match="a.ply: the file ends inside element 'edge'"):
        read_ply(write(tmp_path, "a.ply", ascii_header + "0 0 0\n0 1 0\n0 2 0\n0 1\n"))
    no_edges = ascii_header.replace("element edge 2", "element edge 0")
    with pytest.raises(GroomError, match="no edges: pass strand_length"):
        read_ply(write(tmp_path, "n.ply", no_edges + "0 0 0\n0 1 0\n0 2 0\n"))
    assert read_ply(tmp_path / "n.ply", strand_length=3).n_strands == 1


# ---------------------------------------------------------------------------- missing files
@pytest.mark.parametrize("reader", [read_obj, read_data, read_hair, read_ply, load_groom])
def test_missing_file(tmp_path, reader):
    path = tmp_path / "nowhere.obj"
    with pytest.raises(GroomError, match=re.escape(f"{path}: no such file")):
        reader(path)


def test_directory_is_not_a_groom(tmp_path):
    (tmp_path / "d.obj").mkdir()
    with pytest.raises(GroomError, match="not a regular file"):
        load_groom(tmp_path / "d.obj")


# ---------------------------------------------------------------------------- head meshes
def _mesh_file(tmp_path, name, vertices, faces) -> str:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, dtype=float).tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces).tolist()]
    return write(tmp_path, name, "\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def sphere():
    import trimesh

    return trimesh.creation.icosphere(3, radius=0.1)


def test_head_with_half_the_faces_reversed_is_repaired(tmp_path, sphere):
    from groomtool.contact.head import root_gaps
    from groomtool.io import load_head
    from groomtool.io.head_validation import HeadWarning

    faces = sphere.faces.copy()
    faces[::2] = faces[::2, ::-1]
    path = _mesh_file(tmp_path, "flipped.obj", sphere.vertices, faces)
    with pytest.warns(HeadWarning, match=r"flipped.obj: 640 of 1280 faces .* reversed"):
        head = load_head(path)
    assert head.is_winding_consistent
    # signed distances as with the intact mesh: points outside positive, inside negative
    pts = np.array([[0, 0.12, 0], [0, 0.09, 0], [0.105, 0, 0], [0, 0, -0.095]])
    good = load_head(_mesh_file(tmp_path, "good.obj", sphere.vertices, sphere.faces))
    assert np.allclose(root_gaps(pts, head), root_gaps(pts, good), atol=1e-12)
    assert np.all(np.sign(root_gaps(pts, head)) == [1, -1, 1, -1])


def test_head_with_a_nan_vertex_is_an_error(tmp_path, sphere):
    from groomtool.io import load_head

    v = sphere.vertices.copy()
    v[7] = [np.nan, 0, 0]
    path = _mesh_file(tmp_path, "nan.obj", v, sphere.faces)
    with pytest.raises(GroomError, match=r"nan.obj: vertex 7 has a non-finite coordinate"):
        load_head(path)


def test_head_of_degenerate_faces_is_an_error(tmp_path):
    from groomtool.io import load_head

    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], dtype=float)  # all on a line
    path = _mesh_file(tmp_path, "flat.obj", v, [[0, 1, 2], [1, 2, 3]])
    with pytest.raises(GroomError, match=r"flat.obj: all 2 faces are degenerate"):
        load_head(path)


def test_head_with_absurd_coordinates_is_an_error(tmp_path, sphere):
    from groomtool.io import load_head

    path = _mesh_file(tmp_path, "huge.obj", sphere.vertices * 1e30, sphere.faces)
    with pytest.raises(GroomError, match=r"huge.obj: a coordinate is .* not a head in metres"):
        load_head(path)


def _groom_on(sphere_radius, n=20, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 1] = np.abs(d[:, 1])
    d /= np.linalg.norm(d, axis=1)[:, None]
    strands = [r * sphere_radius + np.outer(np.linspace(0, 0.1, 6), r + [0, -0.5, 0]) for r in d]
    return Groom.from_strands(strands)


def test_head_far_too_large_for_the_groom_is_an_error(sphere):
    from groomtool.io.head_validation import check_head_fits_groom

    groom = _groom_on(0.1)
    check_head_fits_groom(sphere, groom)  # fits: no error
    big = sphere.copy()
    big.apply_scale(100.0)
    with pytest.raises(GroomError, match=r"different units"):
        check_head_fits_groom(big, groom)


def test_roots_far_from_or_inside_the_head_warn(sphere):
    import warnings

    from groomtool.io.head_validation import HeadWarning, check_head_fits_groom

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_head_fits_groom(sphere, _groom_on(0.1))  # roots on the surface: silent
    with pytest.warns(HeadWarning, match=r"outside the head"):
        check_head_fits_groom(sphere, Groom(_groom_on(0.1).points + [0.3, 0, 0], _groom_on(0.1).offsets))
    with pytest.warns(HeadWarning, match=r"inside the head"):
        check_head_fits_groom(sphere, _groom_on(0.05))


# ---------------------------------------------------------------------------- work bounded by the file size
def test_ply_huge_counts_fail_fast(tmp_path):
    head = "ply\nformat {fmt} 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n" \
           "element face {n}\nproperty list uchar int vertex_indices\nend_header\n"
    for fmt, body in (("binary_little_endian", np.zeros(6, "<f4").tobytes() + b"\x00" * 40),
                      ("ascii", b"0 0 0\n1 1 1\n" + b"0\n" * 20)):
        path = write(tmp_path, "huge.ply", head.format(fmt=fmt, n=2**31 - 1).encode() + body)
        with pytest.raises(GroomError, match=r"huge.ply: element 'face' declares 2147483647 records"):
            read_ply(path)
    with pytest.raises(GroomError, match=r"header line 7: element 'face' has a negative count -1"):
        read_ply(write(tmp_path, "neg.ply", head.format(fmt="ascii", n=-1).encode() + b"0 0 0\n1 1 1\n"))
    dup = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float x\nproperty float z\nend_header\n"
    with pytest.raises(GroomError, match=r"header line 5: property 'x' of element 'vertex' declared twice"):
        read_ply(write(tmp_path, "dup.ply", dup + "0 0 0\n1 1 1\n"))


def test_hair_header_asking_for_gigabytes_fails_fast(tmp_path):
    """No segments array: the hair count alone would allocate 8 bytes per hair."""
    header = struct.pack("<4sIIIIff3f88s", b"HAIR", 2**31, 2**32 - 1, 2, 2, 1.0, 0.0, 1.0, 1.0, 1.0, b"")
    path = write(tmp_path, "big.hair", header + np.zeros(36, "<f4").tobytes())
    with pytest.raises(GroomError, match=r"big.hair: the header declares 2147483648 hairs but the 144 bytes"):
        read_hair(path)


def test_data_strand_count_beyond_the_file_fails_fast(tmp_path):
    path = write(tmp_path, "big.data", struct.pack("<i", 2**31 - 1) + struct.pack("<i", 2) + np.zeros(6, "<f4").tobytes())
    with pytest.raises(GroomError, match=r"big.data: 2147483647 strands declared but the file \(32 bytes\)"):
        read_data(path)


def test_obj_v_records_of_different_widths(tmp_path):
    # 4 numbers (x y z w) then 2: the 2 is an error, not a shift of every later coordinate
    text = "v 0 0 0 1\nv 1 1\nv 2 2 2\nv 3 3 3\nl 1 2 3 4\n"
    with pytest.raises(GroomError, match=r"w.obj: line 2: a v record needs 3 numbers, got 'v 1 1'"):
        read_obj(write(tmp_path, "w.obj", text))
    # 4 and 6 numbers (w, colours) are read as x y z
    g = read_obj(write(tmp_path, "c.obj", "v 0 0 0 1\nv 0.1 0 0 0.5 0.5 0.5\nv 0.2 0.1 0\nl 1 2 3\n"))
    assert np.allclose(g.points, [[0, 0, 0], [0.1, 0, 0], [0.2, 0.1, 0]])


def test_absurd_coordinates_are_an_error(tmp_path):
    groom = Groom.from_strands([s * 1e30 for s in STRANDS])
    with pytest.raises(GroomError, match=r"strand 0, vertex 1 lies 1e\+28 m from the origin .*wrong --units"):
        validate(groom)
    path = tmp_path / "far.data"
    path.write_bytes(data_bytes([s * 1e30 for s in STRANDS]))
    with pytest.raises(GroomError, match="far.data: strand 0"):
        load_groom(path)
