"""Contact solvers: the SOCQP of the inversion and Coulomb friction of the simulator (docs/maths.md sections 5-7).

    u = W r + b,  W = H D H^T + 2 gamma I,  one 3-vector block [N, T1, T2] per contact.

Public API
    solve_socqp(W, b, mu, method="gs" | "apgd" | "clarabel" | "auto", tol=1e-8, max_iter=None, r0=None, **options)
    solve_coulomb(W, b, mu, method="gs", tol=1e-8, max_iter=None, r0=None, **options)
    solve_contact_problem(problem, law="soc" | "coulomb", method="auto", tol=1e-8, max_iter=None, r0=None,
                          form="auto" | "assembled" | "matrix_free", **options)
    (method="admm" there: the strand-split ADMM of admm.py, for contact-dense problems)
    ContactProblem, SolveResult; the 3x3 local solver per block: local.normalize_block, local.solve_block

Modules: cones (projections, natural map), local (3x3 solver), residual (convergence measures),
problem (ContactProblem), blocks (3x3-block storage and assembly), gauss_seidel, anderson, apgd, admm,
clarabel_socqp, certificate, api.
"""

from .api import SolveResult, choose_form, solve_contact_problem, solve_coulomb, solve_socqp
from .problem import ContactProblem

__all__ = [
    "ContactProblem",
    "SolveResult",
    "choose_form",
    "solve_contact_problem",
    "solve_coulomb",
    "solve_socqp",
]
