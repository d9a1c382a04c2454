"""timing.progress: the time left a bar shows is measured on the items after the first (which pays the
numba kernels' loading) and is never shown from the first item alone."""

import re

from groomtool import timing


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _bar(total, budget=False):
    bar = timing.progress(total, "stability with contacts", quiet=False, budget=budget)
    clock = Clock()
    bar._time = clock
    bar.start_t = bar.last_print_t = 0.0
    return bar, clock


def _eta(bar):
    """The time left the bar shows, in seconds (None for '?' or none)."""
    match = re.search(r"<(\d+):(\d+)", str(bar))
    return None if match is None else 60 * int(match[1]) + int(match[2])


def test_first_slow_item_gives_no_eta_then_the_measured_rate_does(capsys):
    """100 strands: the first takes 5 s (kernels loading), the others 10 ms.  From the first strand alone a
    bar extrapolates 99 x 5 s; this one shows '?' until it has measured the others, then the real time."""
    bar, clock = _bar(100)
    clock.t = 5.0
    bar.update(1)
    shown = [(_eta(bar), 0.99)]
    assert "<?" in str(bar)
    for i in range(2, 101):
        clock.t = 5.0 + 0.01 * (i - 1)
        bar.update(1)
        shown.append((_eta(bar), 0.01 * (100 - i)))
    bar.close()
    assert all(eta is None or eta <= max(2 * left, 1) for eta, left in shown), shown
    assert any(eta is not None for eta, _ in shown[60:-1])  # measured: shown once known (in whole seconds)


def test_steady_items_show_their_eta():
    bar, clock = _bar(10)
    for i in range(1, 6):
        clock.t = 10.0 * i
        bar.update(1)
    assert _eta(bar) == 50  # 5 items of 10 s left, at the rate of items 2-5
    assert "10.00s/strand" in str(bar)
    bar.close()


def test_budget_bar_and_quiet_bar():
    bar, clock = _bar(1000, budget=True)
    clock.t = 3.0
    bar.update(10)
    assert _eta(bar) is None and "<?" not in str(bar)  # a budget shows no time left at all
    bar.close()
    quiet = timing.progress(5, "x", quiet=True)
    quiet.update(1)
    quiet.close()


def test_reset_measures_again():
    bar, clock = _bar(10)
    for i in range(1, 6):
        clock.t = float(i)
        bar.update(1)
    assert _eta(bar) == 5
    bar.reset(total=10)  # held_stiffness_ratios resets its bar to the strands it checks
    bar.start_t = clock.t
    clock.t += 30.0
    bar.update(1)
    assert _eta(bar) is None  # a first item again, not extrapolated
    bar.close()


def test_own_estimate_bar_shows_the_callers_postfix_only():
    """simulate_progress.StepProgress writes its own time left (over several runs): no rate, no time left."""
    import io

    stream = io.StringIO()
    bar = timing.progress(10, "simulate", quiet=False, unit="step", own_estimate=True, file=stream)
    bar.set_postfix_str("70 ms/step, ~1 s left", refresh=False)
    bar.update(5)
    text = str(bar)
    bar.close()
    assert "70 ms/step, ~1 s left]" in text and "<" not in text and "step/s" not in text
    assert "simulate" in stream.getvalue()
