r"""The progress bar of `integrate` and `adapt`: a tqdm bar moved from inside the compiled loop.

The streaming loop runs compiled; after every chunk it sends its running
estimate out with `jax.debug.callback` to `report`, which moves the bar (on
stderr) and shows the estimate in the compact notation:

    integrate:  40%|████      | 4.19M/10.5M [00:01<00:02, 3.10Meval/s, 0.74682(12)]

Outside `jit`, `progress_bar` opens the bar before the streaming call, counting
from the evaluations already spent (the pilot of `"auto"`, the training of
`"adaptive"`), and once every callback has run (`jax.effects_barrier`: they run
asynchronously) closes it where the evaluations stopped: at the budget, or
earlier when a tolerance was met. Under a user's `jit` the call is traced before
it runs, so no bar can be opened around it: the loop's first report opens one for
the streaming part alone, and its last report closes it. With several devices,
the first one reports.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import jax
import jax.numpy as jnp
from tqdm import tqdm

from ._format import compact_array


class _Shown:
    """The bar the reports move (callbacks run on the runtime's threads: guarded by `lock`)."""

    lock = threading.Lock()
    bar: tqdm | None = None
    done = 0  # evaluations spent before the streaming call, counted in the bar
    owned = False  # opened by `progress_bar`, which closes it (else the last report does)


_POSTFIX = 40  # characters of the running estimate shown (an array's first components)


def _open(total: int, done: int, desc: str) -> tqdm:
    # (`file` is looked up now, so a redirected stderr, e.g. pytest's, gets the bar.)
    return tqdm(total=total, initial=done, desc=desc, unit="eval", unit_scale=True,
                file=sys.stderr)


def _close() -> None:
    if _Shown.bar is not None:
        _Shown.bar.close()
    _Shown.bar, _Shown.done, _Shown.owned = None, 0, False


def _tracing() -> bool:
    """Whether this runs under a `jit` trace (there even a constant is a tracer)."""
    return isinstance(jnp.zeros(()), jax.core.Tracer)


@contextmanager
def progress_bar(enabled: bool, total: int, done: int = 0, desc: str = "integrate") -> Iterator[None]:
    """The bar around one streaming call outside `jit`: `done` of `total` evaluations
    already spent; `desc` labels it. Does nothing when not `enabled` or under a `jit` trace."""
    if not enabled or _tracing():
        yield
        return
    with _Shown.lock:
        _close()  # a bar left open by a failed traced run
        _Shown.bar, _Shown.done, _Shown.owned = _open(total, done, desc), done, True
    try:
        yield
    finally:
        jax.effects_barrier()  # the reports of the call, which may still be queued
        with _Shown.lock:
            _close()


def report(mean, stderr, n, *, total: int, last: bool, desc: str = "integrate",
           note: str = "") -> None:
    """The host side of the loop's `jax.debug.callback`: the streaming call has done `n` of
    its `total` evaluations and estimates `mean` with error `stderr`; `last` after the loop;
    `desc` labels a bar opened here (under `jit`); `note` follows the estimate (a
    tolerance run's forecast)."""
    with _Shown.lock:
        if _Shown.bar is None:
            if last:  # (a batch of `vmap`ped runs: the first one closed the bar)
                return
            _Shown.bar = _open(total, 0, desc)  # under `jit`: a bar for the streaming part
        text = compact_array(mean, stderr) + (f" {note}" if note else "")
        _Shown.bar.set_postfix_str(
            text if len(text) <= _POSTFIX else text[: _POSTFIX - 1] + "…", refresh=False
        )
        _Shown.bar.update(_Shown.done + int(n) - _Shown.bar.n)
        if last and not _Shown.owned:
            _close()
