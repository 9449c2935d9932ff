"""Readable results: the compact notation, `repr` with numbers, `Combined.summary()`, the progress bar."""

import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import gammaincc

import jaxmc
from jaxmc._format import compact  # the notation itself, tested directly
from jaxmc.stats import Estimate, combine


NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize(
    "mean, stderr, text",
    [
        (0.99771, 0.00423, "0.9977(42)"),
        (12.3456, 0.123, "12.35(12)"),
        (1.0023e-05, 4.5e-08, "1.0023(45)e-05"),
        (-0.99771, 0.00423, "-0.9977(42)"),
        (0.0001234, 1.2e-06, "0.0001234(12)"),  # leading digit at 1e-4: still fixed
        (0.5, 0.0999, "0.50(10)"),  # the error rounds up to the next decade
        (9.9996, 0.012, "10.000(12)"),  # the mean rounds up to the next decade
        (12345678.0, 12.0, "12345678(12)"),
        # An error of 1 or more keeps its decimal point, aligned with the mean's digits.
        (12.3456, 1.23, "12.3(1.2)"),
        (1.0, 1.0, "1.0(1.0)"),
        (1234.5, 12.3, "1234(12)"),
        (1.0, 9.96, "1(10)"),
        # An error of 100 or more: scientific, so that every digit shown counts.
        (1234.5, 123.0, "1.23(12)e+03"),
        (-1234.5, 123.0, "-1.23(12)e+03"),
        (2.5e7, 1.2e5, "2.500(12)e+07"),
        (5e-05, 2e-05, "5.0(2.0)e-05"),
        # An error larger than the mean still fixes the rounding.
        (0.1, 0.5, "0.10(50)"),
        (1.0, 123.0, "0.0(1.2)e+02"),
        (-0.0001, 0.5, "0.00(50)"),  # no "-0.00"
        (0.0, 0.1, "0.00(10)"),
        # Exact values, non-finite values, errors below a float64's resolution.
        (1.5, 0.0, "1.5(0)"),
        (0.0, 0.0, "0(0)"),
        (1e-05, 0.0, "1(0)e-05"),
        (NAN, 1.0, "nan ± 1"),
        (1.0, INF, "1 ± inf"),
        (INF, NAN, "inf ± nan"),
        (1e300, 1e-300, "1e+300 ± 1e-300"),
        (1000000.5, 8.9e-10, "1000000.5 ± 8.9e-10"),  # every digit of the mean kept
    ],
)
def test_compact_notation(mean, stderr, text):
    assert compact(mean, stderr) == text


def hand_made(mean, stderr, n=100_000, n_nonfinite=0, **diagnostics):
    return Estimate(mean=jnp.asarray(mean), variance=jnp.asarray(stderr) ** 2,
                    n=jnp.asarray(n, jnp.int32), n_nonfinite=jnp.asarray(n_nonfinite, jnp.int32),
                    **diagnostics)


def test_str_and_repr_show_numbers():
    est = hand_made(0.99771, 0.00423)
    assert str(est) == "0.9977(42)"
    # Unknown diagnostics (NaN: built by hand) are left out.
    assert repr(est) == "Estimate(mean=0.99771, stderr=0.00423, n=100000)"
    est = hand_made(0.99771, 0.00423, n_nonfinite=3, ess=812.34, pareto_k=0.314)
    assert repr(est) == ("Estimate(mean=0.99771, stderr=0.00423, n=100000, n_nonfinite=3, "
                         "ess=812.3, pareto_k=0.31)")
    # The mean keeps the digits its error resolves.
    assert "mean=1.00000001234" in repr(hand_made(1.00000001234, 1e-9))
    pair = hand_made([0.99771, 1.2345], [0.00423, 0.0123])
    assert str(pair) == "[0.9977(42) 1.234(12)]"
    assert repr(pair).startswith("Estimate(mean=[0.99771, 1.2345], stderr=[0.00423, 0.0123]")


def test_str_says_when_an_error_bar_has_few_degrees_of_freedom():
    # mean +- 2 stderr of 3 replicas covers 82%, not 95%: the reader is told.
    assert str(hand_made(0.99771, 0.00423, dof=2.0)) == "0.9977(42) [dof 2]"
    assert str(hand_made(0.99771, 0.00423, dof=30.0)) == "0.9977(42)"
    # A batch (from `vmap`) whose members' error bars differ: each member's, in order.
    batch = hand_made([0.99771, 1.2345], [0.00423, 0.0123], dof=jnp.array([jnp.inf, 2.0]))
    assert str(batch) == "[0.9977(42) 1.234(12)] [dof inf 2]"
    same = hand_made([0.99771, 1.2345], [0.00423, 0.0123], dof=jnp.array([2.0, 2.0]))
    assert str(same) == "[0.9977(42) 1.234(12)] [dof 2]"
    est = jaxmc.integrate(jax.random.key(0), lambda x: jnp.cos(jnp.sum(x)), [0.0] * 3,
                          [1.0] * 3, n=20_000, method="qmc")
    assert np.isfinite(float(est.dof)) and float(est.dof) < 10
    assert str(est).endswith(f" [dof {float(est.dof):.0f}]")


def test_summary_shows_the_race_and_its_winner():
    peak = lambda x: jnp.exp(-jnp.sum((x - 0.4) ** 2) / (2 * 0.05**2))  # noqa: E731
    est = jaxmc.integrate(jax.random.key(0), peak, [0.0] * 4, [1.0] * 4, n=100_000)
    text = est.summary()
    assert str(est) in text and f"method: {est.method}" in text
    winner = [line for line in text.splitlines() if line.endswith("<- won")]
    assert len(winner) == 1 and winner[0].startswith(est.method)
    for name in est.pilot.candidates:
        assert any(line.startswith(name) for line in text.splitlines())
    assert "diagnostics: nothing to report" in text
    # Without a pilot: no race; with a tolerance: its verdict.
    est = jaxmc.integrate(jax.random.key(0), peak, [0.0] * 4, [1.0] * 4, rtol=1e-2,
                          method="plain")
    text = est.summary()
    assert "<- won" not in text and "tolerance: met" in text
    with pytest.raises(ValueError, match="outside `jit`"):
        jax.jit(lambda k: jaxmc.integrate(k, peak, [0.0] * 4, [1.0] * 4, n=4096,
                                          method="plain").summary())(jax.random.key(0))
    # Chosen under jit, the result's name is "auto"; its summary names the winner.
    traced = jax.jit(lambda k: jaxmc.integrate(k, peak, [0.0] * 4, [1.0] * 4, n=100_000))(
        jax.random.key(0))
    won = traced.pilot.candidates[int(traced.pilot.choice)]
    assert traced.method == "auto" and f"method: {won}, the winner" in traced.summary()


def test_summary_shows_the_grids_training_rounds():
    # The VEGAS+ rounds that trained the grid, as vegas's summary shows its iterations: one
    # row each, with the running weighted average's chi2/dof and Q; none where no grid was
    # trained.
    peak = lambda x: jnp.exp(-jnp.sum((x - 0.4) ** 2) / (2 * 0.05**2))  # noqa: E731
    est = jaxmc.integrate(jax.random.key(0), peak, [0.0] * 4, [1.0] * 4, n=100_000,
                          method="adaptive")
    rounds = int(est.rounds.n.shape[0])
    text = est.summary()
    assert "training rounds" in text and "chi2/dof" in text
    last = jaxmc.stats.combine(est.rounds, sequential=True)
    table = text.split("training rounds", 1)[1].split("\n", 1)[1]
    assert compact(est.rounds.mean[-1], est.rounds.stderr[-1]) in table
    assert compact(last.mean, last.stderr) in table
    assert sum(line.lstrip().startswith(f"{i + 1} ") for i in range(rounds)
               for line in table.splitlines()) >= rounds
    qmc = jaxmc.integrate(jax.random.key(0), peak, [0.0] * 4, [1.0] * 4, n=100_000,
                          method="qmc")
    assert qmc.rounds is None and "training rounds" not in qmc.summary()


@pytest.mark.skipif(sys.version_info < (3, 11), reason="exception notes need Python 3.11")
def test_an_integrand_written_for_a_batch_hears_of_batched():
    f = lambda x: jnp.exp(-x[:, 0] ** 2 - x[:, 1] ** 2)  # noqa: E731  (a batch, not a point)
    with pytest.raises(IndexError) as error:
        jaxmc.integrate(jax.random.key(0), f, [0.0, 0.0], [1.0, 1.0], n=4096, method="plain")
    assert "batched=True" in "".join(getattr(error.value, "__notes__", []))
    est = jaxmc.integrate(jax.random.key(0), f, [0.0, 0.0], [1.0, 1.0], n=4096, method="plain",
                          batched=True)
    assert abs(float(est.mean) - 0.557746) < 5 * float(est.stderr)


def test_repr_of_jitted_and_traced_estimates():
    f = lambda x: jnp.exp(-x * x)
    seen = {}

    def run(key):
        est = jaxmc.uniform(key, f, 0.0, 1.0, 64)
        seen["repr"], seen["str"] = repr(est), str(est)  # traced: must not raise
        return est

    est = jax.jit(run)(jax.random.key(0))
    assert "f64[]" in seen["repr"] and "f64[]" in seen["str"]  # equinox's repr of tracers
    text = repr(est)
    assert text.startswith("Estimate(mean=0.7") and "f64" not in text and "n=64" in text
    assert str(est) == compact(est.mean, est.stderr)


# Four rounds, one of them off by ~3 sigma; the fifth empty (no weight, no dof).
MEANS = np.array([1.0, 1.2, 0.7, 1.02, 0.0])
STDERRS = np.array([0.1, 0.2, 0.1, 0.01, 0.0])


def expected_rows(means, stderrs):
    """The running weighted averages, chi2/dof and Q of the parts, computed directly."""
    rows = []
    for i in range(len(means)):
        m, s = means[: i + 1], stderrs[: i + 1]
        m, s = m[s > 0], s[s > 0]
        w = 1 / s**2
        average = np.sum(w * m) / np.sum(w)
        chi2, dof = np.sum(w * (m - average) ** 2), len(m) - 1
        q = gammaincc(dof / 2, chi2 / 2) if dof else 1.0
        rows.append((compact(average, np.sum(w) ** -0.5), chi2 / max(dof, 1), q))
    return rows


def test_summary_table():
    combined = combine([hand_made(m, s, n=1000) for m, s in zip(MEANS, STDERRS)])
    assert repr(combined).endswith(", parts=Estimate[5])") and "chi2_dof=" in repr(combined)
    lines = combined.summary().splitlines()
    assert lines[0].split() == ["itn", "integral", "wgt", "average", "chi2/dof", "Q"]
    assert set(lines[1]) == {"-"}
    rows = [line.split() for line in lines[2:]]
    assert len(rows) == len(MEANS)
    for i, (row, (average, chi2_dof, q)) in enumerate(zip(rows, expected_rows(MEANS, STDERRS))):
        assert row == [str(i + 1), compact(MEANS[i], STDERRS[i]), average,
                       f"{chi2_dof:.2f}", f"{q:.2f}"]
    assert rows[-1][2] == str(combined)  # the last row's average is the combination
    assert float(rows[2][3]) > 2  # the third round disagrees: the column shows it

    # Array-valued: one table per component, each with its own chi2/dof and Q.
    scale = np.array([1.0, 2.0])
    pairs = combine([hand_made(m * scale, s * scale, n=1000) for m, s in zip(MEANS, STDERRS)])
    tables = pairs.summary().split("\n\n")
    assert [t.splitlines()[0] for t in tables] == ["[0]", "[1]"]
    first, second = ([line.split() for line in t.splitlines()[3:]] for t in tables)
    assert [r[3:] for r in first] == [r[3:] for r in second]  # scaling leaves chi2 alone
    assert second[-1][2] == compact(2 * float(combined.mean), 2 * float(combined.stderr))

    with pytest.raises(ValueError, match="outside `jit`"):
        jax.jit(lambda c: (c.summary(), c.mean)[1])(combined)


F = lambda x: jnp.exp(-jnp.sum(x**2))


def last_line(err):
    """The bar's final state: the text after the last carriage return of its last line."""
    assert err.endswith("\n"), repr(err[-80:])  # closed cleanly
    return err.rstrip("\n").split("\n")[-1].split("\r")[-1]


def test_progress_bar(capsys):
    est = jaxmc.integrate(jax.random.key(8), F, [0.0, 0.0], [1.0, 1.0], n=100_000,
                          method="plain", chunk=2**14, progress=True)
    err = capsys.readouterr().err
    final = last_line(err)
    assert final.startswith("integrate: 100%") and "100k/100k" in final
    assert str(est) in final  # the final estimate, in the compact notation
    assert err.count("integrate:") >= 3  # it moved: chunk by chunk
    assert repr(est).startswith("IntegrationEstimate(mean=") and "method='plain'" in repr(est)


def test_progress_bar_under_jit_stops_with_the_tolerance(capsys):
    # Under jit the loop opens and closes its own bar; the tolerance stops it early. With a
    # tolerance the bar counts evaluations with no total (not max_n: 2^30 by default, whose
    # time left would read in days) and no percentage.
    run = jax.jit(lambda key: jaxmc.integrate(key, F, [0.0, 0.0], [1.0, 1.0], rtol=2e-3,
                                              max_n=2**21, method="plain", chunk=2**14,
                                              progress=True))
    est = run(jax.random.key(9))
    err = capsys.readouterr().err
    final = last_line(err)
    assert bool(est.converged) and int(est.n) < 2**21
    assert "%" not in final and str(est) in final
    assert "/" not in final.split("eval")[0] and f"{2**21 / 1e6:.2f}M" not in final


def test_progress_bar_outside_jit_has_no_total_with_a_tolerance(capsys):
    # The bar `integrate` opens around its stream (not the loop's own, as under jit).
    est = jaxmc.integrate(jax.random.key(9), F, [0.0, 0.0], [1.0, 1.0], rtol=2e-3,
                          max_n=2**21, method="plain", chunk=2**14, progress=True)
    final = last_line(capsys.readouterr().err)
    assert bool(est.converged) and int(est.n) < 2**21
    # (No total: no "n/2.10M"; the rate, "2.10Meval/s" on a fast machine, is not one.)
    assert "%" not in final and str(est) in final and f"/{2**21 / 1e6:.2f}M" not in final


def test_adapt_progress_bar(capfd):
    f = lambda x: jnp.exp(-jnp.sum((x - 0.5) ** 2) / 0.02)  # noqa: E731
    grid = jaxmc.proposals.Grid(jnp.zeros(2), jnp.ones(2), bins=16)
    est, _ = jaxmc.fit.adapt(jax.random.key(0), f, grid, iterations=3, n_per_iteration=1000,
                             progress=True)
    err = capfd.readouterr().err
    # One bar labelled `adapt`, at all 3 x 1000 evaluations, closed with a newline.
    assert err.count("adapt:") >= 1 and "3.00k/3.00k" in err and err.endswith("\n")
    assert compact(est.parts.mean[-1], est.parts.stderr[-1]) in err  # the last round's estimate
