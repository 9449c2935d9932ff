"""A long session: the programs compiled for integrands that are no longer used are freed.

JAX keeps a compiled program for the life of the process unless its cache lets go of
it; a session that integrates many integrands would otherwise run out of memory
mappings. Here the cache is made small, so that a few integrands through `auto`'s whole
pilot (QMC's nets, the grid, the mixture and its mode search) overflow it: the first
integrand must then be released by every program that evaluated it.
"""

import gc
import weakref

import jax
import jax.numpy as jnp
import pytest

import jaxmc
from benchmarks._harness import compiled_programs
from jaxmc import _compiled

from .helpers import box


def _peak(centre):
    def f(x):
        return jnp.exp(-jnp.sum((x - centre) ** 2) / 0.01)

    return f


@pytest.mark.parametrize("n", [2**12, 2**15])  # QMC alone; the whole pilot
def test_an_integrand_no_longer_used_is_released(monkeypatch, n):
    monkeypatch.setattr(_compiled, "MAX_PROGRAMS", 4)
    lo, hi = box(2)
    first = _peak(0.31)
    est = jaxmc.integrate(jax.random.key(0), first, lo, hi, n=n)
    assert n != 2**15 or est.pilot.stages[2], "the grid's stage should have run"
    released = weakref.ref(first)
    del first, est
    for i in range(4):
        jax.block_until_ready(jaxmc.integrate(jax.random.key(i), _peak(0.4 + 0.05 * i), lo,
                                              hi, n=n))
    gc.collect()
    assert released() is None


@pytest.mark.parametrize("method", ["auto", "plain", "stratified"])
def test_another_budget_compiles_no_program(method):
    # The stream's programs read the budget as an array, and the pilot's sizes from it in
    # powers of two: a session that integrates at many budgets does not compile (and hold)
    # a set of programs per budget. (A budget past a power of two may size a larger pilot,
    # and QMC's nets and blocks; below a chunk of 2^18 evaluations, steps are as many blocks
    # as the budget holds.)
    lo, hi = box(2)
    f = _peak(0.37)
    n = 3 * 2**18
    first = jaxmc.integrate(jax.random.key(0), f, lo, hi, n=n, method=method)
    with compiled_programs() as compiled:
        again = jaxmc.integrate(jax.random.key(0), f, lo, hi, n=n + 3 * 2**14 + 7,
                                method=method)
    assert compiled == [], f"{len(compiled)} programs compiled"
    assert again.n > first.n  # (the larger budget was spent, not the first one's)


def test_a_session_near_the_mapping_limit_clears_its_programs_and_goes_on(monkeypatch):
    # Past CROWDED_SHARE of the kernel's limit on memory mappings (here made 0), the next
    # eager call clears the compiled programs first and still integrates correctly; a call
    # under jit does not clear them mid-trace.
    if _compiled._mappings() is None:
        pytest.skip("no /proc memory-mapping count here")
    cleared = []
    clear = jax.clear_caches
    monkeypatch.setattr(jax, "clear_caches", lambda: (cleared.append(1), clear())[1])
    monkeypatch.setattr(_compiled, "_crowded", False)  # (restored as False afterwards)
    monkeypatch.setattr(_compiled, "CROWDED_SHARE", 0.0)
    monkeypatch.setattr(_compiled, "CHECK_EVERY", 1)
    lo, hi = box(2)
    jaxmc.integrate(jax.random.key(0), _peak(0.33), lo, hi, n=2**12)  # (compiles: crowded)
    assert _compiled._crowded and not cleared
    jax.jit(lambda k: jaxmc.integrate(k, _peak(0.34), lo, hi, n=2**12).mean)(jax.random.key(1))
    assert not cleared
    est = jaxmc.integrate(jax.random.key(2), _peak(0.35), lo, hi, n=2**12, method="qmc")
    assert len(cleared) == 1
    sd = jnp.sqrt(0.005)
    exact = jnp.pi * 0.01 * jnp.prod(jax.scipy.special.ndtr((hi - 0.35) / sd)
                                     - jax.scipy.special.ndtr((lo - 0.35) / sd))
    assert abs(float(est.mean) - float(exact)) <= 5 * float(est.stderr)
