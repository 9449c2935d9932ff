r"""MIS weights: the balance and power heuristics (Veach's thesis, §9.2.1–9.2.3).

With techniques $l = 1..s$, densities $p_l$ and sample counts or selection
probabilities $c_l$, write $q_l = c_l\,p_l(x)$. The heuristics weight
technique $k$ by

$$ w_k^{\rm balance} = \frac{q_k}{\sum_l q_l}, \qquad
   w_k^{\rm power} = \frac{q_k^\beta}{\sum_l q_l^\beta}, $$

which sum to one wherever some $q_l > 0$. Used by `jaxmc.mis`,
`jaxmc.mis_one_sample` and the MIS strategies of `jaxmc.render`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp


HEURISTICS = ("balance", "power")
FORMS = ("log", "ratio")


def safe_log(p: jax.Array) -> jax.Array:
    """log p with log 0 = -inf and a finite (zero) gradient there."""
    pos = p > 0
    return jnp.where(pos, jnp.log(jnp.where(pos, p, 1.0)), -jnp.inf)


def _safe_div(num: jax.Array, den: jax.Array) -> jax.Array:
    """`num / den` where `den != 0`, else 0 (gradient-safe)."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _power_log(scaled: jax.Array, beta: Any) -> jax.Array:
    # w_k = exp(β log q_k - logsumexp_l β log q_l), shifted by the largest term.
    logs = beta * safe_log(scaled)
    top = jnp.max(logs, axis=0)
    top = jnp.where(jnp.isfinite(top), top, 0.0)
    e = jnp.exp(logs - top)
    total = jnp.sum(e, axis=0)
    return e / jnp.where(total > 0, total, 1.0)


def _power_ratio(rows: list[jax.Array], k: int, beta: Any) -> jax.Array:
    # w_k = 1 / (1 + Σ_{l≠k} (q_l/q_k)^β): no overflow for the large pdfs of tiny
    # lights and sharp lobes, and for two techniques the textbook 1 / (1 + r^β).
    own = rows[k]
    total = 1.0
    for other in rows[:k] + rows[k + 1 :]:
        total = total + _safe_div(other, own) ** beta
    return jnp.where(own > 0, 1.0 / total, 0.0)


def _balance(rows: list[jax.Array], k: int) -> jax.Array:
    total = rows[0]
    for other in rows[1:]:
        total = total + other
    return _safe_div(rows[k], total)


def mis_weights(
    scaled: jax.Array | Sequence[jax.Array],
    heuristic: str = "balance",
    beta: Any = 2.0,
    *,
    form: str = "log",
    technique: int | None = None,
) -> jax.Array:
    r"""Weights $w_k$ of $s$ techniques from their scaled densities $q_l = c_l p_l(x)$.

    **Arguments:**

    - `scaled`: $q_l$ for every technique, an array of shape `(s, ...)` or a
      sequence of `s` arrays that broadcast together.
    - `heuristic`: `"balance"` or `"power"`.
    - `beta`: the power heuristic's exponent $\beta > 0$ (a static int such as
      `2` keeps `q ** beta` a product).
    - `form`: how the power heuristic is computed. `"log"` (default) as a
      softmax of $\beta \log q_l$, finite for any $s$, any $\beta$ and zero
      densities; `"ratio"` as $1 / (1 + \sum_{l \ne k} (q_l/q_k)^\beta)$, with
      no logarithms. Both avoid overflow; they differ only in rounding. The
      balance heuristic has one form, $q_k / \sum_l q_l$ (0 where the sum is 0).
    - `technique`: the index $k$ of the one technique whose weight is wanted,
      or `None` for all of them.

    **Returns:** the weights, shape `(s, ...)`, or `...` for one `technique`.
    Where every $q_l$ is 0 all weights are 0.
    """
    if heuristic not in HEURISTICS:
        raise ValueError(f"`heuristic` must be one of {HEURISTICS}, got {heuristic!r}.")
    if form not in FORMS:
        raise ValueError(f"`form` must be one of {FORMS}, got {form!r}.")
    if heuristic == "power" and form == "log":
        if not isinstance(scaled, jax.Array):
            scaled = jnp.stack(jnp.broadcast_arrays(*scaled))
        weights = _power_log(scaled, beta)
        return weights if technique is None else weights[technique]
    rows = [scaled[k] for k in range(len(scaled))]
    if heuristic == "balance":
        weight = lambda k: _balance(rows, k)
    else:
        weight = lambda k: _power_ratio(rows, k, beta)
    if technique is not None:
        return weight(technique)
    return jnp.stack(jnp.broadcast_arrays(*[weight(k) for k in range(len(rows))]))
