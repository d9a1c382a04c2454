"""The real data in ../shared/data (skipped when absent): counts, units, the one broken strand."""

import numpy as np
import pytest

from groomtool import GroomError
from groomtool.io import load_groom, load_head, save_groom

CSTRANDS = "usc/cstrands/cstrands{:05d}.data"


@pytest.mark.parametrize("number", [1, 2, 3, 100, 343])
def test_usc_cstrands(shared_data, number):
    groom = load_groom(shared_data / CSTRANDS.format(number))
    assert groom.n_strands == 5 and groom.counts.tolist() == [100] * 5
    assert "repairs" not in groom.metadata
    assert np.all((groom.lengths() > 0.01) & (groom.lengths() < 1.0))  # metres
    roots = groom.points[groom.offsets[:-1]]
    assert np.all((roots[:, 1] > 1.55) & (roots[:, 1] < 1.9))  # on the head (y from 1.55 to 1.89)
    assert np.all(groom.points[:, 1] > 0.9)


def test_usc_all_styles_only_00356_needs_repair(shared_data):
    """All 343 styles load; only cstrands00356 strand 1 collapses into one point after vertex 10
    (89 segments of zero length or a float32 ULP).  No strand has fewer than 2 vertices."""
    repaired = {}
    files = sorted((shared_data / "usc" / "cstrands").glob("*.data"))
    assert len(files) == 343
    for path in files:
        groom = load_groom(path, repair=True)
        assert groom.n_strands == 5
        if "repairs" in groom.metadata:
            repaired[path.name] = (groom.metadata["repairs"], groom.counts.tolist())
    assert repaired == {
        "cstrands00356.data": (
            {"dropped_points": 89, "deduplicated_strands": [1], "dropped_strands": []},
            [100, 11, 100, 100, 100],
        )
    }
    with pytest.raises(GroomError, match=r"cstrands00356.data: strand 1, vertex 11 repeats vertex 10"):
        load_groom(shared_data / CSTRANDS.format(356))


def test_harolongo_in_centimetres(shared_data):
    groom = load_groom(shared_data / "digital-salon" / "harolongo.data", units="cm")
    assert groom.n_strands == 7905 and set(groom.counts.tolist()) == {21}
    lengths = groom.lengths()
    assert abs(np.median(lengths) - 0.235) < 0.002
    assert 0.22 < lengths.min() and lengths.max() < 0.25
    assert "repairs" not in groom.metadata


@pytest.mark.parametrize("suffix", [".data", ".hair"])
def test_real_data_round_trips_exactly(shared_data, tmp_path, suffix):
    """float32 formats: writing what was read gives the same float32 numbers back."""
    groom = load_groom(shared_data / "digital-salon" / "harolongo.data", units="cm")
    back = load_groom(save_groom(groom, tmp_path / f"h{suffix}", units="cm"), units="cm")
    np.testing.assert_array_equal(back.offsets, groom.offsets)
    np.testing.assert_array_equal(back.points, groom.points)


def test_usc_head_and_roots(shared_data):
    head = load_head(shared_data / "usc" / "head_model.obj")
    assert len(head.faces) == 13832
    assert abs(head.bounds[0, 1] - 1.55) < 0.01 and abs(head.bounds[1, 1] - 1.89) < 0.01
    roots = load_groom(shared_data / "usc" / "roots10k.obj", strand_length=2)  # bare v records
    assert roots.n_points == 10_000
