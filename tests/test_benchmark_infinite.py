"""The infinite-limits benchmark: its closed forms and vegas's substitution are right."""

import numpy as np

import benchmarks
from benchmarks import infinite


def test_the_substituted_integrands_integrate_to_the_closed_forms():
    # Plain Monte Carlo on vegas's substituted box (2^20 points): within 5 of its standard
    # errors of each case's exact value (for the posterior, of the ratio's two integrals).
    rng = np.random.default_rng(0)
    for case in infinite.cases():
        fz, bounds = infinite._substituted(case)
        lo, hi = (np.asarray(b) for b in zip(*bounds))
        z = lo + (hi - lo) * rng.random((2**20, case.d))
        values = fz(z) * np.prod(hi - lo)
        mean, stderr = values.mean(axis=0), values.std(axis=0) / np.sqrt(len(values))
        if case.posterior:  # E[x0] = int x0 pi / int pi, by the delta method
            ratio = mean[1] / mean[0]
            residual = (values[:, 1] - ratio * values[:, 0]) / mean[0]
            mean, stderr = ratio, residual.std() / np.sqrt(len(values))
        assert abs(mean - case.exact) < 5 * stderr, (case.name, mean, case.exact, stderr)


def test_a_case_is_measured():
    case = infinite.cases()[3]  # exp(-x) on [0, inf)
    entry = infinite._jaxmc(case, 2**12, keys=3)
    assert entry["relerr"] < 1e-3 and entry["max_z"] < 5 and entry["first_s"] > 0
    scipy = infinite._scipy(case, 1e-6)
    assert scipy["relerr"] < 1e-6
    assert "infinite" in benchmarks.SUITES and "infinite" not in benchmarks.FULL_ONLY
