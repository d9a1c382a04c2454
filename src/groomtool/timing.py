"""Wall-clock seconds per stage (report.json's timings_s) and the progress bars of a long run."""

from __future__ import annotations

import functools
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


def progress(total, desc, quiet, unit="strand", budget: bool = False, own_estimate: bool = False, file=None):
    """A tqdm bar (off when ``quiet``), left off the screen when done: the one form of the package's progress
    bars.  ``budget``: ``total`` is an upper bound (a sweep budget a solver usually stops well before), so the
    bar shows no time left extrapolated to it (that read 42 minutes for a 6 s solve); its postfix says what is
    known instead.  ``own_estimate``: the caller writes its own time left in the postfix
    (simulate_progress.StepProgress, over several runs), so the bar shows neither a time left nor a rate.
    ``file``: the stream (default: tqdm's, stderr).

    The time left is measured on the items after the first, which pays what is done once for all (loading
    numba kernels, batched set-up: "stability with contacts" computes every strand's contact Hessian before
    its first strand, 1.5-2.3 s, then takes 0.2-0.5 s for the other 199; extrapolated from the first, its bar
    read minutes), and shown only once ``ETA_AFTER_ITEMS`` of them took ``ETA_AFTER_S`` seconds; until then
    it reads ``?``."""
    fmt = _BUDGET if budget else _OWN_ESTIMATE if own_estimate else None
    stream = {} if file is None else {"file": file}
    return _bar_class()(total=total, desc=desc, disable=quiet, unit=unit, leave=False, bar_format=fmt, **stream)


ETA_AFTER_ITEMS = 2  # items after the first before a time left is shown
ETA_AFTER_S = 0.5  # ... and seconds they took
_UNMEASURED = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<?{postfix}]"
_BUDGET = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}, {rate_fmt}{postfix}]"
_OWN_ESTIMATE = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]"


@functools.cache
def _bar_class():
    from tqdm.auto import tqdm  # 50 ms: kept off the CLI's start

    class Bar(tqdm):
        """tqdm whose rate (and so its time left) counts only the items after the first."""

        _first = None  # (time, n) when the first item was done

        def update(self, n=1):
            if not self.disable and self._first is None and self.n + n >= 1:
                self._first = (self._time(), self.n + n)  # before the refresh that update may make
            return super().update(n)

        def reset(self, total=None):
            self._first = None
            return super().reset(total=total)

        @property
        def format_dict(self):
            d = super().format_dict
            if self.disable or self.bar_format is not None:  # off, or a bar that shows no time left of its own
                return d
            done = self.n - self._first[1] if self._first else 0
            took = self._time() - self._first[0] if self._first else 0.0
            if done >= ETA_AFTER_ITEMS and took >= ETA_AFTER_S:
                d["rate"] = done / took
            else:
                d["bar_format"] = _UNMEASURED
            return d

    return Bar
