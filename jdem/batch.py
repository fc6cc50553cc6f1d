"""Batches: a leading member axis on every leaf of a pytree (state, params, history).

One place for the four things every batched caller needs:

* :func:`is_batched` -- whether ``params`` carry a member axis;
* :func:`broadcast_batch` -- repeat a pytree along a new member axis;
* :func:`member` -- take member ``b`` of a batched pytree or history dict
  (:func:`put_member` puts one back);
* :func:`stack_states` -- put the states of *different* specimens (an ensemble of
  packings) on one member axis, padded to common capacities, with one search
  grid that covers them all.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jdem import neighbors
from jdem.simulate import make_config
from jdem.state import empty_bonds


def is_batched(params) -> bool:
    """True if ``params`` carry a leading member axis (``params.dt`` has shape (B,))."""
    return np.ndim(params.dt) == 1


def broadcast_batch(tree, batch: int):
    """Repeat every leaf of ``tree`` along a new leading axis of size ``batch``."""
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (batch,) + jnp.shape(a)), tree)


def member(tree, b: int):
    """Member ``b`` of a batched pytree (state, params) or history dict (NumPy)."""
    if isinstance(tree, dict):
        return {k: np.asarray(v)[b] for k, v in tree.items()}
    return jax.tree_util.tree_map(lambda a: a[b], tree)


def put_member(tree, b: int, value):
    """``tree`` (batched) with member ``b`` replaced by the unbatched ``value``."""
    return jax.tree_util.tree_map(lambda a, v: a.at[b].set(v), tree, value)


def _pad_rows(a, n, fill=0):
    extra = n - a.shape[0]
    if extra == 0:
        return a
    return jnp.concatenate([a, jnp.full((extra,) + a.shape[1:], fill, a.dtype)])


def pad_particles(p, n):
    """Particles padded with invalid rows to capacity ``n`` (unit mass and inertia,
    so that nothing divides by zero)."""
    fill = dict(mass=1.0, inertia=1.0)
    return p._replace(**{name: _pad_rows(a, n, fill.get(name, 0))
                         for name, a in p._asdict().items()})


def pad_bonds(b, n, dim):
    """Bonds padded with invalid rows to capacity ``n``."""
    extra = n - b.i.shape[0]
    if extra == 0:
        return b
    pad = empty_bonds(dim, extra, b.normal_force.dtype)
    return jax.tree_util.tree_map(lambda a, e: jnp.concatenate([a, e]), b, pad)


def stack_states(states, dim):
    """States of different specimens on one member axis.

    Pads particles, bonds, wall histories and neighbour lists to the largest
    capacity of any member, makes one search grid covering every member and
    rebuilds each list on it.  Returns ``(state (B, ...), config)``.
    """
    n = max(s.particles.pos.shape[0] for s in states)
    nb = max(s.bonds.i.shape[0] for s in states)
    parts = [pad_particles(s.particles, n) for s in states]
    bonds = [pad_bonds(s.bonds, nb, dim) for s in states]
    walls = []
    for s in states:
        w = s.walls
        extra = n - w.shear.shape[1]
        z = jnp.zeros((w.shear.shape[0], extra, w.shear.shape[2]), w.shear.dtype)
        walls.append(w._replace(shear=jnp.concatenate([w.shear, z], axis=1)))
    union = parts[0]._replace(
        pos=jnp.concatenate([p.pos for p in parts]),
        radius=jnp.concatenate([p.radius for p in parts]),
        valid=jnp.concatenate([p.valid for p in parts]))
    config = make_config(union)
    built = []
    for p, b in zip(parts, bonds):
        c, config = neighbors.allocate(p, config, b)
        built.append((p, b, c))
    cap = max(c.i.shape[0] for _, _, c in built)
    members = []
    for (p, b, c), w, s in zip(built, walls, states):
        c, config = neighbors.reallocate(c, p, config, b, capacity=cap)
        members.append(s._replace(particles=p, bonds=b, contacts=c, walls=w))
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *members), config
