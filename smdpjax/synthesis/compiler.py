"""How the backup loops are compiled: ``backup_jit``, ``jax.jit`` with ``backup_compiler_options``
(``value_iteration``'s loops and ``sweep.batched_synthesis``).

On the CPU, XLA hands reductions and elementwise fusions to YNNPACK by default (jaxlib 0.10).
The backups' reductions are short (the cells of one block, the entries of one list) and many,
and there each library call costs more than XLA's own loop: one 2I-MDP backup of the 3-D
temperature (1728 rows, 27-cell blocks) took 15.4 and 12.6 ms with them, 11.0 and 9.9 ms
without; the IMDP and SMDP backups are unchanged within noise, and so are their values bit for
bit (docs/performance.md). Only products keep YNNPACK. The 2I-MDP's values may differ in the
last bits (another order of the same sums), which the rounding allowance covers: its bound does
not depend on the order.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

CPU_BACKUP_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}


@functools.cache
def backup_compiler_options(backend: str) -> dict | None:
    """The compiler options of the backup loops on ``backend``: ``CPU_BACKUP_OPTIONS`` on a
    CPU whose XLA knows them (tried on a one-line program once), else ``None`` (the defaults)."""
    if backend != "cpu":
        return None
    try:
        jax.jit(lambda x: x + 1, compiler_options=CPU_BACKUP_OPTIONS).lower(jnp.zeros(2)).compile()
    except Exception:  # an older jax.jit without compiler_options, or an XLA without the option
        return None
    return dict(CPU_BACKUP_OPTIONS)


def backup_jit(fn=None, **jit_kwargs):
    """``jax.jit(fn, **jit_kwargs)`` with ``backup_compiler_options`` of JAX's default backend,
    looked up at the first call (not at import, which would start the backend). Called inside
    another trace (``jax.jit``, ``vmap``), where JAX refuses compiler options, a plain ``jax.jit``."""
    if fn is None:
        return functools.partial(backup_jit, **jit_kwargs)
    plain = jax.jit(fn, **jit_kwargs)
    tuned = {}

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves((args, kwargs))):
            return plain(*args, **kwargs)
        backend = jax.default_backend()
        compiled = tuned.get(backend)
        if compiled is None:
            options = backup_compiler_options(backend)
            compiled = tuned[backend] = plain if options is None else jax.jit(fn, compiler_options=options,
                                                                              **jit_kwargs)
        return compiled(*args, **kwargs)

    return call
