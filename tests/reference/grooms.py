"""Random grooms for the tests: one generator of random Super-Helices (ragged or not)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from groomtool.rods import superhelix as sh


def random_helix(seed, n_strands=4, max_elements=9, scale=30.0, ragged=True):
    """Random Super-Helices; with ``ragged`` the strands have different element counts (padding)."""
    rng = np.random.default_rng(seed)
    n = rng.integers(1, max_elements + 1, n_strands) if ragged else np.full(n_strands, max_elements)
    lengths = np.zeros((n_strands, max_elements))
    q = np.zeros((n_strands, max_elements, 3))
    for i, k in enumerate(n):
        lengths[i, :k] = rng.uniform(0.005, 0.04, k)
        q[i, :k] = rng.normal(size=(k, 3)) * scale
    return sh.SuperHelix(0.05 * rng.normal(size=(n_strands, 3)),
                         Rotation.random(n_strands, random_state=seed).as_matrix(), lengths, q, n)
