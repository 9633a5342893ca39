"""Disturbance distributions P_W.

A distribution only has to say how likely an axis-aligned box is (``box_probability``), how likely
the complement of a box is (``outside_probability``, overridden where ``1 - box`` would cancel),
what its support is, and how to sample. Everything else in the library is written against this
interface, so adding a distribution means adding one class here.
"""

from __future__ import annotations

import abc

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import ndtr

from .errors import as_vector, check_low_high


class Distribution(abc.ABC):
    """A distribution on R^d with independent or joint components."""

    @property
    @abc.abstractmethod
    def dim(self) -> int:
        """Dimension d of the disturbance."""

    @abc.abstractmethod
    def box_probability(self, low, high):
        """P_W([low, high]) for boxes ``low, high: (..., d)``; returns ``(...)``. Bounds may be +-inf."""

    def outside_probability(self, low, high):
        """P_W(R^d minus [low, high]) for ``low, high: (..., d)``; returns ``(...)``."""
        return 1.0 - self.box_probability(low, high)

    @abc.abstractmethod
    def support(self) -> tuple[np.ndarray, np.ndarray]:
        """Smallest box ``(low, high)``, each ``(d,)``, holding all the mass (entries may be inf)."""

    @abc.abstractmethod
    def sample(self, key, shape=()):
        """Samples of shape ``(*shape, d)``."""

    @property
    def has_density(self) -> bool:
        """Every component has a density (no atoms), so a noise box's faces carry probability 0.
        Lets the abstraction treat a reachable box's ends that come from noise bounds as never
        attained. False (the conservative answer) unless a subclass knows better."""
        return False

    def mean(self):
        """Mean ``(d,)``; used to probe the dynamics for shape and finiteness checks."""
        low, high = self.support()
        return jnp.asarray(np.where(np.isfinite(low) & np.isfinite(high), (low + high) / 2, 0.0))


@jax.tree_util.register_pytree_node_class
class Gaussian(Distribution):
    """Gaussian with independent components: ``w ~ N(mean, diag(std**2))``.

    Args:
        mean: ``(d,)`` mean vector.
        std: ``(d,)`` standard deviations, all > 0 (a scalar is broadcast).
    """

    def __init__(self, mean, std):
        mean = jnp.atleast_1d(jnp.asarray(mean, dtype=jnp.float64))
        std = jnp.broadcast_to(jnp.asarray(std, dtype=jnp.float64), mean.shape)
        if mean.ndim != 1:
            raise ValueError(f"Gaussian mean must be 1-D, got shape {mean.shape}")
        if not isinstance(std, jax.core.Tracer):
            std_np = np.asarray(std)
            if not np.all(np.isfinite(std_np)) or np.any(std_np <= 0):
                raise ValueError(f"Gaussian std must be finite and > 0 (a positive covariance), got {std_np}")
        if not isinstance(mean, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(mean))):
            raise ValueError(f"Gaussian mean must be finite, got {np.asarray(mean)}")
        self._mean = mean
        self.std = std

    @property
    def dim(self) -> int:
        return int(self._mean.shape[0])

    def mean(self):
        return self._mean

    def _interval_masses(self, low, high):
        """Per-axis P(a <= w_i <= b), computed on the tail side to avoid cancellation."""
        a = (jnp.asarray(low) - self._mean) / self.std
        b = (jnp.asarray(high) - self._mean) / self.std
        upper_tail = a > 0  # both endpoints right of the mean: use the complementary CDF
        p_right = ndtr(-jnp.where(upper_tail, a, 0.0)) - ndtr(-jnp.where(upper_tail, b, 0.0))
        p_left = ndtr(jnp.where(upper_tail, 0.0, b)) - ndtr(jnp.where(upper_tail, 0.0, a))
        return jnp.clip(jnp.where(upper_tail, p_right, p_left), 0.0, 1.0)

    def box_probability(self, low, high):
        return jnp.prod(self._interval_masses(low, high), axis=-1)

    def outside_probability(self, low, high):
        # 1 - prod(1 - q_i) with q_i the per-axis tail masses, without cancellation.
        a = (jnp.asarray(low) - self._mean) / self.std
        b = (jnp.asarray(high) - self._mean) / self.std
        q = ndtr(a) + ndtr(-b)
        return -jnp.expm1(jnp.sum(jnp.log1p(-jnp.clip(q, 0.0, 1.0)), axis=-1))

    def support(self):
        d = self.dim
        return np.full(d, -np.inf), np.full(d, np.inf)

    @property
    def has_density(self) -> bool:
        return True  # std > 0 in every component

    def sample(self, key, shape=()):
        shape = tuple(np.atleast_1d(shape)) if shape != () else ()
        return self._mean + self.std * jax.random.normal(key, (*shape, self.dim), dtype=jnp.float64)

    def tree_flatten(self):
        return (self._mean, self.std), None

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)  # skip validation: children may be tracers or placeholders
        obj._mean, obj.std = children
        return obj

    def __repr__(self):
        return f"Gaussian(mean={np.asarray(self._mean).tolist()}, std={np.asarray(self.std).tolist()})"


class Uniform(Distribution):
    """Uniform distribution on the box ``[low, high]`` (each ``(d,)``, low < high)."""

    def __init__(self, low, high):
        low = as_vector(low, "Uniform low")
        high = as_vector(high, "Uniform high", dim=low.shape[0])
        check_low_high(low, high, "Uniform")
        self.low = low
        self.high = high

    @property
    def dim(self) -> int:
        return int(self.low.shape[0])

    def box_probability(self, low, high):
        lo = jnp.maximum(jnp.asarray(low), self.low)
        hi = jnp.minimum(jnp.asarray(high), self.high)
        frac = jnp.clip((hi - lo) / (self.high - self.low), 0.0, 1.0)
        return jnp.prod(frac, axis=-1)

    def support(self):
        return self.low.copy(), self.high.copy()

    @property
    def has_density(self) -> bool:
        return True  # low < high in every component

    def sample(self, key, shape=()):
        shape = tuple(np.atleast_1d(shape)) if shape != () else ()
        u = jax.random.uniform(key, (*shape, self.dim), dtype=jnp.float64)
        return self.low + (self.high - self.low) * u

    def __repr__(self):
        return f"Uniform(low={self.low.tolist()}, high={self.high.tolist()})"
