"""Box over-approximations of Reach(s, a, c) = { f(x, u_a, w) : x in s, w in c } for all triples."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .centered import enclose


def reachable_boxes(dynamics, x_low, x_high, actions, w_low, w_high, method: str = "both", x_high_open=None,
                    noise_open: bool = False, staged: bool = True):
    """Enclosures of Reach for every (state box, action, noise box) triple.

    Args:
        dynamics: ``f(x (n,), u (m,), w (d,)) -> (n,)``.
        x_low, x_high: ``(R, n)`` state boxes.
        actions: ``(A, m)`` inputs shared by all states, or ``(R, A, m)`` per state.
        w_low, w_high: ``(C, d)`` noise boxes (bounded).
        method: ``"natural"``, ``"centered"`` or ``"both"`` (their intersection).
        x_high_open: optional ``(R, n)`` bool: the state box excludes its upper face there
            (half-open cells). When given, the upper ends' open flags are returned too.
        noise_open: the noise has a density, so no noise box attains its faces with positive
            probability.
        staged: store every intermediate that depends on fewer of (state, action, noise) than
            its consumer (e.g. the cos of a heading interval, once per state instead of once per
            (state, action, noise) triple). The same bounds bit for bit; on the CPU 2-3x faster
            for dynamics with costly per-state terms.

    Returns:
        ``(lo, hi)``, each ``(R, A, C, n)``, with ``f(x, u_a, w) in [lo, hi]`` for all x, w in
        the boxes, rounding included; with ``x_high_open``, also ``hi_open (R, A, C, n)``: the
        next state is almost surely below ``hi`` there (see `interval_eval`).
    """
    with_open = x_high_open is not None

    def one(xl, xh, xo, u, wl, wh):
        if not with_open:
            return enclose(dynamics, (xl, u, wl), (xh, u, wh), method, staged=staged)
        w_open = jnp.full(wl.shape, bool(noise_open))
        lo, hi, _, hi_open = enclose(dynamics, (xl, u, wl), (xh, u, wh), method,
                                     open_lows=(False, False, w_open), open_highs=(xo, False, w_open),
                                     with_open=True, staged=staged)
        return lo, hi, hi_open

    over_noise = jax.vmap(one, in_axes=(None, None, None, None, 0, 0))
    over_actions = jax.vmap(over_noise, in_axes=(None, None, None, 0, None, None))
    actions = jnp.asarray(actions)
    over_states = jax.vmap(over_actions, in_axes=(0, 0, 0 if with_open else None,
                                                  0 if actions.ndim == 3 else None, None, None))
    x_low = jnp.asarray(x_low)
    return over_states(x_low, jnp.asarray(x_high), x_high_open, actions,
                       jnp.asarray(w_low), jnp.asarray(w_high))
