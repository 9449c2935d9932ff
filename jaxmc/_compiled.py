"""Programs compiled for one integrand, kept for the most recent ones only.

`equinox.filter_jit` keys its cache on the static part of its arguments (the integrand
among them) and JAX keeps those compilations for the life of the process: a session that
integrates many integrands accumulates their programs, each holding a few hundred memory
mappings of machine code, until the kernel's limit (`vm.max_map_count`, 65,530 by default)
ends it ("LLVM compilation error: Cannot allocate memory"). `per_integrand` compiles the
same way (arrays traced, everything else static), but as one `jax.jit` of a closure over
the static part per distinct static part, held in a cache of the `MAX_PROGRAMS` used last:
a program dropped from it is freed, and compiled anew if it is needed again. `per_shape`
does the same for the stream's programs that serve every integrand of a shape, in a cache
of their own.
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
# The stream's programs that do not evaluate the integrand (its points, its moments, its
# estimate) serve every integrand of a shape: a cache of their own, so that a session of
# many integrands does not evict them, and bounded, so that one of many shapes (sizes of
# `n`, dimensions, methods) does not accumulate them.
MAX_SHAPE_PROGRAMS = 64

_programs: collections.OrderedDict[Hashable, Callable] = collections.OrderedDict()
_shape_programs: collections.OrderedDict[Hashable, Callable] = collections.OrderedDict()


def per_integrand(fn: Callable) -> Callable:
    """`fn` compiled as `equinox.filter_jit` compiles it (its array arguments traced, the
    rest static), one program per static part, the `MAX_PROGRAMS` used last kept."""
    return _bounded(fn, _programs, lambda: MAX_PROGRAMS)


def per_shape(fn: Callable) -> Callable:
    """`per_integrand` for programs that do not evaluate an integrand, in a cache of their
    own: the `MAX_SHAPE_PROGRAMS` used last kept."""
    return _bounded(fn, _shape_programs, lambda: MAX_SHAPE_PROGRAMS)


def _bounded(fn: Callable, programs: collections.OrderedDict, size: Callable[[], int]):
    # One flatten per call, not `equinox.partition`'s tree maps: these programs run several
    # times per eager `integrate` call, where the split is a visible share of the time.
    @functools.wraps(fn)
    def compiled(*args: Any, **kwargs: Any) -> Any:
        leaves, treedef = jax.tree.flatten((args, kwargs))
        arrays = [a for a in leaves if eqx.is_array(a)]
        # (Arrays' slots hold None, which no leaf is: the key fixes which leaves are arrays.)
        static = tuple(None if eqx.is_array(a) else a for a in leaves)
        key = (fn, treedef, static)
        try:
            program = programs.pop(key, None)
        except TypeError:  # an unhashable static argument: compiled for this call alone
            return _compile(fn, treedef, static)(arrays)
        if program is None:
            program = _compile(fn, treedef, static)
        programs[key] = program  # (the most recent last)
        while len(programs) > size():
            programs.popitem(last=False)
        return program(arrays)

    return compiled


def _compile(fn: Callable, treedef, static: tuple) -> Callable:
    """`fn` with its static leaves bound (the arrays' slots of `static` are None), as one
    `jax.jit` program of its array leaves. As `equinox.filter_jit`'s, its outputs that are
    not arrays (Python numbers among them) come back as they are, not as arrays: they are
    kept from the trace, one per signature of the traced arguments."""
    outputs: dict[Hashable, Any] = {}

    def run(arrays):
        supply = iter(arrays)
        args, kwargs = jax.tree.unflatten(
            treedef, [next(supply) if a is None else a for a in static])
        leaves, out_treedef = jax.tree.flatten(fn(*args, **kwargs))
        outputs[_signature(arrays)] = (out_treedef, tuple(
            None if eqx.is_array(a) else a for a in leaves))
        return [a for a in leaves if eqx.is_array(a)]

    run.__name__ = run.__qualname__ = fn.__name__  # (what JAX's logs call the program)
    program = jax.jit(run)

    def call(arrays):
        supply = iter(program(arrays))  # (traced on first sight of a signature)
        out_treedef, out_static = outputs[_signature(arrays)]
        return jax.tree.unflatten(out_treedef, [next(supply) if a is None else a
                                                for a in out_static])

    return call


def _signature(arrays: list) -> Hashable:
    return tuple((a.shape, a.dtype, getattr(a, "weak_type", False)) for a in arrays)


# Memory mappings. On Linux every compiled CPU program holds some (its code and data
# sections), and the kernel allows a process `vm.max_map_count` of them (65,530 by
# default): past it the next compilation fails ("LLVM compilation error: Cannot allocate
# memory") and ends the process. The caches above are bounded, but JAX's own caches keep
# every program compiled for a shape (each dimension, budget range and method of a session
# adds its set). After every `CHECK_EVERY` compilations the mappings are counted; past
# `CROWDED_SHARE` of the limit, the next eager `integrate` or `expectation` first clears
# these caches and JAX's (`jax.clear_caches`): its programs, and the session's, are
# compiled anew when next needed, where the alternative is the end of the process.
CHECK_EVERY = 16
CROWDED_SHARE = 0.6

_compilations = 0
_crowded = False


def _mappings() -> tuple[int, int] | None:
    """`(mappings held, the kernel's limit)`, where the system says (Linux), else None."""
    try:
        with open("/proc/sys/vm/max_map_count") as limit, open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps), int(limit.read())
    except (OSError, ValueError):
        return None


def _compiled_one(event: str, duration: float, **_: Any) -> None:
    global _compilations, _crowded
    if event != "/jax/core/compile/backend_compile_duration":
        return
    _compilations += 1
    if _compilations % CHECK_EVERY == 0:
        held = _mappings()
        _crowded = _crowded or (held is not None and held[0] > CROWDED_SHARE * held[1])


jax.monitoring.register_event_duration_secs_listener(_compiled_one)


def release_if_crowded(*inputs: Any) -> bool:
    """Clear the compiled programs (these caches and JAX's) if the process's memory mappings
    crowded its limit at the last count, and no leaf of `inputs` (a call's arguments) is
    traced: eagerly, between programs, never inside a trace. Whether it did."""
    global _crowded
    if not _crowded or any(isinstance(a, jax.core.Tracer) for a in jax.tree.leaves(inputs)):
        return False
    _programs.clear()
    _shape_programs.clear()
    jax.clear_caches()
    _crowded = False
    return True
