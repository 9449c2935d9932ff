"""`OneOf`: a plan whose method was chosen at run time, under `jit`."""

from __future__ import annotations

from typing import ClassVar

import jax

from .._checks import is_concrete
from ._method import AbstractMethod, Problem, Run, switch


class OneOf(AbstractMethod):
    """The plan of a method that chose among `options` while traced (`Auto` under `jit`):
    it streams as `options[choice]` does.

    Passed back to `integrate` with a concrete `choice` (the plan returned from a jitted
    function, or closed over), only that option is traced and compiled; with a traced one
    (the plan passed into `jit` as an argument), every option is compiled and `lax.switch`
    runs one. Under `vmap` with one `choice` for the whole batch the switch stays a switch.

    **Fields:** `choice` (an int32 index) and `options` (trained methods: plans).
    """

    choice: jax.Array
    options: tuple[AbstractMethod, ...]
    name: ClassVar[str] = "auto"

    @property
    def trained(self) -> bool:
        return True

    def run(self, key, problem: Problem, budget: int) -> Run:
        if is_concrete(self.choice):
            return self.options[int(self.choice)].run(key, problem, budget)
        branches = [lambda o=o: o.run(key, problem, budget).estimate for o in self.options]
        return Run(switch(self.choice, branches), self)
