"""Which contact solver the inversion runs, and when it gives up or stops early: the policy, apart from
the inverse problem (inverse_problem.py) and the solvers themselves (solvers/).  Measurements behind
the thresholds: docs/solvers.md sections 9 and 11, bench/results/invert.md.
"""

from __future__ import annotations

import numpy as np

from .rods import superhelix as sh

AUTO_CLARABEL_MAX_CONTACTS = 10_000
AUTO_GS_MAX_REDUNDANT = 0.25
#: default q0_tolerance: certified relative rest-curvature error at which the contact solve may stop (gamma itself
#: moves q0 by ~1 %; harolongo's head contacts: 210 sweeps instead of 1,460 to residual 1e-8, true error 4.5e-4)
Q0_TOLERANCE = 1e-3
#: Gauss-Seidel stops early once its rate projects more than this many times the sweep budget
#: (solvers.gauss_seidel.projected_sweeps): dense grooms then fail in minutes, not after the whole budget
GS_GIVE_UP = 2.0
#: ``auto`` on dense contacts beyond AUTO_CLARABEL_MAX_CONTACTS runs the strand-split ADMM (solvers/admm.py) instead of
#: Gauss-Seidel when its per-strand Cholesky factors and per-end state take at most this many bytes
ADMM_MEMORY_CAP = 4 << 30


def redundant_strand_fraction(helix: sh.SuperHelix, contacts) -> float:
    """Of the strands that carry contacts, the fraction on which, up to some element e, the contact ends
    give more constraint rows (3 each) than the dofs of elements 0..e (3 each).  There W = H D H^T +
    2 gamma I has directions held by gamma alone and Gauss-Seidel stalls (docs/solvers.md section 9):
    measured 3 % on sparse real contacts that converge, 85-100 % on dense ones that stall."""
    strand = np.concatenate([np.asarray(contacts.strand_a), np.asarray(contacts.strand_b)])
    arc = np.concatenate([np.asarray(contacts.s_a), np.asarray(contacts.s_b)])
    keep = strand >= 0
    strand, arc = strand[keep].astype(np.int64), arc[keep]
    if not len(strand):
        return 0.0
    elem, _ = sh.locate(helix, strand, arc)
    order = np.lexsort((elem, strand))
    strand, elem = strand[order], elem[order]
    first = np.searchsorted(strand, strand)  # index of each end's strand's first end
    rank = np.arange(len(strand)) - first + 1  # ends on this strand at elements <= elem (ties: the last one counts)
    over = rank > elem + 1
    return float(len(np.unique(strand[over])) / len(np.unique(strand)))


def choose_solver(solver: str, n_contacts: int, redundant_fraction: float = 1.0) -> str:
    """``auto``: Gauss-Seidel where it converges: sparse contacts (at most 25 % of the contact-carrying
    strands redundant, redundant_strand_fraction), or more than 10,000 contacts, where clarabel's
    factorisations stop scaling; clarabel (then polished by Gauss-Seidel) for dense contacts up to 10,000.
    Measured (docs/solvers.md section 9, bench/results/invert.md): harolongo's 8,379 head contacts (0 %
    redundant) GS 5.1 s vs clarabel + polish 12.9 s; usc10k's 11,717 head contacts (1 %) GS 3.8 s; the
    200-strand example's 6,094 contacts (100 %) clarabel 10 s while GS stalls."""
    if solver != "auto":
        return solver
    if n_contacts > AUTO_CLARABEL_MAX_CONTACTS or redundant_fraction <= AUTO_GS_MAX_REDUNDANT:
        return "gs"
    return "clarabel"



def dense_iterative_method(problem, redundant_fraction: float, structured: bool = False) -> str:
    """The iterative method for ``auto`` once choose_solver has picked the iterative family ("gs"): the
    strand-split ADMM (solvers/admm.py) on dense contacts (more than AUTO_GS_MAX_REDUNDANT of the contact-carrying
    strands redundant) when its memory (solvers.admm.strand_split_bytes of the ContactProblem; ``structured``: with
    the Super-Helix geometry, its semiseparable strand factors) fits ADMM_MEMORY_CAP, else Gauss-Seidel.  Measured on example_groom(1000) with all contacts (67,805, 100 %
    redundant): the certified rest-curvature bound 1e-3 in ~50 s CPU, where Gauss-Seidel is at 4.3e-2 after 60 s
    and every Gauss-Seidel / APGD option tried stays above 3e-3 after 90 s (docs/solvers.md section 12)."""
    if redundant_fraction <= AUTO_GS_MAX_REDUNDANT:
        return "gs"
    from .solvers.admm import strand_split_bytes  # the solvers: kept off the CLI's start

    return "admm" if strand_split_bytes(problem, structured=structured) <= ADMM_MEMORY_CAP else "gs"
