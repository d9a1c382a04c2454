"""Synthetic hair-like contact problems (SOCQPs / Coulomb problems) for the solver benchmarks and tests.

``hair_like_problem(m)`` builds a groomtool.solvers.ContactProblem that looks like the inverse (or
dynamic) hair problem of docs/maths.md sections 5-7:

* S strands of N = 20 Super-Helix-like elements, 3 dofs per element (60 dofs per strand); each strand is a
  random smooth curve of length 1 with a material frame per element.
* Contact Jacobians are those of a kinematic chain: a point at arc s on element e moves with dof (j, k),
  j <= e, by  lever_j * n_k^j x (p - c_j)  (lever = l for j < e, s - s_e for j = e; c_j the middle of the
  swept part of element j).  So contact i's rows are non-zero only on the dofs of elements 0..e of each
  strand involved, and contacts near the tip depend on all upstream elements.
* m contacts: a fraction ``body_fraction`` strand/body (one strand, element in the root half), the rest
  between two random distinct strands (elements uniform), u = F (J_a v_a - J_b v_b) with a random
  orthonormal frame F = [e_N, e_T1, e_T2].
* D per strand: ``variant="inverse"``: D = K^{-2}, K = l diag(GJ, EI, EI) per element (GJ = EI / 1.35,
  the circular-fibre ratio), a diagonal;  ``variant="dynamics"``: D = (M + a K)^{-1} dense, M the chain's
  mass matrix (sum over 2 samples per element of J^T J) and a = 0.1 tr(M) / tr(K) (the implicit stiffness
  of one time step), an SPD block with the wide, hair-like spectrum of a rod.
* D is scaled so that the mean diagonal entry of H D H^T is 1; then gamma (default 0.01) is relative to
  that scale: W = H D H^T + 2 gamma I.
* mu uniform in ``mu_range`` (default 0.2-0.4); b = H v_free with v_free ~ N(0, 1) per dof, scaled so that
  rms_i ||b_i|| = 1.
* ``window=None``: the two strands of a contact are drawn at random (the contact graph is an expander:
  the worst case for a direct factorisation); ``window=w``: strands sit on a sqrt(S) x sqrt(S) scalp grid
  and a contact joins strands at most w cells apart (contacts between neighbours, as in real hair).
* The default strand count is m / 4 (about 7.4 contact ends per strand: 30k contacts on 7.5k strands,
  the density of a full groom such as digital-salon's 7,905-strand "harolongo").
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from groomtool.solvers import ContactProblem

GJ_OVER_EI = 1.0 / 1.35


def _rotation(axis_angle: np.ndarray) -> np.ndarray:
    """Rodrigues: (k, 3) rotation vectors -> (k, 3, 3) rotation matrices."""
    th = np.linalg.norm(axis_angle, axis=1)
    k = np.where(th[:, None] > 1e-12, axis_angle / np.maximum(th, 1e-300)[:, None], 0.0)
    K = np.zeros((len(th), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3)[None] + s * K + (1 - c) * (K @ K)


def strand_geometry(S: int, N: int, rng, curl: float = 4.0):
    """Random smooth strands of length 1: element start points x (S, N+1, 3) and frames F (S, N, 3, 3)
    (F[s, j, k] = n_k of element j; n_0 the tangent)."""
    l = 1.0 / N
    q, _ = np.linalg.qr(rng.normal(size=(S, 3, 3)))
    frame = np.transpose(q, (0, 2, 1))  # rows = n0, n1, n2
    x = np.zeros((S, N + 1, 3))
    F = np.zeros((S, N, 3, 3))
    for j in range(N):
        F[:, j] = frame
        x[:, j + 1] = x[:, j] + l * frame[:, 0]
        omega = rng.normal(scale=curl, size=(S, 3)) * l  # rotation over the element, in material coords
        R = _rotation(np.einsum("ska,sk->sa", frame, omega))
        frame = np.einsum("sab,skb->ska", R, frame)
    return x, F


def point_jacobian(x, F, strand, elem, t, N):
    """d p / d q (k, 3, 3N) for points p = x[e] + t n0[e] (chain kinematics, see module docstring)."""
    l = 1.0 / N
    k = len(strand)
    p = x[strand, elem] + t[:, None] * F[strand, elem, 0]
    J = np.zeros((k, 3, 3 * N))
    for j in range(N):
        active = j <= elem
        if not active.any():
            continue
        idx = np.flatnonzero(active)
        s = strand[idx]
        lever = np.where(elem[idx] > j, l, t[idx])
        centre = x[s, j] + 0.5 * lever[:, None] * F[s, j, 0]
        arm = p[idx] - centre
        for kk in range(3):
            J[idx, :, 3 * j + kk] = lever[:, None] * np.cross(F[s, j, kk], arm)
    return J


def _frames(k: int, rng) -> np.ndarray:
    """(k, 3, 3) random orthonormal contact frames, rows e_N, e_T1, e_T2."""
    n = rng.normal(size=(k, 3))
    n /= np.linalg.norm(n, axis=1)[:, None]
    a = rng.normal(size=(k, 3))
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    t2 = np.cross(n, t1)
    return np.stack([n, t1, t2], axis=1)


def _grid_partner(sa: np.ndarray, S: int, w: int, rng) -> np.ndarray:
    """A partner for each strand among its neighbours within +-w cells on a sqrt(S) x sqrt(S) scalp grid."""
    g = int(np.ceil(np.sqrt(S)))
    ia, ja = sa // g, sa % g
    sb = np.full_like(sa, -1)
    todo = np.arange(len(sa))
    while todo.size:
        di = rng.integers(-w, w + 1, size=todo.size)
        dj = rng.integers(-w, w + 1, size=todo.size)
        i, j = ia[todo] + di, ja[todo] + dj
        cand = i * g + j
        ok = (i >= 0) & (i < g) & (j >= 0) & (j < g) & (cand < S) & (cand != sa[todo])
        sb[todo[ok]] = cand[ok]
        todo = todo[~ok]
    return sb


def make_hair_like(
    n_contacts: int,
    *,
    n_strands: int | None = None,
    elements: int = 20,
    body_fraction: float = 0.15,
    variant: str = "inverse",
    gamma: float = 0.01,
    mu_range: tuple[float, float] = (0.2, 0.4),
    seed: int = 0,
    window: int | None = None,
):
    """(ContactProblem, info) for a hair-like problem (module docstring).  info holds per-contact
    strand / element of each end (-1 for the body) and the strand count."""
    rng = np.random.default_rng(seed)
    m = int(n_contacts)
    N = int(elements)
    S = int(n_strands) if n_strands else max(2, m // 4)
    ndof = 3 * N
    x, F = strand_geometry(S, N, rng)

    n_body = int(round(body_fraction * m))
    sa = rng.integers(0, S, size=m)
    if window is None:
        sb = rng.integers(0, S - 1, size=m)
        sb = np.where(sb >= sa, sb + 1, sb)
    else:
        sb = _grid_partner(sa, S, int(window), rng)
    sb[:n_body] = -1
    ea = rng.integers(0, N, size=m)
    ea[:n_body] = rng.integers(0, max(1, N // 2), size=n_body)
    eb = np.where(sb >= 0, rng.integers(0, N, size=m), -1)
    l = 1.0 / N
    frames = _frames(m, rng)

    rows, cols, vals = [], [], []
    for strand, elem, sign, sel in ((sa, ea, 1.0, np.arange(m)), (sb, eb, -1.0, np.flatnonzero(sb >= 0))):
        for chunk in np.array_split(sel, max(1, len(sel) // 20000)):
            if len(chunk) == 0:
                continue
            t = rng.uniform(0.05, 0.95, size=len(chunk)) * l
            J = point_jacobian(x, F, strand[chunk], elem[chunk], t, N)
            B = sign * np.einsum("kab,kbc->kac", frames[chunk], J)  # (k, 3, 3N)
            width = 3 * (elem[chunk] + 1)
            kk, aa, cc = np.nonzero(np.arange(ndof)[None, None, :] < width[:, None, None] + 0 * B)
            rows.append(3 * chunk[kk] + aa)
            cols.append(strand[chunk][kk] * ndof + cc)
            vals.append(B[kk, aa, cc])
    H = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * m, S * ndof)
    )
    offsets = np.arange(S + 1, dtype=np.int64) * ndof

    kdiag = np.tile(l * np.array([GJ_OVER_EI, 1.0, 1.0]), N)  # K per strand (EI = 1)
    if variant == "inverse":
        D = np.tile(1.0 / kdiag**2, S)
        blocks = D
    elif variant == "dynamics":
        blocks = np.empty((S, ndof, ndof))
        for chunk in np.array_split(np.arange(S), max(1, S // 500)):
            st = np.repeat(chunk, 2 * N)
            el = np.tile(np.repeat(np.arange(N), 2), len(chunk))
            tt = np.tile(np.array([0.25, 0.75]) * l, N * len(chunk))
            J = point_jacobian(x, F, st, el, tt, N).reshape(len(chunk), 2 * N, 3, ndof)
            M = np.einsum("sxai,sxaj->sij", J, J) * (l / 2)
            a = 0.1 * np.trace(M, axis1=1, axis2=2) / kdiag.sum()
            Mh = M + a[:, None, None] * np.diag(kdiag)[None]
            Dinv = np.linalg.inv(Mh)
            blocks[chunk] = 0.5 * (Dinv + np.transpose(Dinv, (0, 2, 1)))
    else:
        raise ValueError("variant must be 'inverse' or 'dynamics'")

    mu = rng.uniform(*mu_range, size=m)
    prob = ContactProblem(H, blocks if variant == "inverse" else list(blocks), offsets, 0.0, np.zeros(3 * m), mu)
    # scale D so the mean diagonal entry of H D H^T is 1
    tr = np.einsum("kii->k", prob.diagonal_blocks())
    c = tr.mean() / 3.0
    if variant == "inverse":
        blocks = blocks / c
    else:
        blocks = list(blocks / c)
    v_free = rng.normal(size=S * ndof)
    b = H @ v_free
    b /= np.sqrt(np.mean(np.sum(b.reshape(-1, 3) ** 2, axis=1)))
    prob = ContactProblem(H, blocks, offsets, gamma, b, mu)
    info = {"strand_a": sa, "elem_a": ea, "strand_b": sb, "elem_b": eb, "n_strands": S, "variant": variant}
    return prob, info


def hair_like_problem(n_contacts: int, **kw) -> ContactProblem:
    """The ContactProblem of make_hair_like (see module docstring)."""
    return make_hair_like(n_contacts, **kw)[0]


def random_factored_problem(m: int, n_strands: int, dofs: int, *, gamma=0.01, mu=0.3, dense=True, seed=0):
    """A small unstructured factored problem (tests): random sparse H, random SPD (or diagonal) D."""
    rng = np.random.default_rng(seed)
    n = n_strands * dofs
    H = sp.random(3 * m, n, density=min(1.0, 6.0 / dofs), random_state=rng, format="csr")
    H = H + sp.csr_matrix((rng.normal(size=3 * m), (np.arange(3 * m), rng.integers(0, n, size=3 * m))), shape=(3 * m, n))
    if dense:
        blocks = []
        for _ in range(n_strands):
            B = rng.normal(size=(dofs, dofs))
            blocks.append(B @ B.T / dofs + 0.1 * np.eye(dofs))
    else:
        blocks = rng.uniform(0.2, 2.0, size=n)
    b = rng.normal(size=3 * m)
    mus = np.broadcast_to(np.asarray(mu, float), (m,)).copy()
    return ContactProblem(H, blocks, np.arange(n_strands + 1) * dofs, gamma, b, mus)


# ----------------------------------------------------------------------------------------------
# so-bogus's generator (../shared/bench/gen_hair_problem.py): the side-by-side problems
# ----------------------------------------------------------------------------------------------
def read_bogus_problem(path):
    """(W, b, mu) of a problem file written by gen_hair_problem.py ("BGSPRB01": n, nnzb, the lower block
    triangle's rows, cols and row-major 3x3 blocks, b (3n,), mu (n,), little-endian).  W is returned as
    the full symmetric scipy CSR matrix (3n, 3n)."""
    with open(path, "rb") as f:
        magic = f.read(8)
        if magic != b"BGSPRB01":
            raise ValueError(f"{path}: not a BGSPRB01 problem file (magic {magic!r})")
        n, nnzb = (int(v) for v in np.fromfile(f, dtype="<i8", count=2))
        rows = np.fromfile(f, dtype="<i8", count=nnzb)
        cols = np.fromfile(f, dtype="<i8", count=nnzb)
        vals = np.fromfile(f, dtype="<f8", count=9 * nnzb).reshape(nnzb, 3, 3)
        b = np.fromfile(f, dtype="<f8", count=3 * n)
        mu = np.fromfile(f, dtype="<f8", count=n)
        if mu.size != n or f.read(1):
            raise ValueError(f"{path}: truncated or oversized problem file")
    off = rows != cols
    # lower blocks (i >= j) and their transposes above the diagonal
    R = np.concatenate([rows, cols[off]])
    C = np.concatenate([cols, rows[off]])
    V = np.concatenate([vals, np.transpose(vals[off], (0, 2, 1))])
    ii = (3 * R[:, None, None] + np.arange(3)[None, :, None]) + 0 * np.arange(3)[None, None, :]
    jj = (3 * C[:, None, None] + np.arange(3)[None, None, :]) + 0 * np.arange(3)[None, :, None]
    W = sp.csr_matrix((V.reshape(-1), (ii.reshape(-1), jj.reshape(-1))), shape=(3 * n, 3 * n))
    return W, b, mu
