import os

import jax
import pytest

jax.config.update("jax_enable_x64", True)

# Hypothesis profile for a 2-core CI machine: no deadlines (JIT compiles on first call).
try:
    from hypothesis import settings

    settings.register_profile("ci", deadline=None, max_examples=25, derandomize=True)
    settings.register_profile("dev", deadline=None, max_examples=25)
    settings.load_profile("ci" if os.environ.get("CI") else "dev")
except ImportError:  # pragma: no cover
    pass


@pytest.fixture
def key():
    return jax.random.PRNGKey(0)
