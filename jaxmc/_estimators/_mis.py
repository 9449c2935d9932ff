r"""Multiple importance sampling: the multi-sample and one-sample models.

Formulas as in Veach's thesis, ch. 9 (E. Veach, *Robust Monte Carlo Methods for Light
Transport Simulation*, Stanford 1997) and Veach & Guibas, "Optimally Combining Sampling
Techniques for Monte Carlo Rendering" (SIGGRAPH 1995).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import (
    check_callable,
    check_choice,
    check_count,
    check_key,
    is_concrete,
)
from .._integrand import bind, evaluate, ratio
from .._stats import Estimate, diagnosed, estimate_iid, moments, tail_of
from ..proposals import check_proposal
from ._mis_weights import HEURISTICS, mis_weights, safe_log


def _check_proposals(proposals: Any) -> list:
    if isinstance(proposals, (str, bytes)) or not isinstance(proposals, Sequence):
        raise TypeError(
            "`proposals` must be a sequence (list or tuple) of proposals, "
            f"got {type(proposals).__name__}."
        )
    proposals = list(proposals)
    if not proposals:
        raise ValueError("`proposals` must contain at least one proposal, got an empty sequence.")
    return [check_proposal(p, f"proposals[{k}]") for k, p in enumerate(proposals)]


def _check_beta(beta: Any, heuristic: str) -> Any:
    if heuristic == "power" and is_concrete(beta):
        b = np.asarray(beta)
        if b.shape != () or not np.isfinite(b) or not b > 0:
            raise ValueError(f"`beta` must be a finite number > 0, got {beta!r}.")
    return beta


def _pdf_matrix(proposals: list, x: jax.Array) -> jax.Array:
    """`P[l, i] = p_l(x_i)`, shape `(s, n)`."""
    n = x.shape[0]
    rows = []
    for k, q in enumerate(proposals):
        p = jnp.asarray(q.pdf(x))
        if p.shape != (n,):
            raise ValueError(
                f"`proposals[{k}].pdf` must map a batch of {n} points to shape ({n},), "
                f"got {p.shape}."
            )
        rows.append(p)
    return jnp.stack(rows)


def mis(
    key: jax.Array,
    f: Callable,
    proposals: Sequence[Any],
    counts: Sequence[int] | int,
    *,
    heuristic: str = "balance",
    beta: float = 2.0,
    batched: bool = False,
    args: Any = None,
) -> Estimate:
    r"""Multiple importance sampling, multi-sample model (Veach, §9.2).

    Draw $n_k$ = `counts[k]` points $X_{k,i}$ from each of the $s$ proposals $p_k$
    and combine them with weights $w_k$ that sum to one at every $x$:

    $$\hat I_{\rm MIS} = \sum_{k=1}^s \frac1{n_k}\sum_{i=1}^{n_k}
      w_k(X_{k,i})\,\frac{f(X_{k,i})}{p_k(X_{k,i})}.$$

    - `heuristic="balance"`: $w_k = n_k p_k / \sum_l n_l p_l$, so each term is
      $f / \sum_l (n_l/n_k) p_l$. With equal counts this is
      $w_k = p_k / \sum_l p_l$.
    - `heuristic="power"`: $w_k = (n_k p_k)^\beta / \sum_l (n_l p_l)^\beta$
      (β = `beta`, default 2; β = 1 is the balance heuristic).

    Unbiased whenever, wherever $f \ne 0$, some $p_k > 0$. The techniques are
    independent, so the variance is $\sum_k s_k^2 / n_k$ with $s_k^2$ the sample
    variance of technique $k$'s weighted terms (`inf` if some $n_k = 1$).

    **Arguments:**

    - `key`: a PRNG key.
    - `f`: the integrand, written for one point.
    - `proposals`: a sequence of proposals (`sample(key, n) -> (x, pdf)` and
      batched `pdf(x)`) on the same space.
    - `counts`: samples per proposal, a sequence of static ints (or one int for all).
    - `heuristic`: `"balance"` or `"power"`.
    - `beta`: the power heuristic's exponent (> 0).
    - `batched`: if True, `f` receives all $\sum_k n_k$ points at once.
    - `args`: parameters of `f` (any pytree); if given, `f` is called as `f(x, args)`.

    **Returns:** an `Estimate` with `n = Σ counts` integrand evaluations (each
    proposal's `pdf` is evaluated at every point).
    """
    key = check_key(key)
    f = bind(check_callable(f), args)
    proposals = _check_proposals(proposals)
    s = len(proposals)
    if isinstance(counts, (tuple, list)):
        if len(counts) != s:
            raise ValueError(
                f"`counts` must have one entry per proposal ({s}), got {len(counts)}: {counts!r}."
            )
        counts = tuple(check_count(c, f"counts[{k}]") for k, c in enumerate(counts))
    else:
        counts = (check_count(counts, "counts"),) * s
    heuristic = check_choice(heuristic, "heuristic", HEURISTICS)
    beta = _check_beta(beta, heuristic)

    keys = jax.random.split(key, s)
    xs, own = [], []
    for k, (q, nk) in enumerate(zip(proposals, counts)):
        x, p = q.sample(keys[k], nk)
        x, p = jnp.asarray(x), jnp.asarray(p)
        if x.shape[:1] != (nk,) or p.shape != (nk,):
            raise ValueError(
                f"`proposals[{k}].sample(key, {nk})` must return x of shape ({nk}, ...) and "
                f"pdf of shape ({nk},), got {x.shape} and {p.shape}."
            )
        if xs and x.shape[1:] != xs[0].shape[1:]:
            raise ValueError(
                f"all proposals must sample the same space: proposals[0] gives points of shape "
                f"{xs[0].shape[1:]}, proposals[{k}] gives {x.shape[1:]}."
            )
        xs.append(x)
        own.append(p)
    x_all = jnp.concatenate(xs)
    fx = evaluate(f, x_all, batched)
    pdfs = _pdf_matrix(proposals, x_all)  # (s, N)
    n_vec = jnp.asarray(counts, dtype=pdfs.dtype)[:, None]
    scaled = n_vec * pdfs

    mean = 0.0
    variance = 0.0
    n_bad = jnp.zeros((), jnp.int32)
    contributions = []
    start = 0
    for k, nk in enumerate(counts):
        sl = slice(start, start + nk)
        start += nk
        fk = fx[sl]
        if heuristic == "balance":
            # w_k f / p_k = f / (Σ_l n_l p_l / n_k); the sampled pdf stands in for p_k(x).
            others = jnp.sum(jnp.delete(scaled[:, sl], k, axis=0, assume_unique_indices=True), axis=0)
            denom = (others + nk * own[k]) / nk
            y, bad = ratio(fk, denom)
        else:
            sc = scaled[:, sl].at[k].set(nk * own[k])
            w = mis_weights(sc, heuristic, beta, technique=k)
            y, bad = ratio(fk * w.reshape(w.shape + (1,) * (fk.ndim - 1)), own[k])
        mom = moments(y)
        contributions.append(y * (sum(counts) / nk))  # so that the mean is their sum / N
        mean = mean + mom.mean
        variance = variance + (mom.m2 / (nk - 1) / nk if nk > 1 else jnp.inf)
        n_bad = n_bad + jnp.sum(bad, dtype=jnp.int32)
    return Estimate(**diagnosed(
        mean,
        jnp.asarray(variance * jnp.ones_like(mean), mean.dtype),
        jnp.asarray(sum(counts), dtype=jnp.int32),
        n_bad,
        tail_of(jnp.concatenate(contributions)),
    ))


def _check_probs(probs: Any, s: int) -> jax.Array:
    arr = jnp.asarray(probs)
    if arr.shape != (s,):
        raise ValueError(
            f"`probs` must have one entry per proposal, shape ({s},), got shape {arr.shape}."
        )
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        arr = arr.astype(jnp.result_type(float))
    if is_concrete(arr):
        a = np.asarray(arr, dtype=np.float64)
        if not np.all(np.isfinite(a)) or np.any(a < 0):
            raise ValueError(f"`probs` must be finite and >= 0, got {a}.")
        if abs(a.sum() - 1.0) > 1e-5:
            raise ValueError(f"`probs` must sum to 1, got sum {a.sum()} for {a}.")
    return arr


def mis_one_sample(
    key: jax.Array,
    f: Callable,
    proposals: Sequence[Any],
    probs: Any,
    n: int,
    *,
    heuristic: str = "balance",
    beta: float = 2.0,
    batched: bool = False,
    args: Any = None,
) -> Estimate:
    r"""Multiple importance sampling, one-sample model (Veach, §9.2.4).

    Each of the $n$ samples first picks a technique $I$ with probability
    $c_I$ = `probs[I]`, then draws $X \sim p_I$, and scores

    $$\hat I_{\rm MIS,\,single} = \frac{w_I(X)\, f(X)}{c_I\, p_I(X)}.$$

    - `heuristic="balance"`: $w_k = c_k p_k / \sum_l c_l p_l$, so the score is
      $f(X) / \sum_l c_l p_l(X)$ — with equal `probs` exactly
      $f(X_I) / (c_I \sum_l p_l(X_I))$. This is the optimal weighting for the
      one-sample model (Veach, Theorem 9.4).
    - `heuristic="power"`: $w_k = (c_k p_k)^\beta / \sum_l (c_l p_l)^\beta$.

    The samples are i.i.d., so the variance is $s^2/n$ (eq. 13). Shapes stay
    fixed: every proposal draws $n$ candidates and the chosen one is kept, so
    sampling costs $s\cdot n$ draws while $f$ is evaluated $n$ times.

    **Arguments:**

    - `key`: a PRNG key.
    - `f`: the integrand, written for one point.
    - `proposals`: a sequence of proposals on the same space.
    - `probs`: selection probabilities $c_k$, shape `(s,)`, $\ge 0$, summing to 1.
    - `n`: number of samples (static int).
    - `heuristic`, `beta`: as in `mis`.
    - `batched`: if True, `f` receives all `n` points at once.
    - `args`: parameters of `f` (any pytree); if given, `f` is called as `f(x, args)`.

    **Returns:** an `Estimate` with `n` evaluations.
    """
    key = check_key(key)
    f = bind(check_callable(f), args)
    proposals = _check_proposals(proposals)
    s = len(proposals)
    c = _check_probs(probs, s)
    n = check_count(n)
    heuristic = check_choice(heuristic, "heuristic", HEURISTICS)
    beta = _check_beta(beta, heuristic)

    key_choice, key_sample = jax.random.split(key)
    choice = jax.random.categorical(key_choice, safe_log(c), shape=(n,))
    keys = jax.random.split(key_sample, s)
    cand = []
    for k, q in enumerate(proposals):
        x, _ = q.sample(keys[k], n)
        x = jnp.asarray(x)
        if x.shape[:1] != (n,):
            raise ValueError(
                f"`proposals[{k}].sample(key, {n})` must return x of shape ({n}, ...), got {x.shape}."
            )
        if cand and x.shape != cand[0].shape:
            raise ValueError(
                f"all proposals must sample the same space: proposals[0] gives points of shape "
                f"{cand[0].shape[1:]}, proposals[{k}] gives {x.shape[1:]}."
            )
        cand.append(x)
    cand = jnp.stack(cand)  # (s, n, ...)
    x = cand[choice, jnp.arange(n)]
    fx = evaluate(f, x, batched)
    pdfs = _pdf_matrix(proposals, x)  # (s, n)
    scaled = c[:, None].astype(pdfs.dtype) * pdfs
    if heuristic == "balance":
        y, bad = ratio(fx, jnp.sum(scaled, axis=0))
    else:
        w = mis_weights(scaled, heuristic, beta)[choice, jnp.arange(n)]
        chosen = scaled[choice, jnp.arange(n)]
        y, bad = ratio(fx * w.reshape(w.shape + (1,) * (fx.ndim - 1)), chosen)
    return estimate_iid(y, bad)
