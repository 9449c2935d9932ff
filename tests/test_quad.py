"""Deterministic quadrature baselines: exactness, error orders, tensor products, transforms."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmc import quad


LO, HI = -0.3, 1.7  # an asymmetric interval, so odd-degree terms do not cancel
RULES = {
    "midpoint": quad.midpoint,
    "trapezoid": quad.trapezoid,
    "simpson": quad.simpson,
    "gauss_legendre": quad.gauss_legendre,
}


def nodes_per_axis(name, n):
    return n + 1 if name in ("trapezoid", "simpson") else n


def exact_degree(name, n):
    return {"midpoint": 1, "trapezoid": 1, "simpson": 3, "gauss_legendre": 2 * n - 1}[name]


def poly_integral(coef, lo, hi):
    """Exact integral of sum_k coef[k] x^k over [lo, hi]."""
    return sum(c * (hi ** (k + 1) - lo ** (k + 1)) / (k + 1) for k, c in enumerate(coef))


def poly(coef):
    return lambda x: sum(c * x**k for k, c in enumerate(coef))


def next_degree_error(name, n, lo, hi):
    """Rule minus integral for x^(p+1), p the degree of exactness.

    The error terms of all four rules involve only the (p+1)-th derivative,
    which is the constant (p+1)! for x^(p+1), so these are exact values, not
    bounds.
    """
    h = (hi - lo) / n
    if name == "midpoint":  # -(b-a) h^2 f''/24, f'' = 2
        return -(hi - lo) * h**2 / 12
    if name == "trapezoid":  # +(b-a) h^2 f''/12
        return (hi - lo) * h**2 / 6
    if name == "simpson":  # +(b-a) h^4 f''''/180, f'''' = 24
        return (hi - lo) * h**4 * 24 / 180
    # Gauss-Legendre: -(b-a)^(2n+1) (n!)^4 / ((2n+1) ((2n)!)^3) f^(2n), f^(2n) = (2n)!
    c = (hi - lo) ** (2 * n + 1) * math.factorial(n) ** 4
    c /= (2 * n + 1) * math.factorial(2 * n) ** 3
    return -c * math.factorial(2 * n)


EXACTNESS_CASES = [
    ("midpoint", 1),
    ("midpoint", 5),
    ("trapezoid", 1),
    ("trapezoid", 5),
    ("simpson", 2),
    ("simpson", 6),
] + [("gauss_legendre", n) for n in range(1, 7)]


@pytest.mark.parametrize("name, n", EXACTNESS_CASES)
def test_exact_up_to_degree(name, n):
    rule = RULES[name]
    p = exact_degree(name, n)
    coef = np.random.default_rng(p + 10 * n).normal(size=p + 1)
    exact = poly_integral(coef, LO, HI)
    got = rule(poly(coef), LO, HI, n)
    np.testing.assert_allclose(got, exact, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("name, n", EXACTNESS_CASES)
def test_not_exact_for_next_degree(name, n):
    # The teeth of the exactness test: one degree more and the error is the
    # rule's known (non-zero) error term.
    p = exact_degree(name, n) + 1
    exact = poly_integral([0.0] * p + [1.0], LO, HI)
    got = RULES[name](lambda x: x**p, LO, HI, n)
    expected_error = next_degree_error(name, n, LO, HI)
    assert abs(expected_error) > 1e-6 * abs(exact)
    np.testing.assert_allclose(got - exact, expected_error, rtol=1e-9)


# --- error bounds and orders on a smooth non-polynomial integrand -----------


@pytest.mark.parametrize(
    "name, n_values, constant",
    [
        # c in: rule - I = c (b - a) h^r f^(r)(xi), r = 2 or 4, for some xi in [a, b].
        ("midpoint", [4, 16, 64], -1 / 24),
        ("trapezoid", [4, 16, 64], 1 / 12),
        ("simpson", [2, 8, 32], 1 / 180),
    ],
)
def test_error_within_lecture_bound(name, n_values, constant):
    # The lecture's error formulas: error = constant (b-a) h^r f^(r)(xi) for some
    # xi, so for exp on [0, 1] the ratio error / (constant h^r) lies in [1, e].
    r = 4 if name == "simpson" else 2
    for n in n_values:
        err = float(RULES[name](jnp.exp, 0.0, 1.0, n)) - (math.e - 1)
        ratio = err / (constant * (1.0 / n) ** r)
        assert 1.0 <= ratio <= math.e, (n, ratio)


def test_gauss_legendre_error_within_bound():
    for n in range(1, 5):
        c = math.factorial(n) ** 4 / ((2 * n + 1) * math.factorial(2 * n) ** 3)
        err = (math.e - 1) - float(quad.gauss_legendre(jnp.exp, 0.0, 1.0, n))
        assert 1.0 <= err / c <= math.e, (n, err / c)


def _slope(name, ns, d):
    f = lambda x: jnp.exp(jnp.sum(x)) if d > 1 else jnp.exp(x)
    lo, hi = (jnp.zeros(d), jnp.ones(d)) if d > 1 else (0.0, 1.0)
    exact = (math.e - 1) ** d
    errors = [abs(float(RULES[name](f, lo, hi, n)) - exact) for n in ns]
    h = 1.0 / np.asarray(ns, dtype=float)
    return np.polyfit(np.log(h), np.log(errors), 1)[0]


@pytest.mark.parametrize("d", [1, 2])
@pytest.mark.parametrize(
    "name, ns, order",
    [
        ("midpoint", [8, 16, 32, 64], 2.0),
        ("trapezoid", [8, 16, 32, 64], 2.0),
        ("simpson", [4, 8, 16, 32], 4.0),
    ],
)
def test_error_order(name, ns, order, d):
    # Halving h divides the error by 2^order; in d dimensions that is still
    # n^-order per axis, i.e. N^(-order/d) in evaluations.
    slope = _slope(name, ns, d)
    assert abs(slope - order) < 0.15, slope


def test_gauss_legendre_converges_geometrically():
    errs = [
        abs(float(quad.gauss_legendre(jnp.cos, 0.0, 2.0, n)) - math.sin(2.0)) for n in (2, 3, 4, 5)
    ]
    # Each extra node gains at least two orders of magnitude for this analytic integrand.
    assert all(b < 1e-2 * a for a, b in zip(errs, errs[1:])), errs


# --- tensor products --------------------------------------------------------


def _vector_poly(p):
    """A vector-valued polynomial of degree p in each variable, and its integral."""

    def f(x):
        return jnp.stack([jnp.prod(x**p), jnp.sum(x**p), jnp.prod(1.0 + x), jnp.ones(())])

    def integral(lo, hi):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        w = hi - lo
        vol = np.prod(w)
        m_p = (hi ** (p + 1) - lo ** (p + 1)) / (p + 1)  # per-axis integral of x^p
        m_1 = w + (hi**2 - lo**2) / 2  # per-axis integral of 1 + x
        return np.array(
            [np.prod(m_p), sum(m_p[j] * vol / w[j] for j in range(len(w))), np.prod(m_1), vol]
        )

    return f, integral


BOX = {
    2: (np.array([-0.5, 1.0]), np.array([1.0, 2.5])),
    3: (np.array([0.0, -1.0, 2.0]), np.array([1.0, 0.5, 2.5])),
}


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize(
    "name, n", [("midpoint", 3), ("trapezoid", 3), ("simpson", 4), ("gauss_legendre", 3)]
)
def test_tensor_product_exact_vector_valued(name, n, d):
    p = exact_degree(name, n)
    lo, hi = BOX[d]
    f, integral = _vector_poly(p)
    got = RULES[name](f, jnp.asarray(lo), jnp.asarray(hi), n)
    assert got.shape == (4,)
    np.testing.assert_allclose(got, integral(lo, hi), rtol=1e-12)
    # One degree more along one axis and the rule is off by exactly the 1-D error
    # times the other axes' volume.
    q = p + 1
    got = RULES[name](lambda x: x[0] ** q, jnp.asarray(lo), jnp.asarray(hi), n)
    exact = (hi[0] ** (q + 1) - lo[0] ** (q + 1)) / (q + 1) * np.prod(hi[1:] - lo[1:])
    expected = next_degree_error(name, n, lo[0], hi[0]) * np.prod(hi[1:] - lo[1:])
    np.testing.assert_allclose(got - exact, expected, rtol=1e-9)


@pytest.mark.parametrize("name", RULES)
def test_tensor_product_of_separable_integrand_is_product_of_1d_rules(name):
    # Eq. 2 for f(x) = g(x0) h(x1) k(x2) factorises into three 1-D rules (eq. 1),
    # whatever the accuracy of each.
    g, h, k = jnp.exp, jnp.cos, lambda t: 1.0 / (1.0 + t**2)
    lo, hi = BOX[3]
    n = 6
    rule = RULES[name]
    f = lambda x: jnp.stack([g(x[0]) * h(x[1]) * k(x[2]), g(x[0])])
    got = rule(f, jnp.asarray(lo), jnp.asarray(hi), n)
    one_d = [rule(fn, lo[j], hi[j], n) for j, fn in enumerate((g, h, k))]
    np.testing.assert_allclose(got[0], one_d[0] * one_d[1] * one_d[2], rtol=1e-13)
    np.testing.assert_allclose(got[1], one_d[0] * np.prod(hi[1:] - lo[1:]), rtol=1e-13)


@pytest.mark.parametrize(
    "name, n", [("midpoint", 5), ("trapezoid", 5), ("simpson", 4), ("gauss_legendre", 5)]
)
def test_evaluation_count_and_nodes(name, n):
    seen = []

    def f(x):
        # The rule runs under jit: fetch the points with a callback.
        jax.debug.callback(lambda v: seen.append(np.asarray(v)), x)
        return jnp.sum(x, axis=1)

    lo, hi = BOX[2]
    RULES[name](f, jnp.asarray(lo), jnp.asarray(hi), n, batched=True)
    (x,) = seen
    m = nodes_per_axis(name, n)
    assert x.shape == (m**2, 2)
    assert len(np.unique(x, axis=0)) == m**2
    on_edges = np.isclose(x.min(0), lo).all() and np.isclose(x.max(0), hi).all()
    assert on_edges == (name in ("trapezoid", "simpson"))
    if name == "midpoint":
        np.testing.assert_allclose(x.min(0), lo + (hi - lo) / (2 * n))


@pytest.mark.parametrize("name", RULES)
def test_chunking_and_batched_agree(name):
    lo, hi = jnp.asarray(BOX[3][0]), jnp.asarray(BOX[3][1])
    f = lambda x: jnp.stack([jnp.exp(-jnp.sum(x**2)), jnp.sin(x[0]) * x[2]])
    n = 6
    whole = RULES[name](f, lo, hi, n)
    sizes = []

    def fb(x):
        sizes.append(x.shape)
        return jax.vmap(f)(x)

    # 10 does not divide the grid size, so the last chunk is padded.
    chunked = RULES[name](fb, lo, hi, n, batched=True, chunk=10)
    m = nodes_per_axis(name, n)
    assert sizes == [(10, 3)] and m**3 % 10 != 0
    np.testing.assert_allclose(chunked, whole, rtol=1e-13)


def test_scalar_bounds_give_scalar_points_and_output_shape():
    seen = []

    def f(x):
        seen.append(jnp.shape(x))
        return jnp.stack([x, x**2]) * jnp.ones((3, 1))

    out = quad.simpson(f, 0.0, 2.0, 4)
    assert seen == [()]
    assert out.shape == (3, 2)
    np.testing.assert_allclose(out, np.tile([2.0, 8.0 / 3.0], (3, 1)), rtol=1e-14)


def test_one_dimensional_box_matches_scalar_bounds():
    f = lambda x: jnp.cos(x)
    a = quad.gauss_legendre(lambda x: f(x[0]), jnp.array([0.2]), jnp.array([1.1]), 7)
    b = quad.gauss_legendre(f, 0.2, 1.1, 7)
    np.testing.assert_allclose(a, b, rtol=1e-15)


def test_float32_stays_accurate_over_many_points():
    lo32, hi32 = jnp.zeros(2, jnp.float32), jnp.ones(2, jnp.float32)
    f = lambda x: jnp.cos(x[0]) * jnp.cos(x[1])
    got = quad.trapezoid(f, lo32, hi32, 255, chunk=2**12)  # 2^16 evaluations in 16 chunks
    assert got.dtype == jnp.float32
    ref = quad.trapezoid(f, jnp.zeros(2), jnp.ones(2), 255)
    np.testing.assert_allclose(got, ref, rtol=2e-6)


# --- jit, vmap, grad --------------------------------------------------------


@pytest.mark.parametrize("use_jit", [False, True])
@pytest.mark.parametrize("name", RULES)
def test_jit_with_traced_bounds(name, use_jit):
    f = lambda x: jnp.stack([jnp.prod(jnp.cos(x)), jnp.sum(x)])
    run = lambda lo, hi: RULES[name](f, lo, hi, 8)
    lo, hi = jnp.asarray(BOX[2][0]), jnp.asarray(BOX[2][1])
    got = (jax.jit(run) if use_jit else run)(lo, hi)
    expected = RULES[name](f, BOX[2][0], BOX[2][1], 8)
    np.testing.assert_allclose(got, expected, rtol=1e-14)


@pytest.mark.parametrize("name", RULES)
def test_vmap_over_bounds_and_parameters(name):
    rule = RULES[name]
    n = 4
    p = exact_degree(name, n)
    his = jnp.linspace(0.5, 2.0, 5)
    got = jax.vmap(lambda b: rule(lambda x: x**p, 0.0, b, n))(his)
    np.testing.assert_allclose(got, his ** (p + 1) / (p + 1), rtol=1e-13)

    a = jnp.linspace(-1.0, 1.5, 4)
    got = jax.vmap(lambda ai: rule(lambda x: jnp.exp(ai * x), 0.0, 1.0, n))(a)
    # the same integrals as one vector-valued integrand
    all_at_once = rule(lambda x: jnp.exp(a * x), 0.0, 1.0, n)
    assert got.shape == all_at_once.shape == (4,)
    np.testing.assert_allclose(got, all_at_once, rtol=1e-14)


@pytest.mark.parametrize("name", RULES)
def test_grad_wrt_closed_over_parameter(name):
    # The rule is linear in f, so d/da rule(exp(a x)) = rule(x exp(a x)) exactly.
    rule = RULES[name]
    a = 0.7
    grad = jax.grad(lambda a: rule(lambda x: jnp.exp(a * x), 0.0, 1.0, 16))(a)
    np.testing.assert_allclose(grad, rule(lambda x: x * jnp.exp(a * x), 0.0, 1.0, 16), rtol=1e-13)


def test_grad_matches_analytic_derivative():
    # d/da int_0^1 exp(a x) dx = ((a - 1) e^a + 1) / a^2
    a = np.array([-0.8, 0.7, 2.0])
    rule = lambda a: quad.gauss_legendre(lambda x: jnp.exp(a * x), 0.0, 1.0, 12)
    grad = jax.vmap(jax.grad(rule))(jnp.asarray(a))
    np.testing.assert_allclose(grad, ((a - 1) * np.exp(a) + 1) / a**2, rtol=1e-13)
    # and in 2-D through a vector of parameters: d/dc_j int prod exp(c_j x_j)
    c = jnp.array([0.5, -1.2])
    g = jax.grad(
        lambda c: quad.simpson(lambda x: jnp.exp(jnp.dot(c, x)), jnp.zeros(2), jnp.ones(2), 64)
    )(c)
    one = lambda a: (math.exp(a) - 1) / a
    d_one = lambda a: ((a - 1) * math.exp(a) + 1) / a**2
    expected = [d_one(0.5) * one(-1.2), one(0.5) * d_one(-1.2)]
    np.testing.assert_allclose(g, expected, rtol=1e-7)


def test_grad_wrt_bounds_is_fundamental_theorem():
    # For a polynomial the Gauss-Legendre rule equals the integral for every
    # (lo, hi), so its derivatives are f(hi) and -f(lo).
    f = lambda x: 1.0 - 2.0 * x + 3.0 * x**3
    g_lo, g_hi = jax.grad(lambda lo, hi: quad.gauss_legendre(f, lo, hi, 2), argnums=(0, 1))(
        -0.4, 1.3
    )
    np.testing.assert_allclose(g_hi, f(1.3), rtol=1e-13)
    np.testing.assert_allclose(g_lo, -f(-0.4), rtol=1e-13)


# --- bad input --------------------------------------------------------------


@pytest.mark.parametrize("name", RULES)
@pytest.mark.parametrize(
    "lo, hi",
    [(1.0, 1.0), (2.0, 1.0), (jnp.array([0.0, 1.0]), jnp.array([1.0, 1.0])), (0.0, jnp.inf)],
)
def test_bad_bounds(name, lo, hi):
    with pytest.raises(ValueError, match="`lo`"):
        RULES[name](lambda x: x, lo, hi, 4)


@pytest.mark.parametrize("name", RULES)
@pytest.mark.parametrize(
    "lo, hi",
    [
        (jnp.zeros(2), jnp.ones(3)),
        (0.0, jnp.ones(2)),
        (jnp.zeros((2, 2)), jnp.ones((2, 2))),
        (jnp.zeros(0), jnp.ones(0)),
    ],
)
def test_mismatched_or_malformed_shapes(name, lo, hi):
    with pytest.raises(ValueError, match="`lo` and `hi`"):
        RULES[name](lambda x: x, lo, hi, 4)


@pytest.mark.parametrize("name", RULES)
@pytest.mark.parametrize("n", [0, -2])
def test_n_below_one(name, n):
    with pytest.raises(ValueError, match="`n` must be >= 1"):
        RULES[name](lambda x: x, 0.0, 1.0, n)


@pytest.mark.parametrize("name", RULES)
@pytest.mark.parametrize("n", [4.0, "4", True, None, jnp.array(4.0)])
def test_n_not_an_int(name, n):
    with pytest.raises(TypeError, match="`n`"):
        RULES[name](lambda x: x, 0.0, 1.0, n)


def test_n_accepts_numpy_int():
    np.testing.assert_allclose(
        quad.simpson(lambda x: x**3, 0.0, 1.0, np.int64(2)), 0.25, rtol=1e-15
    )


def test_traced_n_is_rejected():
    with pytest.raises(TypeError, match="`n`"):
        jax.jit(lambda n: quad.midpoint(lambda x: x, 0.0, 1.0, n))(4)


@pytest.mark.parametrize("n", [1, 3, 7])
def test_simpson_needs_even_n(n):
    with pytest.raises(ValueError, match="`n` must be even"):
        quad.simpson(lambda x: x, 0.0, 1.0, n)


@pytest.mark.parametrize("name", RULES)
def test_not_callable(name):
    with pytest.raises(TypeError, match="`f` must be callable"):
        RULES[name](1.0, 0.0, 1.0, 4)


@pytest.mark.parametrize("name", RULES)
def test_too_many_evaluations_is_refused_before_evaluating(name):
    calls = []
    f = lambda x: calls.append(1) or jnp.sum(x)
    with pytest.raises(ValueError, match="MAX_EVALUATIONS"):
        RULES[name](f, jnp.zeros(9), jnp.ones(9), 10)
    assert not calls


def test_evaluation_limit_is_inclusive(monkeypatch):
    monkeypatch.setattr(quad, "MAX_EVALUATIONS", 100)
    assert quad.midpoint(lambda x: jnp.sum(x), jnp.zeros(2), jnp.ones(2), 10) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="11\\^2 = 121"):
        quad.midpoint(lambda x: jnp.sum(x), jnp.zeros(2), jnp.ones(2), 11)


def test_bad_chunk_and_batched():
    with pytest.raises(ValueError, match="`chunk`"):
        quad.midpoint(lambda x: x, 0.0, 1.0, 4, chunk=0)
    with pytest.raises(TypeError, match="`batched`"):
        quad.midpoint(lambda x: x, 0.0, 1.0, 4, batched="yes")
    with pytest.raises(ValueError, match="batched=True"):
        quad.midpoint(lambda x: jnp.sum(x), 0.0, 1.0, 4, batched=True)


def test_no_retrace_for_same_integrand_and_new_bounds():
    traces = []

    def f(x):
        traces.append(1)  # runs once per trace, not per evaluation
        return jnp.sin(x)

    first = quad.gauss_legendre(f, 0.0, 1.0, 5)
    second = quad.gauss_legendre(f, 0.5, 2.0, 5)
    assert len(traces) == 1
    np.testing.assert_allclose(first, 1 - np.cos(1.0), rtol=1e-9)
    np.testing.assert_allclose(second, np.cos(0.5) - np.cos(2.0), rtol=1e-9)
