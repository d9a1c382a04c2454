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


def progress(total, desc, quiet, unit="strand"):
    """A tqdm bar (off when ``quiet``), left off the screen when done."""
    from tqdm.auto import tqdm  # 50 ms: kept off the CLI's start

    return tqdm(total=total, desc=desc, disable=quiet, unit=unit, leave=False)

