"""The first run: numba compiles groomtool's kernels (and caches them on disk, so later runs load them).

On a cold cache a first ``groom invert`` spends most of its time compiling, inside whichever stage
first calls each kernel: the progress bars then sit at 0 % and extrapolate absurd ETAs from a first
step that was mostly compilation.  :func:`cold_kernels` tells from numba's own cache index whether
that is about to happen; :func:`warm_up` compiles what an inversion with the same options needs by
inverting a tiny groom first, so that the real run's bars measure the real work.  ``groom invert``
does both, saying so once ("compiling kernels, first run only").
"""

from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path

# every inversion calls the kernels of these modules: their cache says whether this is a first run
# (other modules hold kernels of paths a given run may not take: clarabel, strand/strand, simulate)
FIRST_RUN_MODULES = ("groomtool.rods.superhelix", "groomtool.fit.error", "groomtool.fit.helix",
                     "groomtool.fit.sampling", "groomtool.fit.state")
COLD_FRACTION = 0.5  # a first run: at least half of those kernels are not cached
# seconds the warm-up compiled for with an empty NUMBA_CACHE_DIR (bundled example, --contacts head):
# 282 s on 2 CPU cores shared with other jobs (the whole first run: 314 s, of which 2.1 s inversion;
# without the warm-up 364 s, the fit bar at 0 % for 74 s).  An estimate only: it scales with the
# machine and its load
FIRST_RUN_COMPILE_S = 280


def kernel_modules() -> list[str]:
    """groomtool modules that define disk-cached numba kernels (``cache=True``)."""
    root = Path(__file__).resolve().parent
    names = []
    for path in sorted(root.rglob("*.py")):
        try:
            text = path.read_text(encoding="utf-8")
        except OSError:
            continue
        if "cache=True" in text:
            rel = path.relative_to(root).with_suffix("")
            names.append(".".join(("groomtool",) + rel.parts))
    return names


def _dispatchers(module) -> list:
    from numba.core.dispatcher import Dispatcher

    return [v for v in vars(module).values()
            if isinstance(v, Dispatcher) and getattr(v, "__module__", None) == module.__name__]


def cold_kernels(modules=None) -> tuple[int, int]:
    """(cold, total): disk-cached kernels of ``modules`` (default :func:`kernel_modules`) that numba's
    cache holds no compiled version of (no index, or one made stale by an edited source), and how
    many there are.  Modules that fail to import (optional dependencies) are skipped."""
    cold = total = 0
    for name in modules if modules is not None else kernel_modules():
        try:
            module = importlib.import_module(name)
        except Exception:  # an optional dependency missing: not our kernels' business
            continue
        for d in _dispatchers(module):
            cache = getattr(d, "_cache", None)
            cache_file = getattr(cache, "_cache_file", None)
            if cache_file is None:  # NullCache: not cached on disk
                continue
            total += 1
            try:
                index = cache_file._load_index()  # numba: {} when missing or stale
            except Exception:
                index = {}
            cold += not index
    return cold, total


def warm_up(params=None, with_head: bool = True, n_strands: int = 8) -> float:
    """Compile the kernels an inversion with ``params`` needs by inverting the bundled example's
    first ``n_strands`` strands (quietly, nothing written); returns the seconds it took."""
    import warnings

    from .examples import example_groom
    from .invert import invert_groom

    start = time.perf_counter()
    groom, head = example_groom(n_strands=n_strands, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            invert_groom(groom, head=head if with_head else None, params=params, quiet=True)
        except Exception:  # a warm-up failing must not stop the real run: it compiles lazily then
            pass
    return time.perf_counter() - start


def announce_and_warm(params=None, with_head: bool = True, stream=None) -> bool:
    """When kernels are cold: say so once on ``stream`` (stderr), compile them, say how long it
    took; returns whether it did."""
    stream = stream if stream is not None else sys.stderr
    cold, total = cold_kernels(FIRST_RUN_MODULES)
    if total == 0 or cold < COLD_FRACTION * total:  # a few cold kernels (an edited module): compiled lazily
        return False
    estimate = max(10, int(round(FIRST_RUN_COMPILE_S * cold / total, -1)))
    print(f"groom: compiling kernels (first run only, up to ~{estimate} s, less on a fast idle machine); "
          "later runs load them from numba's cache", file=stream, flush=True)
    took = warm_up(params, with_head)
    print(f"groom: kernels compiled in {took:.0f} s", file=stream, flush=True)
    return True
