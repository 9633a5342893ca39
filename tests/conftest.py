import os
import tempfile

# Test workers share the machine (pytest-xdist): on a GPU, do not let each one reserve most of
# its memory up front.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

# A persistent compilation cache per test process: each xdist worker's, shared with the
# notebooks, Table 1 rows and multi-device runs it starts as subprocesses (they inherit the
# environment and run while the worker waits), which compile many of the same programs. Not one
# cache for both workers: without a size limit JAX writes an entry in place (no lock, no rename),
# so a worker could read the other's half-written executable and crash. Keyed by program, jax
# version and devices, so a stale entry is never used; compiled programs only, it changes no result.
# The worker's id is known only once pytest configures it (``pytest_configure`` below).
# (A directory set by this file in the xdist controller reaches the workers too: not the user's.)
_USER_CACHE_DIR = None if os.environ.get("SMDPJAX_TESTS_CACHE_SET") else os.environ.get("JAX_COMPILATION_CACHE_DIR")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)


def pytest_configure(config):
    if _USER_CACHE_DIR is None:
        worker = os.environ.get("PYTEST_XDIST_WORKER") or getattr(config, "workerinput", {}).get("workerid", "main")
        path = os.path.join(tempfile.gettempdir(), f"smdpjax-tests-jax-cache-{os.getuid()}-{worker}")
        os.environ["JAX_COMPILATION_CACHE_DIR"] = path  # for the subprocesses
        os.environ["SMDPJAX_TESTS_CACHE_SET"] = "1"
        jax.config.update("jax_compilation_cache_dir", path)


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
