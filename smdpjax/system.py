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
        g, B: set by ``System.additive`` (``None`` otherwise): the system is
            ``f(x, u, w) = g(x, u) + B w`` with ``B (n, d)`` constant, which the direct IMDP
            bounds (``abstract(..., bounds="direct")``) integrate exactly.
    """

    dynamics: Callable
    actions: np.ndarray
    noise: Distribution
    g: Callable | None = None
    B: np.ndarray | None = None

    @classmethod
    def additive(cls, g: Callable, B=None, *, actions, noise: Distribution) -> "System":
        """The system ``x' = g(x, u) + B w`` (additive noise with a constant matrix ``B``).

        Args:
            g: ``g(x (n,), u (m,)) -> (n,)``, JAX-traceable, float64.
            B: ``None`` (identity, ``n = d``), a scalar (``B I``), a ``(d,)`` diagonal, or an
                ``(n, d)`` matrix.
            actions, noise: as for ``System``.

        Returns an ordinary ``System`` (``dynamics = g(x, u) + B w``, so every abstraction class,
        ``simulate`` and the Lemma 1 bounds work as usual) that also records ``g`` and ``B``.
        """
        if not callable(g):
            raise TypeError(f"g must be callable, got {type(g).__name__}")
        if not isinstance(noise, Distribution):
            raise TypeError(f"noise must be a smdpjax Distribution (Gaussian, Uniform, ...), got {noise!r}")
        d = noise.dim
        matrix = np.eye(d) if B is None else np.array(B, dtype=np.float64)  # a copy: frozen below
        if matrix.ndim == 0:
            matrix = matrix * np.eye(d)
        elif matrix.ndim == 1:
            if matrix.shape != (d,):
                raise ValueError(f"a 1-D B is the diagonal and must have length d = {d} (the noise "
                                 f"dimension), got {matrix.shape}")
            matrix = np.diag(matrix)
        if matrix.ndim != 2 or matrix.shape[1] != d:
            raise ValueError(f"B must be None, a scalar, a ({d},) diagonal or an (n, {d}) matrix for noise of "
                             f"dimension {d}, got shape {np.shape(B)}")
        if not np.all(np.isfinite(matrix)):
            raise ValueError("B must be finite")
        matrix.setflags(write=False)
        return cls(_additive_dynamics(g, matrix), actions, noise, g=g, B=matrix)

    @property
    def is_additive(self) -> bool:
        """Declared by ``System.additive`` (``g`` and ``B`` are known)."""
        return self.g is not None and self.B is not None

    def __post_init__(self):
        if (self.g is None) != (self.B is None):
            raise ValueError("g and B go together (use System.additive to declare x' = g(x, u) + B w)")
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
        catches wrong shapes and NaN/inf before the abstraction spends minutes on them. A check
        that passed is not run again for the same function, actions, noise mean and states (the
        outcome is a function of those, as ``jax.jit``'s cache assumes; on the 145-cell
        temperature model the check was a third of the reachable-set stage).
        """
        w = np.asarray(self.noise.mean())
        key = (self.dynamics, int(n), *(_fingerprint(a) for a in (self.actions, w, probe_x)))
        if key in _PASSED:
            return
        self._check(n, np.asarray(probe_x), w)
        _PASSED[key] = None
        if len(_PASSED) > _PASSED_SIZE:
            _PASSED.pop(next(iter(_PASSED)))

    def _check(self, n: int, probe_x: np.ndarray, w: np.ndarray) -> None:
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


def _additive_dynamics(g, B: np.ndarray):
    """``f(x, u, w) = g(x, u) + B w``. One nonzero per row (a diagonal or a permutation times a
    diagonal): ``b * w[perm]``, elementwise, so that the Lemma 1 enclosures and the samples see
    no sums of zero terms; identity: ``g + w``."""
    one_per_row = np.count_nonzero(B, axis=1) == 1
    if np.all(one_per_row):
        perm = np.argmax(B != 0, axis=1)
        scale = B[np.arange(B.shape[0]), perm]
        if B.shape[0] == B.shape[1] and np.array_equal(perm, np.arange(B.shape[0])) and np.all(scale == 1):
            def dynamics(x, u, w):
                return g(x, u) + w
        else:
            def dynamics(x, u, w):
                return g(x, u) + jnp.asarray(scale) * w[perm]
    else:
        def dynamics(x, u, w):
            return g(x, u) + jnp.asarray(B) @ w
    dynamics.__name__ = f"{getattr(g, '__name__', 'g')}_plus_Bw"
    return dynamics


# Checks that passed (``System.check_against``), oldest first.
_PASSED: dict = {}
_PASSED_SIZE = 256


def _fingerprint(a) -> tuple:
    a = np.asarray(a)
    return a.shape, a.dtype.str, a.tobytes()


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
