"""Save the inverse contact problem of `groom invert --contacts all` to an .npz, for solver experiments
(bench/prototypes/dual_newton.py) without rerunning fit and detection.

    python bench/prototypes/dump_problem.py INPUT [--units cm] [--head MESH] [--snap-roots]
                                            [--contact-radius R] -o problem.npz

Keys: Hd, Hi, Hp, Hs (H in CSR parts), inv_k (K^-1 per dof), w_scale, gamma (relative), b (solver units),
mu, offsets (dof offsets per strand), strand_a, strand_b; stage CPU seconds are printed.
The ContactProblem is ContactProblem(H, inv_k**2 / w_scale, offsets, gamma, b, mu) (as inverse_problem.solve_inverse_problem).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

from groomtool.contact import detect_contacts  # noqa: E402
from groomtool.contact.head import snap_roots  # noqa: E402
from groomtool.contact.jacobian import contact_jacobian  # noqa: E402
from groomtool.fit import fit_groom  # noqa: E402
from groomtool.inverse_problem import build_inverse_problem  # noqa: E402
from groomtool.invert import InversionParams, _snap_groom_roots  # noqa: E402
from groomtool.io import load_groom, load_head  # noqa: E402
from groomtool.rods import superhelix as sh  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("input")
    ap.add_argument("--units", default="m")
    ap.add_argument("--head")
    ap.add_argument("--snap-roots", action="store_true")
    ap.add_argument("--contact-radius", type=float, default=None, help="in --units")
    ap.add_argument("-o", "--output", required=True)
    args = ap.parse_args()
    t = time.process_time()
    stages = {}

    def tick(name):
        nonlocal t
        stages[name] = round(time.process_time() - t, 2)
        print(name, stages[name], "s", flush=True)
        t = time.process_time()

    groom = load_groom(args.input, units=args.units)
    head = load_head(args.head, units=args.units) if args.head else None
    scale = {"m": 1.0, "cm": 0.01, "mm": 0.001}[args.units]
    tick("load")
    if head is not None and args.snap_roots:
        groom, _ = _snap_groom_roots(groom, head, snap_roots)
    params = InversionParams(contacts="all", contact_radius=None if args.contact_radius is None
                             else args.contact_radius * scale)
    helix = fit_groom(groom, tolerance=params.tolerance).helix
    tick("fit")
    kin = sh.kinematics(helix)
    pts, offsets, _, arc = sh.sample(helix, params.samples_per_element, kin)
    contacts = detect_contacts(pts, offsets, arc, radius=params.contact_radius, head=head, strand_strand=True)
    tick("contacts")
    H = sp.csr_matrix(contact_jacobian(helix, contacts, kin))
    tick("jacobian")
    gravity = groom.gravity(params.material.gravity)
    F = sh.gravity_force(helix, params.material.linear_density, gravity, kin)
    mu = np.full(len(contacts.strand_a), params.material.friction)
    P = build_inverse_problem(helix, F, H, params.material, gravity, params.guess, params.gamma, mu)
    tick("build")
    np.savez(args.output, Hd=H.data, Hi=H.indices, Hp=H.indptr, Hs=np.array(H.shape), inv_k=P.inv_stiffness,
             w_scale=P.w_scale, gamma=P.gamma, b=P.b, mu=P.mu, offsets=3 * helix.flat_offsets(),
             strand_a=np.asarray(contacts.strand_a), strand_b=np.asarray(contacts.strand_b))
    print(f"{len(mu):,} contacts, H nnz {H.nnz:,}, {H.shape[1]:,} dofs -> {args.output}; CPU s {stages}")


if __name__ == "__main__":
    main()
