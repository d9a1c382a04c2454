"""io.peek.peek_counts: strand and vertex counts from a groom file's header, read-only, never raising."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from groomtool.examples import example_groom
from groomtool.io import save_groom
from groomtool.io.peek import peek_counts


@pytest.fixture(scope="module")
def groom():
    g, _ = example_groom(n_strands=7, seed=3)
    return g


@pytest.mark.parametrize("suffix", [".data", ".hair", ".obj"])
def test_counts_of_the_writers_files(groom, tmp_path, suffix):
    path = tmp_path / f"g{suffix}"
    save_groom(groom, path)
    assert peek_counts(path) == (groom.n_strands, groom.n_points)


def test_ply_header_and_bare_obj_vertices(tmp_path):
    ply = tmp_path / "g.ply"
    ply.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 12\nproperty float x\nend_header\n"
                    + np.zeros(12, "<f4").tobytes())
    assert peek_counts(ply) == (None, 12)
    bare = tmp_path / "bare.obj"
    bare.write_text("# points only\nv 0 0 0\nv 0 1 0\n  v 0 2 0\nvn 0 0 1\nvt 0 0\n")
    assert peek_counts(bare) == (None, 3)  # strands: split by strand_length when read


def test_what_it_cannot_size_is_none(tmp_path):
    assert peek_counts(tmp_path / "missing.data") is None
    (tmp_path / "short.data").write_bytes(b"\x01\x00")
    assert peek_counts(tmp_path / "short.data") is None
    (tmp_path / "odd.data").write_bytes(struct.pack("<ii", 1, 2) + b"\x00" * 5)  # not 12 bytes per vertex
    assert peek_counts(tmp_path / "odd.data") is None
    (tmp_path / "neg.data").write_bytes(struct.pack("<i", -3))
    assert peek_counts(tmp_path / "neg.data") is None
    (tmp_path / "x.hair").write_bytes(b"NOPE" + b"\x00" * 124)
    assert peek_counts(tmp_path / "x.hair") is None
    (tmp_path / "x.usd").write_text("#usda 1.0\n")
    assert peek_counts(tmp_path / "x.usd") is None  # not peeked into
    (tmp_path / "x.ply").write_text("not a ply\n")
    assert peek_counts(tmp_path / "x.ply") is None


def test_data_counts_come_from_the_header_and_the_size_only(tmp_path):
    """A .data file of 3 strands of 4, 2 and 5 vertices: 3 strands, 11 vertices (no strand is read)."""
    words = [struct.pack("<i", 3)]
    for n in (4, 2, 5):
        words.append(struct.pack("<i", n) + np.ones(3 * n, "<f4").tobytes())
    (tmp_path / "g.data").write_bytes(b"".join(words))
    assert peek_counts(tmp_path / "g.data") == (3, 11)
