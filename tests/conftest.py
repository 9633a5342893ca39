import os
import tempfile

# Test workers share the machine (pytest-xdist): on a GPU, do not let each one reserve most of
# its memory up front.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

# One persistent compilation cache for the test session's processes: the xdist workers, and the
# notebooks, Table 1 rows and multi-device runs that the tests start as subprocesses (which
# inherit the environment), compile many of the same programs. Keyed by program, jax version and
# devices, so a stale entry is never used; compiled programs only, it changes no result.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR",
                      os.path.join(tempfile.gettempdir(), f"smdpjax-tests-jax-cache-{os.getuid()}"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")

import jax  # noqa: E402
import pytest  # noqa: E402

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
