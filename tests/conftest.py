import jax
import pytest


# Tests run in float64 so that statistical checks measure the estimators, not
# float32 rounding; accuracy-sensitive float32 paths have explicit tests.
jax.config.update("jax_enable_x64", True)


@pytest.fixture
def key():
    """Deterministic key; tests that need several split it."""
    return jax.random.key(20261122)
