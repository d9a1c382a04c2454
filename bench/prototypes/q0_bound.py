"""How tight is the certified rest-curvature error bound (solvers/certificate.py) on a real dense problem?

    python bench/prototypes/q0_bound.py --strands 300 [--contact-radius 3e-4] [--sweeps 100,300,1000]

Builds the inverse problem of example_groom(N) with its head and all contacts (as `groom invert
--contacts all`), solves it to a certified optimum with clarabel (+ Gauss-Seidel polish), then runs
Gauss-Seidel for the listed sweep counts and prints, for each iterate (projected onto the cones): the
natural-map residual, the true relative rest-curvature error |q0 - q0*| / |q0*| and the bound of
certificate.error_bound relative to |q0| (also both relative to the contact correction |q0* - q0_free|).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from groomtool.contact import detect_contacts  # noqa: E402
from groomtool.contact.jacobian import contact_jacobian  # noqa: E402
from groomtool.examples import example_groom  # noqa: E402
from groomtool.fit import fit_groom  # noqa: E402
from groomtool.rods import superhelix as sh  # noqa: E402
from groomtool.solvers import solve_contact_problem  # noqa: E402
from groomtool.solvers.certificate import error_bound, project_forces  # noqa: E402

inv = importlib.import_module("groomtool.invert")
ip = importlib.import_module("groomtool.inverse_problem")


def build(n_strands, radius):
    groom, head = example_groom(n_strands)
    params = inv.InversionParams(contacts="all", contact_radius=radius)
    mat = params.material
    g = groom.gravity(mat.gravity)
    helix = fit_groom(groom, tolerance=params.tolerance).helix
    kin = sh.kinematics(helix)
    pts, offsets, _, arc = sh.sample(helix, params.samples_per_element, kin)
    contacts = detect_contacts(pts, offsets, arc, radius=radius, head=head, strand_strand=True)
    H = contact_jacobian(helix, contacts, kin)
    F = sh.gravity_force(helix, mat.linear_density, g, kin)
    mu = np.full(len(contacts.strand_a), mat.friction)
    P = ip.build_inverse_problem(helix, F, H, mat, g, params.guess, params.gamma, mu)
    q0_free = P.q0_free  # q0 without contacts
    return P, P.contact_problem(helix), q0_free


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--strands", type=int, default=300)
    ap.add_argument("--contact-radius", type=float, default=3e-4)
    ap.add_argument("--sweeps", default="50,100,200,400,800,1600,3200")
    args = ap.parse_args()
    P, cp, q0_free = build(args.strands, args.contact_radius)
    scale = P.f_scale * np.sqrt(P.w_scale)  # |q0 - q0*| = scale |A^T (r - r*)| (solver units)
    sqrt_d = np.sqrt(cp.D_data)
    print(f"example_groom({args.strands}), r_c {args.contact_radius}: {cp.n_contacts:,} contacts, {cp.n_dofs:,} dofs")
    t = time.perf_counter()
    ref = solve_contact_problem(cp, method="clarabel", tol=1e-10)
    print(f"reference: clarabel {ref.status}, residual {ref.residual:.1e}, {time.perf_counter() - t:.1f} s")
    y_ref = sqrt_d * (cp.H.T @ ref.r)
    q0_ref = q0_free - scale * y_ref
    e_ref = error_bound(cp, project_forces(ref.r, cp.mu)[0])
    print(f"|q0*| {np.linalg.norm(q0_ref):.4e}, contact correction |q0* - q0_free| {scale * np.linalg.norm(y_ref):.4e}; "
          f"bound at the reference {scale * e_ref['bound'] / np.linalg.norm(q0_ref):.1e} relative")
    print("| sweeps | residual | true q0 error (rel. q0*) | bound (rel. q0) | bound / true | true (rel. correction) | "
          "bound (rel. correction) | bound with line search | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    r0 = None
    done = 0
    for s in [int(x) for x in args.sweeps.split(",")]:
        t = time.perf_counter()
        res = solve_contact_problem(cp, method="gs", tol=1e-14, max_iter=s - done, r0=r0)
        done, r0 = s, res.r
        r, _ = project_forces(res.r, cp.mu)
        tb = time.perf_counter()
        e = error_bound(cp, r, line_search=False)
        e2 = error_bound(cp, r)
        tb = time.perf_counter() - tb
        y = sqrt_d * (cp.H.T @ r)
        q0 = q0_free - scale * y
        true = np.linalg.norm(q0 - q0_ref)
        bound = scale * e["bound"]
        corr = scale * np.linalg.norm(y)
        print(f"| {s} | {res.residual:.1e} | {true / np.linalg.norm(q0_ref):.2e} | "
              f"{bound / np.linalg.norm(q0):.2e} | {bound / true:.1f} | {true / scale / np.linalg.norm(y_ref):.2e} | "
              f"{bound / corr:.2e} | {scale * e2['bound'] / np.linalg.norm(q0):.2e} | {tb:.2f} |")


if __name__ == "__main__":
    main()
