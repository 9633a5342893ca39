import gc
import os

# Test workers share the machine (pytest-xdist): on a GPU, do not let each one reserve most of
# its memory up front.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)

# Every compiled CPU program holds ~18 memory mappings (its code and data) for as long as JAX
# caches it, and Linux allows a process vm.max_map_count (65 530 by default) of them: a test
# worker that had compiled some 3 600 programs crashed inside XLA (a segfault while compiling,
# or an abort in ``executable.serialize()``), late in the suite, in whichever test compiled
# next; CI died that way (and the xdist controller then waited forever). tests/abstraction/
# test_mimdp.py alone passes 21 000 mappings. So after any test that leaves the process above
# half the limit, JAX's caches are dropped, which unmaps the programs.
def _mappings() -> int | None:
    try:
        with open("/proc/self/maps") as maps:
            return sum(1 for _ in maps)
    except OSError:  # not Linux
        return None


def _map_limit() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as limit:
            return int(limit.read())
    except (OSError, ValueError):
        return 65530


_MAP_BUDGET = _map_limit() // 2


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    yield
    count = _mappings()
    if count is not None and count > _MAP_BUDGET:
        jax.clear_caches()
        gc.collect()


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


@pytest.fixture
def assert_same_q_values():
    """``check(a, b, values, strategy, atol)``: two abstractions of the same rows give the same
    q-values (both adversaries) for each value vector: every action, the fixed ``strategy``, and
    after ``restrict(strategy)``."""
    import numpy as np

    q = jax.jit(lambda a, v, adversary, s: a.q_values(v, adversary, s), static_argnums=2)

    def check(a, b, values, strategy, atol):
        same = lambda x, y: np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=atol)
        for v in values:
            for adversary in ("min", "max"):
                for s in (None, strategy):
                    same(q(a, v, adversary, s), q(b, v, adversary, s))
                same(q(a.restrict(strategy), v, adversary, None), q(b.restrict(strategy), v, adversary, None))

    return check
