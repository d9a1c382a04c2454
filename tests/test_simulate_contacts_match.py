"""match_contacts (simulate_contacts) against a brute-force reference: for every new contact the old contact with the
same strands and the smallest |ds_a| + |ds_b| within the tolerance, the first (lowest index) of equal ones, else -1."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from groomtool.simulate_contacts import match_contacts


class _C:
    def __init__(self, a, b, sa, sb):
        self.strand_a, self.strand_b = np.asarray(a, np.int64), np.asarray(b, np.int64)
        self.s_a, self.s_b = np.asarray(sa, float), np.asarray(sb, float)


def _brute(old, new, tol):
    out = np.full(len(new.strand_a), -1)
    sb_old, sb_new = np.nan_to_num(old.s_b), np.nan_to_num(new.s_b)
    for i in range(len(new.strand_a)):
        best = np.inf
        for j in range(len(old.strand_a)):
            if old.strand_a[j] != new.strand_a[i] or old.strand_b[j] != new.strand_b[i]:
                continue
            d = abs(new.s_a[i] - old.s_a[j]) + abs(sb_new[i] - sb_old[j])
            if d <= tol and d < best:
                best, out[i] = d, j
    return out


def _contacts(draw, m):
    a = draw(st.lists(st.integers(0, 3), min_size=m, max_size=m))
    b = draw(st.lists(st.integers(-1, 3), min_size=m, max_size=m))
    # arc lengths on a coarse grid: ties and exact tolerance hits happen
    sa = [0.01 * x for x in draw(st.lists(st.integers(0, 8), min_size=m, max_size=m))]
    sb = [np.nan if bb < 0 else 0.01 * x for bb, x in zip(b, draw(st.lists(st.integers(0, 8), min_size=m, max_size=m)))]
    return _C(a, b, sa, sb)


@st.composite
def _pair(draw):
    return _contacts(draw, draw(st.integers(0, 30))), _contacts(draw, draw(st.integers(0, 30))), \
        draw(st.sampled_from([0.0, 0.01, 0.025, 0.1]))


@settings(max_examples=300, deadline=None)
@given(_pair())
def test_match_contacts_is_the_closest_within_tolerance(case):
    old, new, tol = case
    assert match_contacts(old, new, tol).tolist() == _brute(old, new, tol).tolist()
