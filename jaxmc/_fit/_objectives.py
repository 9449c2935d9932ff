r"""The objectives `fit` minimises, from per-sample $\log|f|$, $\log p_\theta$ and weights.

All are evaluated in log space (`logsumexp`), so they are scale-free and do not
overflow: the log second moment of $f/p$ (`"variance"`), Pearson's $\chi^2$,
and the forward and reverse KL divergences to $p_f = |f|/I$ (neural importance
sampling, Müller et al. 2019).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


OBJECTIVES = ("variance", "chi2", "kl", "reverse_kl")


def log_abs(fx: jax.Array) -> jax.Array:
    """$\\log |f|$ per sample (the Euclidean norm for array-valued `f`), safe at 0."""
    fx = jnp.reshape(fx, (fx.shape[0], -1))
    sq = jnp.sum(fx**2, axis=-1)
    ok = jnp.isfinite(sq) & (sq > 0)
    return jnp.where(ok, 0.5 * jnp.log(jnp.where(ok, sq, 1.0)), -jnp.inf)


def _wlse(a: jax.Array, w: jax.Array) -> jax.Array:
    """$\\log \\sum_i w_i e^{a_i}$ with $-\\infty$ terms allowed."""
    return jax.nn.logsumexp(a, b=w)


def objective_loss(objective: str, logf, log_p, w, log_q=None):
    r"""The objective from per-sample $\log|f|$, $\log p_\theta$, weights and optional $\log q$.

    Without `log_q` the samples are reparameterised draws from $p_\theta$ itself
    ($\sum_i w_i g(x_i) \approx E_p[g]$); with `log_q` they were drawn from a
    frozen density $q$, and $E_p[g] = E_q[g\,p/q]$.
    """
    if log_q is None:
        log_q = log_p
        rev_w = w
    else:
        rev_w = w * jnp.exp(log_p - log_q)
    if objective in ("variance", "chi2"):
        # log E_q[f^2 / (p q)] = log of the second moment of f/p.
        m2 = _wlse(2 * logf - log_p - log_q, w)
        if objective == "variance":
            return m2
        log_i = _wlse(logf - log_q, w)
        return m2 - 2 * log_i
    if objective == "kl":
        # D(p_f || p) with p_f = |f|/I, samples weighted by |f|/q (frozen).
        lw = jax.lax.stop_gradient(logf - log_q)
        log_i = jax.nn.logsumexp(lw, b=w)
        # A batch where f is zero at every sample carries no information: no loss, no gradient.
        seen = jnp.isfinite(log_i)
        log_i = jnp.where(seen, log_i, 0.0)
        nw = jnp.where(seen, w * jnp.exp(lw - log_i), 0.0)
        safe_logf = jnp.where(nw > 0, logf, 0.0)
        safe_logp = jnp.where(nw > 0, log_p, 0.0)
        return jnp.sum(nw * (safe_logf - log_i - safe_logp))
    # reverse_kl: D(p || p_f) = E_p[log p - log|f|] + log I.
    floor = jax.lax.stop_gradient(jnp.max(logf)) - 70.0
    lf = jnp.maximum(logf, floor)
    log_i = jax.lax.stop_gradient(_wlse(logf - log_q, w))
    return jnp.sum(rev_w * (log_p - lf)) + log_i
