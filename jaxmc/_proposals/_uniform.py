"""The uniform density on a box."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .. import _random
from .._box import log_volume, to_box
from .._checks import check_bounds, check_count, check_key
from ._base import AbstractProposal


class Uniform(AbstractProposal):
    r"""The uniform density $1/\prod_j (hi_j - lo_j)$ on the box `[lo, hi]`."""

    lo: jax.Array
    hi: jax.Array

    def __init__(self, lo, hi):
        self.lo, self.hi = check_bounds(lo, hi)

    def sample(self, key, n):
        key = check_key(key)
        n = check_count(n)
        shape = (n,) + jnp.shape(self.lo)
        u = _random.uniform(key, shape, jnp.result_type(self.lo))
        x = to_box(u, self.lo, self.hi)
        pdf = jnp.broadcast_to(jnp.exp(-log_volume(self.lo, self.hi)), (n,))
        return x, pdf

    def log_pdf(self, x):
        batch = self._batch_shape(x)
        inside = self._inside(jnp.asarray(x))
        return jnp.broadcast_to(jnp.where(inside, -log_volume(self.lo, self.hi), -jnp.inf), batch)

