import os

# Test workers share the machine (pytest-xdist): on a GPU, do not let each one reserve most of
# its memory up front.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)

# No persistent compilation cache: with one, a test worker aborted inside
# ``executable.serialize()`` while JAX wrote a CPU executable to the cache (jax 0.10.2, core
# dump of 2026-11-26 16:15, test_structured.py), and CI died the same way. Only the in-process
# cache is used; a user's JAX_COMPILATION_CACHE_DIR is still honoured by JAX itself.


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
