"""Fuzzing the estimators' shapes, bounds and dtypes: a right answer or a clear error, never a crash.

Each example draws a dimension (scalar bounds, 0..5), bounds (random, equal, reversed,
infinite, NaN, mismatched lengths, in several dtypes), a size (valid, zero, negative, huge,
not an int) and an integrand's output shape and dtype. The call must either return an
estimate of the right shape that is right (within 6 reported standard errors, plus
rounding) or that reports its non-finite values, or raise a `TypeError`/`ValueError`
naming the offending argument — never an exception from deep inside JAX.
"""

import functools
import math
import re
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import HealthCheck, event, given, settings, strategies as st

import jaxmc


KEY = jax.random.key(5)
# jaxmc's argument errors name the argument in backticks.
NAMED = re.compile(r"`(key|f|lo|hi|n|counts|counts\[\d\]|per_stratum|replicas|batched)`")
BUDGET = settings(
    max_examples=8, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck)
)


@functools.cache
def integrand(shape, dtype):
    """$c\\,(1 + \\sum_j x_j)$ broadcast to `shape` (c = 1, 2, ...), in `dtype`; integer
    outputs are the constant 2. One function per (shape, dtype), so compiles are reused."""
    scale = jnp.arange(1, math.prod(shape) + 1, dtype=jnp.float64).reshape(shape)

    def f(x):
        if jnp.issubdtype(dtype, jnp.integer):
            return jnp.full(shape, 2, dtype)
        return (scale * (1.0 + jnp.sum(x))).astype(dtype)

    return f


def exact(shape, dtype, lo, hi):
    """The integral of `integrand(shape, dtype)` over the box, and its magnitude scale."""
    lo, hi = np.atleast_1d(np.asarray(lo, np.float64)), np.atleast_1d(np.asarray(hi, np.float64))
    volume = np.prod(hi - lo)
    if np.issubdtype(dtype, np.integer):
        return np.full(shape, 2 * volume), 2 * volume
    scale = np.arange(1, math.prod(shape) + 1, dtype=np.float64).reshape(shape)
    size = volume * (1 + np.sum(np.maximum(np.abs(lo), np.abs(hi))))
    return scale * volume * (1 + np.sum((lo + hi) / 2)), scale * size


@st.composite
def boxes(draw):
    """`(lo, hi)`: usually a valid box (some huge), else equal, reversed, non-finite,
    random or mismatched bounds, as lists or float32/float64/int32 arrays."""
    d = draw(st.integers(-1, 5))  # -1: scalar bounds
    size = max(d, 1)
    coordinates = st.lists(st.floats(-1e3, 1e3, width=32), min_size=size, max_size=size)
    lo = np.array(draw(coordinates))
    widths = np.array(draw(st.lists(st.floats(0.0625, 10.0, width=32), min_size=size,
                                    max_size=size)))
    relation = draw(st.sampled_from(["above"] * 10 + ["huge"] * 2 + [
        "equal", "reversed", "random", "mismatched", "non-finite"]))
    hi = lo + widths
    if relation == "huge":  # fine in float64; in float32 the volume overflows
        lo, hi = lo - 1e30, hi + 1e30
    elif relation == "equal":
        hi = lo.copy()
    elif relation == "reversed":
        hi = lo - widths
    elif relation == "random":
        hi = np.array(draw(coordinates))
    elif relation == "mismatched":
        hi = np.append(hi, 1.0)
    elif relation == "non-finite":
        side = draw(st.sampled_from([lo, hi]))
        side[draw(st.integers(0, size - 1))] = draw(st.sampled_from([math.inf, -math.inf, math.nan]))
    kind = draw(st.sampled_from(["list", "float32", "float64", "int32"]))
    if kind == "int32":  # integer bounds: rounded apart
        lo = np.floor(np.nan_to_num(lo, posinf=1e3, neginf=-1e3)).clip(-1e3, 1e3)
        hi = np.floor(np.nan_to_num(hi, posinf=1e3, neginf=-1e3)).clip(-1e3, 1e3) + 1
    if d == -1:
        lo, hi = lo[0], hi[0]
    elif d == 0:
        lo, hi = lo[:0], hi[:0]
    if kind == "list":
        return np.asarray(lo).tolist(), np.asarray(hi).tolist()
    return jnp.asarray(lo, kind), jnp.asarray(hi, kind)


outputs = st.tuples(st.sampled_from([(), (2,), (2, 3)]),
                    st.sampled_from([jnp.float32, jnp.float64, jnp.int32]))
bad_sizes = st.sampled_from([0, -3, 2**31, 2**40, 8.0, "8", None])


def sizes(valid):
    """Mostly `valid`, else a size that must be refused."""
    return st.one_of(st.just(valid), st.just(valid), st.just(valid), bad_sizes)


def check(call, box, output):
    """Run `call`; a result must be right (or report non-finite values), an error clear."""
    shape, dtype = output
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", jaxmc.ReliabilityWarning)
            est = call(integrand(shape, dtype), *box)
    except (TypeError, ValueError) as error:
        assert NAMED.search(str(error)), f"unclear {type(error).__name__}: {error}"
        event(f"{type(error).__name__} naming {NAMED.search(str(error)).group(0)}")
        return
    except FloatingPointError as error:  # integrate's documented non-finite error
        assert "nonfinite='drop'" in str(error)
        return
    mean, stderr = np.asarray(est.mean, np.float64), np.asarray(est.stderr, np.float64)
    assert mean.shape == shape
    if int(est.n_nonfinite):  # documented: counted, not hidden
        event("non-finite values counted")
        return
    truth, scale = exact(shape, dtype, *box)
    assert np.all(np.isfinite(mean)) and np.all(stderr >= 0)
    tolerance = 6 * stderr + 1e-3 * np.abs(scale)
    assert np.all(np.abs(mean - truth) <= tolerance), (mean, truth, stderr)
    event(f"right answer, d={np.size(box[0])}, output {shape} {np.dtype(dtype).name}")


@BUDGET
@given(box=boxes(), output=outputs, n=sizes(256))
def test_fuzz_integrate(box, output, n):
    check(lambda f, lo, hi: jaxmc.integrate(KEY, f, lo, hi, n=n), box, output)


@BUDGET
@given(box=boxes(), output=outputs, n=sizes(64))
def test_fuzz_uniform(box, output, n):
    check(lambda f, lo, hi: jaxmc.uniform(KEY, f, lo, hi, n), box, output)


@BUDGET
@given(box=boxes(), output=outputs, n=sizes(16),
       replicas=st.sampled_from([8, 8, 8, 8, 0, 2**30]))
def test_fuzz_randomized_qmc(box, output, n, replicas):
    check(lambda f, lo, hi: jaxmc.randomized_qmc(KEY, f, lo, hi, n, replicas=replicas), box, output)


@BUDGET
@given(box=boxes(), output=outputs, per_axis=sizes(2),
       per_stratum=st.sampled_from([2, 2, 2, 2, 1, 0, 2**31]))
def test_fuzz_stratified(box, output, per_axis, per_stratum):
    def call(f, lo, hi):
        d = np.size(lo)
        counts = per_axis if np.ndim(lo) == 0 else (per_axis,) * d
        return jaxmc.stratified(KEY, f, lo, hi, counts, per_stratum=per_stratum)

    check(call, box, output)
