r"""The methods `jaxmc.integrate` streams with, as objects.

A method's options are its fields, with documented defaults, as an optimistix solver's
are; the strings `integrate` accepts are aliases of the default objects:

| name | object | what it does |
| --- | --- | --- |
| `"auto"` | `Auto()` | a pilot races the others on a share of the budget; the winner streams the rest |
| `"qmc"` | `QMC()` | scrambled Sobol' nets that keep their convergence rate |
| `"adaptive"` | `Adaptive()` | VEGAS+: a separable grid map with adaptive stratification |
| `"grid_qmc"` | `GridQMC()` | QMC's nets through a trained VEGAS grid's map |
| `"importance"` | `Importance()` | importance sampling from a fixed density (by default a mixture seeded from a grid) |
| `"plain"` | `Plain()` | i.i.d. uniform points |
| `"stratified"` | `Stratified()` | jittered strata |

Every result of `integrate` carries its *plan*, `est.plan`: the method that streamed, with
what it trained (a grid, a fitted mixture). `integrate(..., method=est.plan)` streams with
it at once, without a pilot or training: a family of integrals (`vmap` over `args`, a
pipeline under `jit`, another process after `equinox.tree_serialise_leaves`) pays for the
choice once. Under `jit`, `Auto`'s plan is a `OneOf` of the candidates, its choice traced;
with infinite limits, a plan is a `Mapped`: the method, and the maps of the infinite axes.
"""

from ._auto._auto import Auto as Auto
from ._auto._pilot import Pilot as Pilot
from ._methods._adaptive import Adaptive as Adaptive
from ._methods._basic import QMC as QMC, Plain as Plain, Stratified as Stratified
from ._methods._grid_qmc import GridQMC as GridQMC
from ._methods._importance import Importance as Importance
from ._methods._mapped import Mapped as Mapped
from ._methods._method import AbstractMethod as AbstractMethod
from ._methods._one_of import OneOf as OneOf


__all__ = [
    "AbstractMethod",
    "Adaptive",
    "Auto",
    "GridQMC",
    "Importance",
    "Mapped",
    "OneOf",
    "Pilot",
    "Plain",
    "QMC",
    "Stratified",
]
