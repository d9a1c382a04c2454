"""Wall-clock seconds per stage (report.json's timings_s) and the progress bars of a long run."""

from __future__ import annotations

import time


class Timer:
    """Collects wall-clock seconds per named stage."""

    def __init__(self):
        self.stages: dict[str, float] = {}
        self._t0 = time.perf_counter()

    def stage(self, name: str):
        timer = self

        class _Stage:
            def __enter__(self):
                self.t = time.perf_counter()

            def __exit__(self, *exc):
                timer.stages[name] = timer.stages.get(name, 0.0) + time.perf_counter() - self.t

        return _Stage()

    def total(self) -> float:
        return time.perf_counter() - self._t0


def progress(total, desc, quiet, unit="strand", budget: bool = False):
    """A tqdm bar (off when ``quiet``), left off the screen when done.  ``budget``: ``total`` is an upper
    bound (a sweep budget a solver usually stops well before), so the bar shows no time left extrapolated
    to it (that read 42 minutes for a 6 s solve); its postfix says what is known instead."""
    from tqdm.auto import tqdm  # 50 ms: kept off the CLI's start

    fmt = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}, {rate_fmt}{postfix}]" if budget else None
    return tqdm(total=total, desc=desc, disable=quiet, unit=unit, leave=False, bar_format=fmt)

