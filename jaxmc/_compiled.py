"""Programs compiled for one integrand, kept for the most recent ones only.

`equinox.filter_jit` keys its cache on the static part of its arguments (the integrand
among them) and JAX keeps those compilations for the life of the process: a session that
integrates many integrands accumulates their programs, each holding a few hundred memory
mappings of machine code, until the kernel's limit (`vm.max_map_count`, 65,530 by default)
ends it ("LLVM compilation error: Cannot allocate memory"). `per_integrand` compiles the
same way (arrays traced, everything else static), but as one `jax.jit` of a closure over
the static part per distinct static part, held in a cache of the `MAX_PROGRAMS` used last:
a program dropped from it is freed, and compiled anew if it is needed again.
"""

from __future__ import annotations

import collections
import functools
from collections.abc import Callable, Hashable
from typing import Any

import equinox as eqx
import jax


# A program with the integrand it evaluates takes ~150-300 memory mappings on a CPU (one
# per kernel and section); a few integrands' worth of programs keeps far below the limit.
MAX_PROGRAMS = 64

_programs: collections.OrderedDict[Hashable, Callable] = collections.OrderedDict()


def per_integrand(fn: Callable) -> Callable:
    """`fn` compiled as `equinox.filter_jit` compiles it (its array arguments traced, the
    rest static), one program per static part, the `MAX_PROGRAMS` used last kept."""

    @functools.wraps(fn)
    def compiled(*args: Any, **kwargs: Any) -> Any:
        dynamic, static = eqx.partition((args, kwargs), eqx.is_array)
        leaves, treedef = jax.tree.flatten(static)
        key = (fn, treedef, tuple(leaves))
        try:
            program = _programs.pop(key, None)
        except TypeError:  # an unhashable static argument: compiled for this call alone
            return _compile(fn, static)(dynamic)
        if program is None:
            program = _compile(fn, static)
        _programs[key] = program  # (the most recent last)
        while len(_programs) > MAX_PROGRAMS:
            _programs.popitem(last=False)
        return program(dynamic)

    return compiled


def _compile(fn: Callable, static: Any) -> Callable:
    def run(dynamic):
        args, kwargs = eqx.combine(dynamic, static)
        return fn(*args, **kwargs)

    run.__name__ = run.__qualname__ = fn.__name__  # (what JAX's logs call the program)
    return jax.jit(run)
