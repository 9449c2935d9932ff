"""The public namespace: each public module declares its API in `__all__` and nothing else leaks.

A public module is one whose dotted path has no component starting with `_`.
Every name it exposes without a leading underscore is either in its `__all__`
or is itself a public submodule (`jaxmc.render.scenes`); imports it only uses
(`jax`, `jnp`, checks from `jaxmc._checks`) live in private modules or under
private names.
"""

import importlib
import pkgutil
import types

import pytest

import jaxmc


PUBLIC_MODULES = (
    "jaxmc",
    "jaxmc.distributions",
    "jaxmc.estimators",
    "jaxmc.fit",
    "jaxmc.methods",
    "jaxmc.points",
    "jaxmc.proposals",
    "jaxmc.quad",
    "jaxmc.render",
    "jaxmc.render.scenes",
    "jaxmc.stats",
    "jaxmc.testing",
    "jaxmc.warps",
)


def _is_public(dotted: str) -> bool:
    return not any(part.startswith("_") for part in dotted.split("."))


def test_the_list_of_public_modules_is_complete():
    found = {"jaxmc"} | {
        info.name
        for info in pkgutil.walk_packages(jaxmc.__path__, "jaxmc.")
        if _is_public(info.name)
    }
    assert found == set(PUBLIC_MODULES)


def _undeclared(module: types.ModuleType) -> list[str]:
    declared = set(getattr(module, "__all__", ()))
    undeclared = []
    for name in dir(module):
        if name.startswith("_") or name in declared:
            continue
        value = getattr(module, name)
        submodule = (
            isinstance(value, types.ModuleType) and value.__name__ == f"{module.__name__}.{name}"
        )
        if not (submodule and value.__name__ in PUBLIC_MODULES):
            undeclared.append(name)
    return undeclared


@pytest.mark.parametrize("name", PUBLIC_MODULES)
def test_public_module_declares_exactly_its_api(name):
    module = importlib.import_module(name)
    assert isinstance(getattr(module, "__all__", None), list), f"{name} has no `__all__` list"
    declared = module.__all__
    assert len(set(declared)) == len(declared), f"{name}.__all__ repeats a name"
    assert [n for n in declared if not hasattr(module, n)] == [], (
        f"{name}.__all__ names a missing object"
    )
    assert _undeclared(module) == [], f"{name} exposes names that are not in `__all__`"


@pytest.mark.parametrize(
    "module, name",
    [
        ("jaxmc", "importlib"),
        ("jaxmc.warps", "is_concrete"),
        ("jaxmc.proposals", "check_bounds"),
        ("jaxmc.render.scenes", "jnp"),
        ("jaxmc.distributions", "is_concrete"),
        ("jaxmc.quad", "jnp"),
    ],
)
def test_known_leaks_stay_gone(module, name):
    assert not hasattr(importlib.import_module(module), name)


def test_star_import_gives_the_declared_api():
    namespace = {}
    exec("from jaxmc.quad import *", namespace)
    assert set(namespace) - {"__builtins__"} == set(jaxmc.quad.__all__)
