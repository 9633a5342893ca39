"""The stochastic control system x[t+1] = f(x[t], u[t], w[t])."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .noise import Distribution


@dataclasses.dataclass(frozen=True, eq=False)
class System:
    """A discrete-time stochastic system with a finite action set.

    Args:
        dynamics: ``f(x (n,), u (m,), w (d,)) -> x_next (n,)``, JAX-traceable, float64.
        actions: ``(|A|, m)`` array; row ``a`` is the input of action index ``a``
            (a 1-D array is read as ``|A|`` scalar inputs).
        noise: the distribution P_W of the i.i.d. disturbance ``w``.
    """

    dynamics: Callable
    actions: np.ndarray
    noise: Distribution

    def __post_init__(self):
        if not callable(self.dynamics):
            raise TypeError(f"dynamics must be callable, got {type(self.dynamics).__name__}")
        if not isinstance(self.noise, Distribution):
            raise TypeError(f"noise must be a smdpjax Distribution (Gaussian, Uniform, ...), got {self.noise!r}")
        actions = np.asarray(self.actions, dtype=np.float64)
        if actions.ndim == 1:
            actions = actions[:, None]
        if actions.ndim != 2 or actions.shape[0] == 0:
            raise ValueError(f"actions must have shape (|A|, m) with |A| >= 1, got {np.shape(self.actions)}")
        if not np.all(np.isfinite(actions)):
            raise ValueError("actions must be finite")
        object.__setattr__(self, "actions", actions)

    @property
    def num_actions(self) -> int:
        return int(self.actions.shape[0])

    def step(self, x, action_index, w):
        """One step for batches: ``x (..., n)``, ``action_index (...)`` int, ``w (..., d)``."""
        u = jnp.asarray(self.actions)[action_index]
        f = self.dynamics
        for _ in range(x.ndim - 1):
            f = jax.vmap(f)
        return f(x, u, w)

    def check_against(self, n: int, probe_x: np.ndarray) -> None:
        """Raise ValueError unless ``f`` maps ``(n,)`` states to finite ``(n,)`` states.

        ``probe_x: (k, n)`` are states to try with every action and the noise mean; cheap, and it
        catches wrong shapes and NaN/inf before the abstraction spends minutes on them.
        """
        w = np.asarray(self.noise.mean())
        x0 = np.asarray(probe_x[0])
        try:
            out = _output_shape(self.dynamics, _spec(x0), _spec(np.asarray(self.actions[0])), _spec(w))
        except Exception as exc:  # the user's function failed on shapes: say which ones we passed
            raise ValueError(f"dynamics(x {x0.shape}, u {self.actions[0].shape}, w {w.shape}) failed: {exc}") from exc
        if out.shape != (n,):
            raise ValueError(f"dynamics must return shape ({n},) for a state of shape ({n},), got {out.shape}")
        xs = np.repeat(np.asarray(probe_x), self.num_actions, axis=0)
        acts = np.tile(np.arange(self.num_actions), probe_x.shape[0])
        nxt = _probe(self.dynamics)(xs, self.actions[acts], w)
        bad = ~np.all(np.isfinite(np.asarray(nxt)), axis=-1)
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"dynamics returned NaN/inf at x={np.asarray(xs[i]).tolist()}, "
                             f"action {int(acts[i])}, w={np.asarray(w).tolist()}")

    def __repr__(self):
        name = getattr(self.dynamics, "__name__", type(self.dynamics).__name__)
        return f"System(dynamics={name}, |A|={self.num_actions}, m={self.actions.shape[1]}, noise={self.noise!r})"


def _spec(a) -> jax.ShapeDtypeStruct:
    return jax.ShapeDtypeStruct(a.shape, jnp.result_type(a.dtype))


@functools.lru_cache(maxsize=256)
def _output_shape(dynamics, *specs):
    """``jax.eval_shape`` of ``dynamics`` (a trace: cached per function and argument shapes)."""
    return jax.eval_shape(dynamics, *specs)


@functools.lru_cache(maxsize=64)
def _probe(dynamics):
    """``f`` over a batch of states and inputs at one noise value, compiled once per function."""
    return jax.jit(jax.vmap(dynamics, in_axes=(0, 0, None)))
