"""`Auto`: the race on stub figures, the figures themselves, and the whole method's behaviour
(unbiased, the same eagerly and under `jit`, better than its baseline, plans that stream at
once)."""

import re
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import erf

import jaxmc
from jaxmc._auto._figures import Figure, iid_figure
from jaxmc._auto._nets import NetFigures, net_values, nets_figures, product_outlook, qmc_figure
from jaxmc._auto._race import (
    ADAPTIVE,
    GRID_QMC,
    IMPORTANCE,
    choose,
    grid_can_win,
    mixture_can_win,
    pooled_any,
)
from jaxmc.methods import Auto

from .helpers import (
    assert_covers,
    assert_unbiased_and_honest,
    box,
    compilations,
    cos_product,
    peak,
    persistently_cached,
)


COSTS = np.asarray(Auto().costs)


def _figure(value, log_sd=0.1):
    return Figure(jnp.asarray(value, float), jnp.asarray(log_sd, float))


def _nets(qmc, plain, outlook, *, log_sd=0.1, blind=False, heavy=False):
    return NetFigures(_figure(qmc, log_sd), _figure(plain, log_sd), jnp.asarray(heavy),
                      jnp.asarray(blind), _figure(outlook, log_sd))


# ----------------------------------------------------------------------------------------
# The race, on stub figures


def test_the_cheapest_candidate_per_unit_of_variance_wins():
    costs = np.asarray([1.0, 5.0, 3.0, 15.0])
    figures = Figure(jnp.asarray([1.0, 0.1, 0.5, 0.01]), jnp.full(4, 0.1))
    # Costs 1, 0.5, 1.5, 0.15: the mixture.
    assert int(choose(figures, costs, jnp.zeros(4, bool))) == IMPORTANCE
    # An unmeasured candidate (inf) never wins; nor a blind one against one that saw f.
    figures = Figure(jnp.asarray([1.0, 0.1, 0.2, jnp.inf]), jnp.full(4, 0.1))
    assert int(choose(figures, costs, jnp.zeros(4, bool))) == ADAPTIVE
    blind = jnp.asarray([False, True, False, False])
    assert int(choose(figures, costs, blind)) == GRID_QMC
    # If none saw anything, the grid, which kept looking as it trained.
    assert int(choose(figures, costs, jnp.ones(4, bool))) == ADAPTIVE


def test_a_stage_runs_while_one_of_its_candidates_can_win():
    z, price = 2.0, 1.5
    # QMC gains 1e4 over plain MC, a product density 2x: neither the grid alone (costlier by
    # far) nor QMC through it (it would gain over QMC what the density gains over uniform, 2x,
    # less than its cost and the stage's price) can win.
    assert not bool(grid_can_win(_nets(1e-4, 1.0, 0.5), COSTS, price, z))
    # A density that gains 100x: QMC through the grid could.
    assert bool(grid_can_win(_nets(1e-4, 1.0, 0.01), COSTS, price, z))
    # QMC no better than plain MC, the density 2x: the grid alone could.
    assert bool(grid_can_win(_nets(1.0, 1.0, 0.2), COSTS, price, z))
    # Uncertain figures widen the bounds: the same 2x density, read on so few points that it
    # may be 100x, keeps the stage.
    assert bool(grid_can_win(_nets(1e-4, 1.0, 0.5, log_sd=3.0), COSTS, price, z))
    # A higher price for the stage makes it less worth running.
    assert bool(grid_can_win(_nets(1e-4, 1.0, 0.1), COSTS, 1.0, z))
    assert not bool(grid_can_win(_nets(1e-4, 1.0, 0.1), COSTS, 10.0, z))
    # Nothing seen, a power-law tail, or no number: the stage runs.
    for flags in (dict(blind=True), dict(heavy=True)):
        assert bool(grid_can_win(_nets(1e-4, 1.0, 0.5, **flags), COSTS, price, z))
    assert bool(grid_can_win(_nets(np.nan, 1.0, 0.5), COSTS, price, z))


def test_the_mixture_is_measured_only_where_its_outlook_could_win():
    measured = Figure(jnp.asarray([1.0, 0.2, 0.5, jnp.inf]), jnp.full(4, 0.1))  # best: 1.0
    costs = np.asarray([1.0, 5.0, 3.0, 15.0])
    assert bool(mixture_can_win(jnp.asarray(0.05), costs, measured))  # 0.75 < 1
    assert not bool(mixture_can_win(jnp.asarray(0.1), costs, measured))  # 1.5


def test_under_vmap_the_decisions_are_pooled_over_the_batch():
    # Every element takes the same path: a stage runs if any element would run it, and the
    # winner minimises the geometric mean of the elements' costs (unbatched outputs: vmap's
    # `out_axes=None` accepts nothing else).
    flags = jnp.asarray([False, True, False])
    assert not bool(pooled_any(flags[0]))
    assert bool(jax.vmap(pooled_any, out_axes=None)(flags))
    costs = np.ones(4)
    values = jnp.asarray([[1.0, 2.0, jnp.inf, jnp.inf], [1.0, 0.1, jnp.inf, jnp.inf]])
    figures = Figure(values, jnp.ones_like(values))
    chosen = jax.vmap(lambda f: choose(f, costs, jnp.zeros(4, bool)), out_axes=None)(figures)
    assert int(chosen) == ADAPTIVE  # sqrt(2 * 0.1) < 1


# ----------------------------------------------------------------------------------------
# The figures


def test_qmc_figure_fits_the_rate_of_its_nets():
    # Projected 2x beyond the pilot's nets, a smooth integrand's figure falls at scrambled
    # nets' rate (variance near n^-3, r = 2), a 4-D peak the nets cannot resolve at plain
    # Monte Carlo's (r = 0).
    def rate(f, d, seed):
        lo, hi = box(d)
        y, _ = net_values(jax.random.key(seed), lo, hi, f, False, 0, 4, 8)
        return float(np.log2(qmc_figure(y, 1.0).value / qmc_figure(y, 2.0).value))

    assert np.median([rate(cos_product, 2, seed) for seed in range(5)]) > 1.5
    assert max(rate(peak(4, s=0.05), 4, seed) for seed in range(3)) < 0.5


def test_a_figures_uncertainty_is_what_it_varies_by():
    # Over 40 keys, the spread of a figure's logarithm is what its reported standard deviation
    # says (within 5 sigma of a chi-square band on 40 keys, and a factor 2 for the jackknife
    # and the delta method themselves): QMC's (projected 4x), and that of i.i.d. values.
    lo, hi = box(3)
    f = lambda x: jnp.exp(-jnp.sum((x - 0.4) ** 2) / 0.2)  # noqa: E731

    @jax.jit
    @jax.vmap
    def figures(key):
        y, _ = net_values(key, lo, hi, f, False, 0, 4, 7)
        plain, _ = iid_figure(jax.vmap(f)(jax.random.uniform(key, (4096, 3))))
        return qmc_figure(y, 4.0), plain

    qmc, plain = figures(jax.random.split(jax.random.key(0), 40))
    for figure in (qmc, plain):
        spread = np.std(np.log(np.asarray(figure.value)), ddof=1)
        reported = float(np.sqrt(np.mean(np.asarray(figure.log_sd) ** 2)))
        assert reported / 2.5 < spread < 2.5 * reported, (spread, reported)


@pytest.mark.filterwarnings("ignore::jaxmc.ReliabilityWarning")  # (the stream's bound: an upper one)
def test_qmc_is_credited_with_the_iid_bound_where_its_stream_reports_it():
    # (x0 + ... + x3)^-1.5: a power law at the corner (k = 3/8). QMC's stream reports the
    # i.i.d. bound, far above its replicas' spread, on every key; the pilot's nets credit
    # QMC with plain MC's figure on every key too (they did on none when the pilot asked for
    # k-hat above 1/4 by two standard errors, a stricter test than the stream's).
    corner = lambda x: jnp.sum(x) ** -1.5  # noqa: E731
    lo, hi = box(4)
    for seed in range(4):
        stream_key, pilot_key = jax.random.split(jax.random.key(seed))
        est = jaxmc.integrate(stream_key, corner, lo, hi, n=10**5, method="qmc")
        y, bins = net_values(pilot_key, lo, hi, corner, False, 0, 4, 7)
        nets = nets_figures(y, bins, 1.0)
        assert bool(est.conservative)
        assert float(nets.qmc.value) >= float(nets.plain.value)


def test_the_product_outlook_reads_what_a_product_density_can_do():
    # A product of one-dimensional factors: a product density fits it and its outlook is far
    # below plain Monte Carlo's figure. A function of x0 + x1 alone (no product): not.
    lo, hi = box(4)
    key = jax.random.key(1)
    product = lambda x: jnp.prod(jnp.exp(-((x - 0.3) ** 2) / 0.02))  # noqa: E731
    ridge = lambda x: jnp.exp(-((x[0] + x[1] - 1) ** 2) / 0.02)  # noqa: E731
    for f, gain in ((product, 20.0), (ridge, None)):
        y, bins = net_values(key, lo, hi, f, False, 0, 4, 8)
        outlook = product_outlook(bins, y)
        plain, _ = iid_figure(jnp.reshape(y, (-1,)))
        ratio = float(plain.value) / float(outlook.value)
        if gain:
            assert ratio > gain, ratio
        else:
            assert ratio < 3, ratio


# ----------------------------------------------------------------------------------------
# The method


PEAK2 = peak(2, s=0.03)  # one object: the runs below share its compiled programs


def _smooth_or_peak(x, peaked):
    """`cos_product`, or where `peaked` `PEAK2`: as `args`, one compiled program serves both."""
    return jnp.where(peaked, PEAK2(x), cos_product(x))


def test_auto_pilot_never_biases_the_result():
    # Under jit and vmap over keys (a pilot and a choice for each), over 120 keys the mean error
    # is within 5 of its standard errors and the error bars are honest, on a smooth integrand
    # and on a peak. (On the peak the batch streams QMC through the grid, whose values read
    # as a power-law tail on a third of the keys: there the stream reports the i.i.d. bound,
    # an upper bound, so the error bars are honest but not tight.)
    lo, hi = box(2)
    keys = jax.random.split(jax.random.key(3), 120)
    over_keys = jax.jit(jax.vmap(
        lambda k, peaked: jaxmc.integrate(k, _smooth_or_peak, lo, hi, n=2**15, args=peaked),
        in_axes=(0, None),
    ))
    for peaked, exact, honest in [(False, np.sin(1.0) ** 2, "equal"), (True, 1.0, "conservative")]:
        est = over_keys(keys, jnp.asarray(peaked))
        assert_unbiased_and_honest(est, exact, honest=honest)


def _correlated(d, sigma, rho):
    """A normalised Gaussian at the box's centre, correlation `rho` between every two axes."""
    cov = sigma**2 * ((1 - rho) * np.eye(d) + rho * np.ones((d, d)))
    precision = jnp.asarray(np.linalg.inv(cov))
    norm = 1 / np.sqrt((2 * np.pi) ** d * np.linalg.det(cov))
    return lambda x: norm * jnp.exp(-0.5 * (x - 0.5) @ precision @ (x - 0.5))


def _kinds():
    """Integrands whose pilots end at different stages: a smooth one that no product fits
    (QMC's early look), a round peak (the grid's stage), a correlated peak (the mixture's).
    `test_the_kinds_cover_every_stage` checks that they do."""
    smooth = lambda x: jnp.cos(0.6 * jnp.pi + 2.25 * jnp.sum(x))  # noqa: E731
    exact = np.cos(0.6 * np.pi + 4.5) * (np.sin(1.125) / 1.125) ** 4
    return {"smooth": (smooth, exact, 4, 2**15), "peak": (peak(3, s=0.05), 1.0, 3, 2**16),
            "correlated": (_correlated(3, 0.05, 0.9), 1.0, 3, 2**15)}


KINDS = _kinds()  # (one object per integrand: the tests share their compiled programs)


@pytest.mark.parametrize("kind", list(KINDS))
def test_eager_and_jit_give_the_same_estimate(kind):
    f, _, d, n = KINDS[kind]
    lo, hi = box(d)
    key = jax.random.key(11)
    eager = jaxmc.integrate(key, f, lo, hi, n=n)

    # (With every value finite, nonfinite="nan" returns what the default returns, and leaves
    # no host callback in the program: JAX's persistent cache then keeps it.)
    def run(k):
        return jaxmc.integrate(k, f, lo, hi, n=n, nonfinite="nan")

    run.__name__ = f"traced_auto_{kind}"
    traced = jax.jit(run)(key)
    assert persistently_cached(run.__name__)
    assert traced.method == "auto" and isinstance(traced.plan, jaxmc.methods.OneOf)
    assert int(traced.pilot.choice) == int(eager.pilot.choice)
    np.testing.assert_array_equal(traced.pilot.stages, eager.pilot.stages)
    assert int(traced.n) == int(eager.n)
    np.testing.assert_allclose(traced.mean, eager.mean, rtol=1e-12)
    np.testing.assert_allclose(traced.stderr, eager.stderr, rtol=1e-9)
    # The traced plan, returned concrete, streams as the eager one.
    again = [jaxmc.integrate(jax.random.key(1), f, lo, hi, n=n, method=plan)
             for plan in (eager.plan, traced.plan)]
    assert again[0].method == again[1].method == eager.method
    np.testing.assert_allclose(again[0].mean, again[1].mean, rtol=1e-12)


def test_the_kinds_cover_every_stage():
    # (So that the test above compares eager and traced runs through each stage.) Each
    # estimate covers its integral.
    stages = []
    for kind, (f, exact, d, n) in KINDS.items():
        est = jaxmc.integrate(jax.random.key(11), f, *box(d), n=n)
        stages.append(np.asarray(est.pilot.stages))
        assert_covers(est, exact, kind)
        assert int(est.n) <= n
    stages = np.asarray(stages)
    assert not np.all(stages[:, 1]) and np.all(np.any(stages, axis=0)), stages


def test_auto_beats_qmc_alone_on_a_narrow_peak_and_matches_it_on_a_smooth_integrand():
    # RMS errors over 6 keys at the same budget: on a narrow 4-D peak QMC's nets sample it as
    # plain MC does, and the grid-based winner is far more accurate; on a smooth integrand
    # auto's pilot costs at most a little.
    lo, hi = box(4)
    narrow = peak(4, s=0.02)

    def rms(f, exact, method):
        with warnings.catch_warnings():  # (QMC's nets barely see the peak, and say so)
            warnings.simplefilter("ignore", jaxmc.ReliabilityWarning)
            ests = [jaxmc.integrate(jax.random.key(s), f, lo, hi, n=100_000, method=method)
                    for s in range(6)]
        return np.sqrt(np.mean([(float(e.mean) - exact) ** 2 for e in ests]))

    assert rms(narrow, 1.0, "auto") < rms(narrow, 1.0, "qmc") / 10
    assert rms(cos_product, np.sin(1.0) ** 4, "auto") < 3 * rms(cos_product, np.sin(1.0) ** 4,
                                                                 "qmc")


def test_a_small_budget_runs_qmc_alone():
    lo, hi = box(2)
    est = jaxmc.integrate(jax.random.key(0), cos_product, lo, hi, n=2**12)
    assert est.method == "qmc" and est.pilot is None
    with pytest.raises(ValueError, match="`n` must be >= 16"):
        jaxmc.integrate(jax.random.key(0), cos_product, lo, hi, n=8)


# ----------------------------------------------------------------------------------------
# Plans


def test_a_plan_streams_at_once_without_a_pilot():
    # The plan of a run that trained a grid streams on it: no pilot, no training, nothing
    # compiled but the stream, the whole budget spent, the estimate honest over keys.
    lo, hi = box(3)
    f = peak(3, s=0.05)
    first = jaxmc.integrate(jax.random.key(0), f, lo, hi, n=2**16)
    assert first.plan.trained and first.plan.name == first.method
    with compilations() as compiled:
        again = jaxmc.integrate(jax.random.key(1), f, lo, hi, n=2**16, method=first.plan)
    names = {m.group(1) for m in (re.search(r"jit\((\w+)\)", c) for c in compiled) if m}
    # (The stream's programs: fused under `jit`, or its steps run one by one eagerly.)
    stream_programs = {"values", "stream", "edged", "context", "_points", "_moments",
                       "_accumulate", "_checked", "_estimate"}
    assert names <= stream_programs, names
    assert again.pilot is None and again.method == first.method
    assert int(again.n) > 0.9 * 2**16  # no pilot spent any of it
    keys = jax.random.split(jax.random.key(2), 64)
    runs = jax.jit(jax.vmap(lambda k: jaxmc.integrate(k, f, lo, hi, n=2**15,
                                                      method=first.plan)))(keys)
    assert_unbiased_and_honest(runs, 1.0)


def test_a_plan_serves_a_family_of_integrals_under_jit_and_vmap():
    # The plan of one member of a family (peaks of varying width, the width in `args`)
    # streams every member under jit(vmap): no pilot compiled, each estimate within 5 of its
    # standard errors of the closed form.
    lo, hi = box(2)

    def f(x, s):
        return jnp.exp(-jnp.sum((x - 0.5) ** 2) / (2 * s * s))

    widths = jnp.linspace(0.05, 0.12, 8)
    exact = np.asarray([2 * np.pi * w**2 * erf(0.5 / (np.sqrt(2) * w)) ** 2 for w in widths])
    plan = jaxmc.integrate(jax.random.key(0), f, lo, hi, n=2**16, args=widths[0]).plan
    family = jax.jit(jax.vmap(lambda s: jaxmc.integrate(jax.random.key(1), f, lo, hi, n=2**15,
                                                        method=plan, args=s)))
    with compilations() as compiled:
        est = family(widths)
    assert not any("net_values" in c or "run_adaptation" in c for c in compiled), compiled
    assert np.all(np.abs(np.asarray(est.mean) - exact) < 5 * np.asarray(est.stderr))


@pytest.mark.filterwarnings("ignore::jaxmc.ReliabilityWarning")  # (the values, not the flags)
@pytest.mark.parametrize("method", [jaxmc.methods.GridQMC(), jaxmc.methods.Adaptive(), "auto"],
                         ids=["grid_qmc", "adaptive", "auto"])
def test_under_vmap_a_method_gives_what_a_loop_gives_and_so_do_its_derivatives(method):
    # Under vmap a plan's (or `auto`'s pilot and) runs go element after element: the batch's
    # estimates are the loop's, its parameter given in `args` or closed over, and vmap of
    # grad is the loop's grads.
    lo, hi = box(2)

    def f(x, c):
        return jnp.exp(-jnp.sum((x - c) ** 2) / (2 * 0.08**2))

    plan = method if method == "auto" else jaxmc.integrate(
        jax.random.key(0), f, lo, hi, n=2**15, args=0.5, method=method).plan
    key, centres = jax.random.key(1), jnp.asarray([0.45, 0.5, 0.55])

    def by_args(c):
        return jaxmc.integrate(key, f, lo, hi, n=2**14, args=c, method=plan).mean

    def closed_over(c):
        return jaxmc.integrate(key, lambda x: f(x, c), lo, hi, n=2**14, method=plan).mean

    loop = np.asarray([by_args(c) for c in centres])
    batches = [jax.vmap(by_args), jax.vmap(closed_over)]
    if method != "auto":
        # (`auto` under `jit(vmap)` traces what `vmap` traces, and its whole pilot compiled
        # as one program costs a third of this test: eager and `jit` agree by
        # `test_eager_and_jit_give_the_same_estimate`.)
        batches.append(jax.jit(jax.vmap(by_args)))
    for batch in batches:
        np.testing.assert_allclose(np.asarray(batch(centres)), loop, rtol=1e-12)
    grads = np.asarray([jax.grad(by_args)(c) for c in centres])
    np.testing.assert_allclose(np.asarray(jax.vmap(jax.grad(by_args))(centres)), grads,
                               rtol=1e-10)
    np.testing.assert_allclose(np.asarray(jax.grad(lambda c: jnp.sum(jax.vmap(by_args)(c)))(
        centres)), grads, rtol=1e-10)


def test_a_plan_survives_serialisation(tmp_path):
    lo, hi = box(3)
    f = peak(3, s=0.05)
    plan = jaxmc.integrate(jax.random.key(0), f, lo, hi, n=2**16).plan
    eqx.tree_serialise_leaves(tmp_path / "plan.eqx", plan)
    like = jax.tree.map(jnp.zeros_like, plan)
    restored = eqx.tree_deserialise_leaves(tmp_path / "plan.eqx", like)
    a, b = (jaxmc.integrate(jax.random.key(5), f, lo, hi, n=2**15, method=p)
            for p in (plan, restored))
    assert float(a.mean) == float(b.mean) and float(a.stderr) == float(b.stderr)


def test_methods_are_objects_and_their_names_are_aliases():
    lo, hi = box(2)
    key = jax.random.key(0)
    for name, method in (("qmc", jaxmc.methods.QMC()), ("plain", jaxmc.methods.Plain()),
                         ("adaptive", jaxmc.methods.Adaptive())):
        by_name = jaxmc.integrate(key, cos_product, lo, hi, n=2**14, method=name)
        by_object = jaxmc.integrate(key, cos_product, lo, hi, n=2**14, method=method)
        assert by_name.method == by_object.method == name
        assert float(by_name.mean) == float(by_object.mean)
    # An option of the object changes what runs: more replicas, more degrees of freedom.
    five = jaxmc.integrate(key, cos_product, lo, hi, n=2**14,
                           method=jaxmc.methods.QMC(min_replicas=5))
    assert float(five.dof) > 2
    with pytest.raises(ValueError, match="jaxmc.methods"):
        jaxmc.integrate(key, cos_product, lo, hi, n=2**14, method="vegas")
    with pytest.raises(ValueError, match="costs"):
        jaxmc.methods.Auto(costs=(1.0, 2.0))


# ----------------------------------------------------------------------------------------
# Compilation


def test_a_new_integrand_compiles_only_what_evaluates_it():
    # The pilot's figures, EM's fits, the mixture's draws and the streams' points and moments
    # are compiled once per shape: a second integrand of the same dimension and budget, whose
    # pilot takes the same path (twice the first: every figure is relative, and doubling is
    # exact), compiles only the programs that evaluate it.
    lo, hi = box(3)
    f = _correlated(3, 0.05, 0.9)
    with warnings.catch_warnings():  # (a peak this narrow at 2^15 may read as a tail)
        warnings.simplefilter("ignore", jaxmc.ReliabilityWarning)
        first = jaxmc.integrate(jax.random.key(6), f, lo, hi, n=2**15)
        with compilations() as compiled:
            second = jaxmc.integrate(jax.random.key(6), lambda x: 2.0 * f(x), lo, hi, n=2**15)
    assert first.method == second.method and bool(first.pilot.stages[2]), first.pilot
    np.testing.assert_array_equal(first.pilot.stages, second.pilot.stages)
    names = {m.group(1) for m in (re.search(r"jit\((\w+)\)", c) for c in compiled) if m}
    # (Outside jit the streams, the grid's rounds and the pilot's nets are run step by step,
    # and only the integrand's values are compiled for a new integrand: `values`.)
    assert names <= {"values", "_modes", "mixture_values"}, names
    assert_covers(first, 1.0)
    np.testing.assert_allclose(second.mean, 2 * first.mean, rtol=1e-12)


# ----------------------------------------------------------------------------------------
# QMC


def genz_gaussian(d):
    """Genz's Gaussian $\\exp(-\\sum (x - 1/2)^2)$: smooth in any dimension."""
    return lambda x: jnp.exp(-jnp.sum((x - 0.5) ** 2))


def test_qmc_keeps_its_rate():
    # One growing net per replica: the error falls much faster than plain MC's n^-1/2.
    # Measured with fixed keys: at 2^14 -> 2^20 the rms error of cos_product (d=4) drops ~240x
    # (plain MC: 8x); here checked as more than 40x.
    lo, hi = box(4)
    exact = np.sin(1.0) ** 4

    def rms(n):
        ests = [jaxmc.integrate(jax.random.key(s), cos_product, lo, hi, n=n, method="qmc")
                for s in range(6)]
        errors = np.array([float(e.mean) - exact for e in ests])
        assert np.all(np.abs(errors) < 5 * np.array([float(e.stderr) for e in ests]))
        return np.sqrt(np.mean(errors**2))

    assert rms(2**14) / rms(2**20) > 40


def test_qmc_tolerance_is_checked_at_powers_of_two():
    lo, hi = box(3)
    est = jaxmc.integrate(jax.random.key(5), cos_product, lo, hi, rtol=1e-6, method="qmc")
    per_replica = int(est.n) // 8
    assert est.converged and per_replica & (per_replica - 1) == 0
    assert abs(est.mean - np.sin(1.0) ** 3) < 5 * est.stderr


def test_qmc_serves_smooth_integrands_beyond_twelve_dimensions():
    # No dimension cut-off: on a smooth 16-D integrand scrambled Sobol' beats plain MC by far.
    d = 16
    lo, hi = box(d)
    f, exact = genz_gaussian(d), (np.sqrt(np.pi) * erf(0.5)) ** d
    qmc = jaxmc.integrate(jax.random.key(6), f, lo, hi, n=2**18, method="qmc")
    plain = jaxmc.integrate(jax.random.key(6), f, lo, hi, n=2**18, method="plain")
    # Four nets of 2^16: the error bar has 3 degrees of freedom, so its t interval.
    assert qmc.dof == 3
    low, high = qmc.interval(1 - 1e-4)
    assert low <= exact <= high
    assert qmc.variance < plain.variance / 100


def test_auto_is_differentiable_with_a_fixed_budget():
    # Under grad the pilot's choice is traced as under jit; the estimate's derivative is that
    # of the chosen method: d/da of the integral of e^(a x) over [0, 1] is 1 at a = 1.
    key = jax.random.key(7)
    g = jax.grad(lambda a: jaxmc.integrate(key, lambda x: jnp.exp(a * x), 0.0, 1.0, n=2**16).mean)
    assert abs(float(g(1.0)) - 1.0) < 1e-4
