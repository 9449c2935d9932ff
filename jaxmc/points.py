r"""Point sets on the unit cube $(0,1)^d$.

Random point sets (`uniform`, `stratified`, `latin_hypercube`) and
low-discrepancy ones (`halton`, `sobol`, `lattice`), optionally randomised so
that every point is marginally uniform on $(0,1)^d$ while the set keeps its
structure; then each randomised point set gives an unbiased estimator. Also
the classic `lcg` generator, a Fisher–Yates `shuffle`, and the `discrepancy`
of a point set.

Sizes (`n`, `d`, `counts`, `skip`) are static Python ints; keys are traced, so
every function works under `jax.jit` and `jax.vmap` over keys. Points come in
the default float dtype (`float64` under `jax_enable_x64`) unless `dtype` is
given.
"""

from ._points._discrepancy import discrepancy as discrepancy
from ._points._halton import halton as halton
from ._points._lattice import LATTICE_MAX_DIM as LATTICE_MAX_DIM, lattice as lattice
from ._points._lcg import lcg as lcg
from ._points._random_sets import (
    latin_hypercube as latin_hypercube,
    stratified as stratified,
    uniform as uniform,
)
from ._points._shuffle import shuffle as shuffle
from ._points._sobol import SOBOL_MAX_DIM as SOBOL_MAX_DIM, sobol as sobol


__all__ = [
    "uniform",
    "stratified",
    "latin_hypercube",
    "halton",
    "sobol",
    "lattice",
    "lcg",
    "shuffle",
    "discrepancy",
    "SOBOL_MAX_DIM",
    "LATTICE_MAX_DIM",
]
