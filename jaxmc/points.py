"""Point sets on the unit cube $[0,1)^d$.

Every randomised point set gives an unbiased estimator: each point is
marginally uniform on $[0,1)^d$.
"""

from __future__ import annotations

import jax

from ._checks import check_count, check_key


def uniform(key: jax.Array, n: int, d: int, *, dtype=None) -> jax.Array:
    """`n` i.i.d. uniform points on $[0,1)^d$, shape `(n, d)`."""
    key = check_key(key)
    n = check_count(n, "n")
    d = check_count(d, "d")
    return jax.random.uniform(key, (n, d), dtype=dtype or float)
