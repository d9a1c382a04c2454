"""Progress of a simulation run: a bar whose time estimate comes from measured steps only.

The first step of a run loads (or, on a first run, compiles) the numba kernels and factorises every
strand's step matrix from scratch (the unstable-mode corrections are kept for the later steps:
minutes for thousands of long strands): it is shown as such and left out of the estimate, which is the median of the
run's last 50 measured steps times its steps left (the median: a sagging groom's second and third steps take 2-4x its
later ones, and a mean of them announced twice the run's real time).  Runs differ too much to estimate one from another (groom check's inverted
groom at rest takes tens of milliseconds a step, the sagging naive one ten times more: its contact solves), so each
run is estimated from its own steps, printed once per run after ``announce_after`` of them, with the runs still to
come named.
"""

from __future__ import annotations

import sys
import time

from .timing import progress


class StepProgress:
    """Progress over ``runs`` = [(name, steps), ...] simulated one after the other.

    ``enabled`` False: silent.  ``step(seconds)`` after every step, ``next_run()`` between runs.
    """

    def __init__(self, runs, enabled: bool = True, announce_after: int = 3, stream=None):
        self.runs = list(runs)
        self.enabled = enabled
        self.announce_after = announce_after
        self.stream = stream if stream is not None else sys.stderr
        self.index = 0
        self.done_in_run = 0
        self.measured: list[float] = []  # step times of the current run after its first step
        self.announced = False
        self.bar = None
        self.t0 = time.perf_counter()
        self._open()

    def steps_left(self) -> int:
        """Steps left in the current run."""
        return (self.runs[self.index][1] - self.done_in_run) if self.index < len(self.runs) else 0

    def step_time_s(self) -> float | None:
        """The current run's step time: the median of its last 50 measured steps (None before one was measured)."""
        if not self.measured:
            return None
        recent = sorted(self.measured[-50:])
        n = len(recent)
        return recent[n // 2] if n % 2 else 0.5 * (recent[n // 2 - 1] + recent[n // 2])

    def estimate_s(self) -> float | None:
        """Seconds left in the current run: step_time_s() x its steps left (None before one of its steps was
        measured)."""
        per_step = self.step_time_s()
        return None if per_step is None else per_step * self.steps_left()

    def _open(self) -> None:
        if not self.enabled or self.index >= len(self.runs):
            return
        name, steps = self.runs[self.index]
        self.bar = progress(steps, name, quiet=False, unit="step", own_estimate=True, file=self.stream)
        self.bar.set_postfix_str("first step: loading kernels (compiled on a first run only), first factorisations",
                                 refresh=True)

    def step(self, seconds: float) -> None:
        if self.done_in_run > 0:
            self.measured.append(seconds)
        self.done_in_run += 1
        if self.bar is None:
            return
        left = self.estimate_s()
        if left is None:
            self.bar.set_postfix_str(f"first step {seconds:.1f} s (kernels loaded, step matrices factorised)",
                                     refresh=False)
        else:
            self.bar.set_postfix_str(f"{1e3 * self.step_time_s():.0f} ms/step, "
                                     f"~{_duration(left)} left", refresh=False)
        self.bar.update(1)
        if not self.announced and len(self.measured) >= self.announce_after:
            self.announced = True
            name = self.runs[self.index][0]
            later = ", ".join(f"{n} ({k} steps)" for n, k in self.runs[self.index + 1:])
            then = f"; then {later}, estimated once it has started" if later else ""
            self.bar.write(f"estimated run time of {name}: ~{_duration(left)} more for {self.steps_left()} steps "
                           f"({1e3 * left / max(self.steps_left(), 1):.0f} ms/step){then}", file=self.stream)

    def next_run(self) -> None:
        self.close()
        self.index += 1
        self.done_in_run = 0
        self.measured = []
        self.announced = False
        self._open()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _duration(seconds: float) -> str:
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
