"""Solving a batch of texels in lanes: every texel's Levenberg-Marquardt solve, P at a time, a lane
taking the next texel as soon as its own is done.

A vmapped while loop runs until the slowest texel of its batch is done: with texels that take 6
steps and a few that take 40, a batch of 32 costs 40 steps per texel (measured on a DiLiGenT
object: median 6 steps, 33 steps for the slowest of each 32). Here the loop steps P lanes at once;
a lane whose texel has finished writes its result and loads the next texel of the batch, so the
work is the sum of the texels' steps (plus the last texels' tail), not the slowest one's times the
batch. A texel's solve is the same sequence of operations on its own data whatever lane it runs in
and whenever: its result does not depend on the batch, its place in it, or the device.

A backend that steps (`fitting.lm_native.Steps`, `fitting.lm_optimistix.Steps`) gives `start(theta0,
problem)`, `step(state, problem)`, `running(state)` and `result(state)` -> (theta, converged, steps)
for one texel.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["solve_in_lanes", "LANES"]

LANES = 64   # texels stepped at once (a multiple of the 16 float32 lanes of a 64-byte vector)


def _where(mask, new, old):
    return jax.tree.map(lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old)


def solve_in_lanes(steps, theta0, per_texel, make, active=None):
    """(theta `N 4`, converged `N`, steps `N`) of every texel's solve from `theta0` (`N 4`): the
    problem of texel i is `make(x[i] for every leaf x of per_texel)`.

    `active` (a traced integer, None: N): only the first `active` texels are solved; the rest
    (a batch's padding) are left at zero and cost nothing. A solved texel's result is the same
    whatever `active` is: the lanes take the texels in the same order."""
    n = theta0.shape[0]
    active = n if active is None else jnp.minimum(active, n)
    lanes = LANES   # always: a lane's arithmetic has one vector shape whatever the batch (bit-identical results)

    def problem_of(index):
        i = jnp.minimum(index, n - 1)
        return jax.tree.map(lambda x: x[i], per_texel)

    def start(index):
        return jax.vmap(lambda th, p: steps.start(th, make(p)))(theta0[jnp.minimum(index, n - 1)], problem_of(index))

    index = jnp.arange(lanes)
    state = start(index)
    out = (jnp.zeros((n + 1,) + theta0.shape[1:], theta0.dtype), jnp.zeros(n + 1, bool), jnp.zeros(n + 1, jnp.int32))

    def cond(carry):
        return jnp.any(carry[0] < active)

    def body(carry):
        index, following, state, out = carry
        state = jax.vmap(lambda st, p: steps.step(st, make(p)))(state, problem_of(index))
        done = ~jax.vmap(steps.running)(state) & (index < active)
        theta, ok, count = jax.vmap(steps.result)(state)
        slot = jnp.where(done, index, n)   # row n: a sink for the lanes that write nothing
        out = (out[0].at[slot].set(theta), out[1].at[slot].set(ok), out[2].at[slot].set(count.astype(jnp.int32)))
        rank = jnp.cumsum(done) - 1
        index = jnp.where(done, jnp.minimum(following + rank, active), index)
        following = following + jnp.sum(done)
        state = _where(done & (index < active), start(index), state)
        return index, following, state, out

    _, _, _, out = jax.lax.while_loop(cond, body, (index, jnp.asarray(lanes), state, out))
    return out[0][:n], out[1][:n], out[2][:n]
