"""Box over-approximations of Reach(s, a, c) = { f(x, u_a, w) : x in s, w in c } for all triples."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .centered import enclose


def reachable_boxes(dynamics, x_low, x_high, actions, w_low, w_high, method: str = "both"):
    """Enclosures of Reach for every (state box, action, noise box) triple.

    Args:
        dynamics: ``f(x (n,), u (m,), w (d,)) -> (n,)``.
        x_low, x_high: ``(R, n)`` state boxes.
        actions: ``(A, m)`` inputs shared by all states, or ``(R, A, m)`` per state.
        w_low, w_high: ``(C, d)`` noise boxes (bounded).
        method: ``"natural"``, ``"centered"`` or ``"both"`` (their intersection).

    Returns:
        ``(lo, hi)``, each ``(R, A, C, n)``, with ``f(x, u_a, w) in [lo, hi]`` for all x, w in
        the boxes, rounding included.
    """

    def one(xl, xh, u, wl, wh):
        return enclose(dynamics, (xl, u, wl), (xh, u, wh), method)

    over_noise = jax.vmap(one, in_axes=(None, None, None, 0, 0))
    over_actions = jax.vmap(over_noise, in_axes=(None, None, 0, None, None))
    actions = jnp.asarray(actions)
    over_states = jax.vmap(over_actions, in_axes=(0, 0, 0 if actions.ndim == 3 else None, None, None))
    return over_states(jnp.asarray(x_low), jnp.asarray(x_high), actions,
                       jnp.asarray(w_low), jnp.asarray(w_high))
