r"""Estimates as text: the compact notation of vegas and gvar, and what is built on it.

A mean $m$ with standard error $s$ is written as $m$ rounded to the place of
the second significant digit of $s$, followed by those two digits of $s$ in
parentheses, in units of the last digit shown:

- $0.99771 \pm 0.00423$ reads `0.9977(42)`: the error is $42 \times 10^{-4}$;
- $12.3456 \pm 0.123$ reads `12.35(12)`;
- an error of 1 or more keeps its decimal point, aligned with the mean's
  digits: $12.3456 \pm 1.23$ reads `12.3(1.2)`, $1234.5 \pm 12.3$ reads
  `1234(12)`.

Very small or very large numbers go to scientific notation, the exponent last:
$1.0023\cdot10^{-5} \pm 4.5\cdot10^{-8}$ reads `1.0023(45)e-05`. That
happens, as in Python's `g` format, when the leading digit is below $10^{-4}$,
or when the error is 100 or more, so that the digits shown all count:
$1234.5 \pm 123$ reads `1.23(12)e+03`. An error larger than the mean fixes
the rounding all the same (`0.10(50)`, `0.0(1.2)e+02` for $1 \pm 123$): the
mean is shown only to the precision the error allows.

Special cases: a zero error is written `(0)` after the mean in Python's `g`
form, 6 significant digits (`1.5(0)`, `1(0)e-05`); a mean or an error that is
NaN or infinite is written `m ± s` (`nan ± 1`, `1 ± inf`), and so is an error
below the resolution of a float64 mean (more than 17 significant digits), the mean
with every digit it has (`1000000.5 ± 8.9e-10`).

An error bar of fewer than 10 degrees of freedom (the spread of a few QMC replicas)
is not Gaussian: mean ± 2 standard errors covers 82% of the time with 2 degrees of
freedom, not 95%. `str` of such an estimate says so, `0.9977(42) [dof 2]`;
`Estimate.interval` gives Student's $t$ interval.

Besides the notation, this module writes the other texts of estimates:
their `str` (the notation) and `repr` (the numbers, not array shapes), and the
iteration table of `Combined.summary()`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from decimal import ROUND_HALF_EVEN, Decimal, localcontext
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


FEW_DOF = 10  # below this, `str` shows the degrees of freedom (Student's t, not Gaussian)


def compact(mean: float, stderr: float) -> str:
    """`mean` and its standard error `stderr` in the compact notation (see the module docstring)."""
    mean, stderr = float(mean), abs(float(stderr))
    if not (math.isfinite(mean) and math.isfinite(stderr)):
        return f"{mean:g} ± {stderr:.2g}"
    if stderr == 0:
        digits, exponent = _split_exponent(f"{mean:g}")
        return f"{digits}(0){exponent}"
    s = Decimal(f"{stderr:.1e}")  # two significant digits, rounded (0.0999 -> 1.0E-1)
    last = s.adjusted() - 1  # the place of the last digit shown: 10**last
    with localcontext() as context:
        context.prec = 1000  # float64 spans ~650 decimal digits: quantize never fails
        m = Decimal(mean).quantize(Decimal(1).scaleb(last), rounding=ROUND_HALF_EVEN)
        if m == 0:
            m = abs(m)  # no "-0.00"
        lead = max(m.adjusted(), s.adjusted())  # the leading digit's place
        if lead - last >= 17:  # finer than a float64 resolves: the mean's every digit
            return f"{mean!r} ± {stderr:.2g}"
        if last >= 1 or lead < -4:
            return _with_error(m.scaleb(-lead), s.scaleb(-lead)) + f"e{lead:+03d}"
        return _with_error(m, s)


def _with_error(m: Decimal, s: Decimal) -> str:
    """`m(s)`: the two digits of `s`, or `s` itself with `m`'s decimals when it is 1 or more."""
    if s.adjusted() >= 0:
        error = f"{s.quantize(m):f}" if m.as_tuple().exponent < 0 else f"{s:.0f}"
    else:
        error = "".join(map(str, s.as_tuple().digits))
    return f"{m:f}({error})"


def _split_exponent(text: str) -> tuple[str, str]:
    """`"1e-05"` -> `("1", "e-05")`; `"1.5"` -> `("1.5", "")`."""
    digits, _, exponent = text.partition("e")
    return digits, "e" + exponent if exponent else ""


def compact_array(mean, stderr) -> str:
    """`compact` element by element: a scalar as `0.9977(42)`, an array as `[0.9977(42) 1.234(12)]`."""
    mean, stderr = np.broadcast_arrays(np.asarray(mean, float), np.asarray(stderr, float))
    if mean.ndim == 0:
        return compact(mean, stderr)
    texts = np.frompyfunc(compact, 2, 1)(mean, stderr)
    return np.array2string(texts, formatter={"all": str}, separator=" ")


def number(value, spec: str = ".3g") -> str:
    """A plain number for a `repr`: integers whole, floats formatted by `spec`."""
    value = np.asarray(value)
    if value.dtype.kind == "b":
        return _array(value, str)
    if value.dtype.kind in "iu":
        return _array(value, lambda v: f"{int(v)}")
    return _array(value, lambda v: _float(f"{float(v):{spec}}"))


def _float(text: str) -> str:
    """`"1"` -> `"1.0"`: a float that reads as one."""
    return text if any(c in text for c in ".eni") else text + ".0"


def mean_number(mean, stderr) -> str:
    """A mean for a `repr`: 6 significant digits, or as many as reach its error's second digit."""

    def one(m, s):
        m, s = float(m), float(s)
        ratio = abs(m) / s if s > 0 and math.isfinite(s) and math.isfinite(m) and m != 0 else 1.0
        return _float(f"{m:.{min(17, max(6, math.ceil(math.log10(ratio)) + 2))}g}")

    mean, stderr = np.broadcast_arrays(np.asarray(mean, float), np.asarray(stderr, float))
    if mean.ndim == 0:
        return one(mean, stderr)
    return _array(np.frompyfunc(one, 2, 1)(mean, stderr), str)


def _array(value: np.ndarray, one: Callable) -> str:
    """A scalar as `one(value)`; an array as a short list (at most 6 entries, then `...`)."""
    if value.ndim == 0:
        return one(value[()])
    return np.array2string(
        value, formatter={"all": one}, separator=", ", threshold=6, edgeitems=3
    )


def concrete(tree: Any) -> bool:
    """Whether every leaf of `tree` holds values (no tracer, no shape-only placeholder)."""
    return all(
        isinstance(a, (np.ndarray, np.generic, int, float))
        or (isinstance(a, jax.Array) and not isinstance(a, jax.core.Tracer)
            and a.is_fully_addressable)  # (not another process's shards)
        for a in jax.tree.leaves(tree)
    )


def estimate_str(e) -> str:
    """An `Estimate`'s mean and standard error in the compact notation, with `[dof N]` below
    `FEW_DOF` degrees of freedom (for an array whose elements' differ, each's, in order; its
    `repr` if traced)."""
    if not concrete(e):
        return repr(e)
    text = compact_array(e.mean, np.sqrt(np.asarray(e.variance, float)))
    dof = np.asarray(getattr(e, "dof", np.inf), float)
    if np.any(dof < FEW_DOF):
        if np.all(dof == dof.flat[0]):
            text += f" [dof {dof.flat[0]:.0f}]"
        else:  # (a batch whose members' error bars differ: each its own)
            text += f" [dof {' '.join(f'{v:.0f}' for v in dof.flat)}]"
    return text


def estimate_repr(e, base: type) -> str:
    """`Estimate(mean=0.997712, stderr=0.00423, n=100000, ess=..., pareto_k=...)`.

    The mean, its standard error, `n` and the diagnostics that are known
    (`n_nonfinite` unless 0; `ess` and `pareto_k` unless NaN: an estimate built
    by hand; `dof` when finite; `conservative` when true), then the fields `e` adds to `base` (`Estimate`): stacked parts by
    their number, a nested module by its name. Equinox's repr (shapes and dtypes)
    when some field is not concrete (a tracer in `jit`).
    """
    if not concrete(e):
        return eqx.Module.__repr__(e)
    stderr = np.sqrt(np.asarray(e.variance, float))
    text = dict(mean=mean_number(e.mean, stderr), stderr=number(stderr), n=number(e.n))
    if np.any(np.asarray(e.n_nonfinite) != 0):
        text["n_nonfinite"] = number(e.n_nonfinite)
    for name, spec in (("ess", ".1f"), ("pareto_k", ".2f")):
        if not np.all(np.isnan(np.asarray(getattr(e, name), float))):
            text[name] = number(getattr(e, name), spec)
    if np.any(np.isfinite(np.asarray(getattr(e, "dof", np.inf), float))):
        text["dof"] = number(e.dof, ".0f")
    if np.any(np.asarray(getattr(e, "conservative", False))):
        text["conservative"] = "True"
    own = {f.name for f in dataclasses.fields(base)}
    for name in (f.name for f in dataclasses.fields(e) if f.name not in own):
        value = getattr(e, name)
        if isinstance(value, base):  # parts stacked along a leading axis
            text[name] = f"{type(value).__name__}[{jnp.shape(value.n)[0]}]"
        elif isinstance(value, eqx.Module):
            text[name] = f"{type(value).__name__}(...)"
        elif isinstance(value, bool):  # a static option: shown when set
            if value:
                text[name] = "True"
        elif value is not None:
            text[name] = repr(value) if isinstance(value, str) else number(value)
    return f"{type(e).__name__}({', '.join(f'{k}={v}' for k, v in text.items())})"


def iteration_tables(combined, combine: Callable) -> str:
    """`Combined.summary()`: `iteration_table` of `combined.parts`, per component if an array
    (`combine` is `stats.combine`, which gives the running averages)."""
    if not concrete(combined):
        raise ValueError("`summary()` needs concrete values: call it outside `jit`.")
    shape = jnp.shape(combined.mean)
    if not shape:
        return _running(combined.parts, combine)
    tables = []
    for index in np.ndindex(shape):
        # Per-component leaves are (parts, *shape); the counts (parts,) are shared.
        part = jax.tree.map(
            lambda a: a[(slice(None), *index)] if jnp.ndim(a) > 1 else a, combined.parts
        )
        tables.append(f"[{', '.join(map(str, index))}]\n{_running(part, combine)}")
    return "\n\n".join(tables)


def _running(parts, combine: Callable) -> str:
    """The table of scalar `parts` stacked along axis 0, with their running combinations."""
    parts = jax.tree.map(np.asarray, parts)
    k = parts.n.shape[0]

    def upto(i):  # parts 0..i: the later ones emptied (mean and variance 0: no weight, no dof)
        keep = lambda a: np.where(np.reshape(np.arange(k) <= i, (k,) + (1,) * (a.ndim - 1)), a, 0)
        return jax.tree.map(np.asarray, combine(jax.tree.map(lambda a: keep(a).astype(a.dtype), parts)))

    # (A loop of eager calls of one shape: no new compilation beyond `combine`'s operations.)
    run = [upto(i) for i in range(k)]
    return iteration_table(
        parts.mean, np.sqrt(parts.variance), *(np.array([getattr(r, name) for r in run])
                                               for name in ("mean", "variance", "chi2_dof", "q"))
    )


def iteration_table(means, stderrs, averages, average_variances, chi2_dof, q) -> str:
    """vegas's table of iterations: per row the part's estimate, the running weighted
    average (both compact), and the running `chi2/dof` and `Q` (1-D arrays, one entry a row)."""
    rows = [
        (f"{i + 1:3d}", compact(m, s), compact(a, math.sqrt(v)), f"{c:.2f}", f"{p:.2f}")
        for i, (m, s, a, v, c, p) in enumerate(
            zip(means, stderrs, averages, average_variances, chi2_dof, q)
        )
    ]
    head = ("itn", "integral", "wgt average", "chi2/dof", "Q")
    widths = [max(len(r[j]) for r in [head, *rows]) for j in range(len(head))]
    widths[1] = widths[2] = max(widths[1], widths[2], 14)  # (vegas's column width)

    def line(row):
        left = [row[0].rjust(widths[0]), row[1].ljust(widths[1]), row[2].ljust(widths[2])]
        right = [row[3].rjust(max(widths[3], 8)), row[4].rjust(max(widths[4], 5))]
        return "   ".join(left + right).rstrip()

    return "\n".join([line(head), "-" * len(line(head)), *map(line, rows)])
