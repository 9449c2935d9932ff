"""Shared test pieces: running an estimator over many keys, the statistical checks on
the result, test integrands with known integrals, and a count of XLA compilations.

Statistical checks use fixed keys, so their outcome is deterministic; the bands are
5 standard deviations (or a p-value floor of `P_FLOOR`) so a correct estimator passes
for essentially every choice of keys.
"""

import contextlib
import logging
import os
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

import jaxmc
from jaxmc._diagnostics import warn_if_unreliable


# Subprocesses (notebook kernels, multi-device and multi-process runs) compile as the
# tests do (`JAXMC_TEST_XLA_FLAGS`, set by conftest.py: no backend optimisation, the
# elemental emitters). They check that code runs and that device layouts agree bit for bit
# among runs compiled alike, not the speed of the compiled code; their small sizes make
# compilation most of their time (measured: notebook 05, 89 s -> 48 s at level 0).
SUBPROCESS_XLA_FLAGS = os.environ.get("JAXMC_TEST_XLA_FLAGS", "--xla_backend_optimization_level=0")


def subprocess_xla_flags(devices: int | None = None) -> str:
    """`XLA_FLAGS` for a test's subprocess: `SUBPROCESS_XLA_FLAGS`, and `devices` host devices."""
    if devices is None:
        return SUBPROCESS_XLA_FLAGS
    return f"--xla_force_host_platform_device_count={devices} {SUBPROCESS_XLA_FLAGS}"


# --------------------------------------------------------------------------------------
# Goodness of fit


P_FLOOR = 1e-4
"""Smallest p-value a goodness-of-fit test may have (divide it among a test's checks)."""


def assert_uniform(samples, label):
    """KS test of each column of `samples` against U[0,1), Bonferroni over columns."""
    samples = np.asarray(samples, np.float64)
    assert samples.min() >= 0.0 and samples.max() < 1.0, label
    cols = samples.reshape(samples.shape[0], -1)
    pvalues = [stats.kstest(cols[:, j], "uniform").pvalue for j in range(cols.shape[1])]
    assert min(pvalues) > P_FLOOR / cols.shape[1], f"{label}: KS p-values {pvalues}"


def one_per_bin(x, bins):
    """Every column of `x` has exactly one point in each of `bins` equal bins of [0, 1)."""
    cells = np.floor(np.asarray(x) * bins).astype(np.int64)
    return all(np.array_equal(np.sort(cells[:, j]), np.arange(bins)) for j in range(cells.shape[1]))


# --------------------------------------------------------------------------------------
# Many keys


def run_keys(fn, seed, k=400):
    """`fn(key)` over `k` keys split from `jax.random.key(seed)`, jitted and vmapped."""
    keys = jax.random.split(jax.random.key(seed), k)
    return jax.jit(jax.vmap(fn))(keys)


def assert_unbiased_and_honest(est, exact, *, honest="equal"):
    r"""Check `k` estimates (an `Estimate` with a leading axis of keys) of the integral `exact`.

    Unbiased: the average of the estimates is within 5 of its empirical standard errors
    of `exact`. Honest: the empirical variance of the estimates matches the mean
    reported variance within a chi-square band of 5 standard deviations,
    $\sqrt{2/(k-1)}$ relative (`honest="equal"`), or is not above it
    (`honest="conservative"`). Returns the ratio empirical / reported variance.
    """
    mean = np.asarray(est.mean)
    var = np.asarray(est.variance)
    k = len(mean)
    assert np.all(np.isfinite(var)) and np.all(var > 0)
    # The average of k estimates, in units of its empirical standard error (a per-key
    # z-score would be skewed when a variance estimate has few degrees of freedom).
    z = (mean.mean(axis=0) - exact) / (mean.std(axis=0, ddof=1) / np.sqrt(k))
    assert abs(z).max() < 5, f"z-score of the average {z}"
    ratio = mean.var(axis=0, ddof=1) / var.mean(axis=0)
    tolerance = 5 * np.sqrt(2 / (k - 1))
    if honest == "equal":
        assert np.all(abs(ratio - 1) < tolerance), f"empirical/reported variance {ratio}"
    else:  # conservative: the reported variance is not below the empirical one
        assert np.all(ratio < 1 + tolerance), f"empirical/reported variance {ratio}"
    return ratio


_compiled_importance = eqx.filter_jit(jaxmc.importance)


def assert_eager_method_honest(f, exact, lo, hi, n, method, keys, least):
    """Over the eager `integrate` runs on `keys` that chose `method` (at least `least` of
    them; the stream's randomness is independent of the pilot's choice): the mean error
    within 5 of its standard errors, the reported variance not below the spread's (within
    a chi-square band of 5 standard deviations)."""
    means, variances = [], []
    for k in keys:
        est = jaxmc.integrate(jax.random.key(k), f, lo, hi, n=n)
        if est.method == method:
            means.append(float(est.mean))
            variances.append(float(est.stderr) ** 2)
    assert len(means) >= least, len(means)
    means = np.asarray(means)
    z = (means.mean() - exact) / (means.std(ddof=1) / np.sqrt(len(means)))
    assert abs(z) < 5, z
    ratio = means.var(ddof=1) / np.mean(variances)
    assert ratio < 1 + 5 * np.sqrt(2 / (len(means) - 1)), ratio


def assert_covers(est, exact, label=""):
    """`exact` lies in `est`'s interval of level 1 - 1e-4 (about 3.9 standard errors for a
    normal error bar; Student's t of the error bar's `dof` where it has few)."""
    low, high = (np.asarray(b) for b in est.interval(1 - 1e-4))
    assert np.all((low <= exact) & (exact <= high)), (label, est, getattr(est, "pilot", None))


def auto_against(f, exact, lo, hi, n, chosen, other, keys=range(4)):
    """`integrate`'s default against `method=other` on the same keys: asserts that each
    default run chose `chosen` and is within 5 of its standard errors; returns both RMS
    errors, and the default runs."""
    errors, runs = {"auto": [], other: []}, []
    for k in keys:
        key = jax.random.key(k)
        est = jaxmc.integrate(key, f, lo, hi, n=n)
        assert est.method == chosen, est.pilot
        assert_covers(est, exact, k)
        errors["auto"].append(float(est.mean) - exact)
        runs.append(est)
        alone = jaxmc.integrate(key, f, lo, hi, n=n, method=other)
        errors[other].append(float(alone.mean) - exact)
    return {m: np.sqrt(np.mean(np.square(e))) for m, e in errors.items()}, runs


def importance(key, f, proposal, n):
    """`jaxmc.importance` as one compiled program (eagerly, its sampler dispatches op by op),
    with the `ReliabilityWarning` it gives outside `jit` (the suite turns it into an error)."""
    est = _compiled_importance(key, f, proposal, n)
    warn_if_unreliable(est, "importance")
    return est


@eqx.filter_jit
def per_sample_variance(key, f, proposal, n):
    """Variance of one sample of f/p (what the estimator's variance is, times n)."""
    return jaxmc.importance(key, f, proposal, n).variance * n


# --------------------------------------------------------------------------------------
# Integrands with known integrals


# A vector-valued smooth integrand on the box [0,1]x[0,2] and its integral.
SMOOTH2_LO, SMOOTH2_HI = jnp.zeros(2), jnp.array([1.0, 2.0])
SMOOTH2 = np.array([(np.e - 1) * (1 - np.exp(-2)), (np.cos(2) + np.cos(3) - np.cos(5) - 1) / 3])


def smooth2(x):
    return jnp.stack([jnp.exp(x[0] - x[1]), jnp.cos(3 * x[0] + x[1])])


def tilted(a):
    """$f_a(x) = e^{a x_0 - x_1}$ on [0,1]x[0,2]: a parameter for gradients to follow."""
    return lambda x: jnp.exp(a * x[0] - x[1])


def tilted_da(a):
    r"""$\partial f_a / \partial a = x_0 e^{a x_0 - x_1}$."""
    return lambda x: x[0] * jnp.exp(a * x[0] - x[1])


def tilted_da_integral(a):
    r"""$\frac{d}{da} \int_{[0,1]\times[0,2]} f_a = \frac{e^a (a - 1) + 1}{a^2} (1 - e^{-2})$."""
    return (np.exp(a) * (a - 1) + 1) / a**2 * (1 - np.exp(-2))


def cos_product(x):
    r"""$\prod_j \cos x_j$: its integral over $[0,1]^d$ is $\sin(1)^d$."""
    return jnp.prod(jnp.cos(x))


def peak(d, centre=0.3, s=0.05):
    """A normalised Gaussian of width `s` at `centre` (integral 1 on [0,1]^d up to ~1e-9)."""
    c = jnp.full((d,), centre)
    return lambda x: jnp.exp(-jnp.sum((x - c) ** 2) / (2 * s * s)) / (2 * jnp.pi * s * s) ** (d / 2)


def box(d):
    """The unit cube $[0,1]^d$ as `(lo, hi)`."""
    return jnp.zeros(d), jnp.ones(d)


def midpoint_grid(lo, hi, m):
    """Midpoints of an `m x m` grid on the 2-D box `[lo, hi]`, and the cell area."""
    lo, hi = np.asarray(lo), np.asarray(hi)
    axes = [lo[j] + (hi[j] - lo[j]) * (np.arange(m) + 0.5) / m for j in range(2)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
    return jnp.asarray(pts), float(np.prod((hi - lo) / m))


@contextlib.contextmanager
def compilations():
    """The list of XLA compilations JAX logs inside the block."""
    messages = []

    class Record(logging.Handler):
        def emit(self, record):
            if record.getMessage().startswith("Compiling "):
                messages.append(record.getMessage())

    handler = Record()
    loggers = [logging.getLogger(name) for name in ("jax._src.interpreters.pxla", "jax._src.dispatch")]
    for logger in loggers:
        logger.addHandler(handler)
    try:
        with jax.log_compiles():
            yield messages
    finally:
        for logger in loggers:
            logger.removeHandler(handler)


def persistently_cached(name: str) -> bool:
    """Whether the run's persistent compilation cache (tests/conftest.py) holds a program
    compiled from a function called `name` (JAX names an entry after the jitted function):
    JAX does not store a program that holds a host callback."""
    cache = pathlib.Path(os.environ["JAXMC_TEST_XLA_CACHE"])
    return any(name in entry.name for entry in cache.iterdir())
