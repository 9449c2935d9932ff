"""A tolerance out of the budget's reach is found out early, and said so."""

import re
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmc
from jaxmc._stream._forecast import Forecast  # the rule itself, on stub error bars
from jaxmc.stats import ReliabilityWarning


F = lambda x: jnp.exp(-jnp.sum(x**2))  # noqa: E731


def _run(forecast, rate, budget_checks, excess0=1e3, dof=7.0):
    """Feed checks at doubling n whose error bar falls like n^-rate from `excess0` times the
    tolerance; the first warning's text, or None."""
    for k in range(budget_checks):
        n = 1024 * 2**k
        stderr = excess0 * (n / 1024) ** -rate
        text = forecast.unreachable(n, 1.0, stderr, dof, 1.0, 0.0)
        if text is not None:
            return text, n
    return None, None


def test_the_forecast_from_stub_error_bars():
    # Falling like n^-1/2 from 1e3 times the tolerance: 1e6 times the evaluations needed.
    text, n = _run(Forecast(2**26, 0.5), 0.5, 12)
    assert text is not None and n <= 1024 * 32 and "out of reach" in text
    # Falling like n^-3/2 from the same: reached within 1e2 times the evaluations.
    assert _run(Forecast(2**26, 1.5), 1.5, 12)[0] is None
    # A stalled error bar, with a budget that a QMC rate would meet: out of reach.
    text, _ = _run(Forecast(2**40, 1.5), 0.0, 12, excess0=100.0)
    assert text is not None and "n^-0.00" in text
    # Noisy error bars of 7 degrees of freedom that fall like n^-3/2: the forecast is
    # optimistic enough that their noise does not call the tolerance unreachable.
    rng = np.random.default_rng(0)
    for _ in range(200):
        forecast = Forecast(int(1024 * 1e3 ** (1 / 1.5) * 4), 1.5)
        for k in range(12):
            n = 1024 * 2**k
            stderr = 1e3 * (n / 1024) ** -1.5 * np.sqrt(rng.chisquare(7) / 7)
            assert forecast.unreachable(n, 1.0, stderr, 7.0, 1.0, 0.0) is None


def test_an_unreachable_tolerance_warns_long_before_the_budget():
    # QMC's error on a smooth 2-D integrand stalls far above 1e-12 of the mean: the default
    # budget, 2^30, cannot meet it. The warning, raised as an error here, ends the run.
    with warnings.catch_warnings():
        warnings.simplefilter("error", ReliabilityWarning)
        with pytest.raises(ReliabilityWarning, match="out of reach") as caught:
            jaxmc.integrate(jax.random.key(0), F, jnp.zeros(2), jnp.ones(2), rtol=1e-12)
    after = int(re.search(r"after ([\d,]+) evaluations", str(caught.value))[1].replace(",", ""))
    assert after < 2**26


@pytest.mark.parametrize("method, rtol", [("auto", 1e-8), ("qmc", 1e-8), ("plain", 3e-4)])
def test_a_reachable_tolerance_is_not_called_unreachable(method, rtol):
    # (Any warning fails a test: pyproject's filterwarnings.)
    for seed in range(3):
        est = jaxmc.integrate(jax.random.key(seed), F, jnp.zeros(2), jnp.ones(2), rtol=rtol,
                              method=method)
        assert bool(est.converged)


def test_the_progress_bar_shows_the_forecast(monkeypatch, capsys):
    # What the stream hands the bar (which redraws at most every 0.1 s: its text may skip
    # any one update).
    from jaxmc._stream import _engine

    notes = []
    report = _engine.report
    monkeypatch.setattr(_engine, "report", lambda *a, note="", **k: (notes.append(note),
                                                                      report(*a, note=note, **k)))
    est = jaxmc.integrate(jax.random.key(0), F, jnp.zeros(2), jnp.ones(2), rtol=3e-4,
                          method="plain", chunk=2**12, progress=True)
    assert bool(est.converged)
    assert any(note.startswith("(needs ~") for note in notes), notes
    capsys.readouterr()  # (the bar's own text, not checked here)
