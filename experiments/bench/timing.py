"""Timing of the jitted step loop: compile once, run consecutive chunks, time
each with ``block_until_ready``."""
from __future__ import annotations

import time

import numpy as np
import jax
import jax.numpy as jnp

from jdem import integrate

def block(x):
    return jax.block_until_ready(x)


def time_fn(fn, *args, repeats=15, warm=1):
    """Compile ``jax.jit(fn)`` and time calls; returns dict (ms) and the last output."""
    jitted = jax.jit(fn)
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    out = None
    for _ in range(warm):
        out = block(compiled(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = block(compiled(*args))
        times.append(time.perf_counter() - t0)
    times = np.array(times) * 1e3
    return dict(best_ms=float(times.min()), median_ms=float(np.median(times)),
                repeats=repeats, compile_s=compile_s), out


def make_chunk(config, k):
    def chunk(state, params):
        return jax.lax.fori_loop(0, k, lambda _, s: integrate.step(s, params, config), state)

    return jax.jit(chunk)


def capacity(state):
    """Rows of the neighbour list (the length of the Contacts arrays)."""
    return int(state.contacts.i.shape[-1])


def all_finite(state):
    p = state.particles
    return bool(jnp.all(jnp.isfinite(p.pos)) & jnp.all(jnp.isfinite(p.vel))
                & jnp.all(jnp.isfinite(p.angvel))) and int(state.first_bad_step) < 0
