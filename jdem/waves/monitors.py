"""Velocity and position records of groups of discs during a run: an
``observe`` function for :func:`jdem.run` / :func:`jdem.rollout`, and helpers
that pick the groups (discs near points, slices across a bar).
"""
from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from jdem.validate import require_finite


@dataclasses.dataclass(frozen=True)
class Monitors:
    """Velocity and position records of groups of discs, an ``observe`` function
    for :func:`jdem.run` / :func:`jdem.rollout` (hashable, so compiled runs are
    reused).  Each group is averaged: ``vel`` (K, d) [m/s], ``pos`` (K, d) [m]."""

    groups: tuple

    def _table(self):
        width = max(len(g) for g in self.groups)
        idx = np.zeros((len(self.groups), width), np.int32)
        w = np.zeros((len(self.groups), width))
        for k, g in enumerate(self.groups):
            idx[k, :len(g)] = g
            w[k, :len(g)] = 1.0 / len(g)
        return idx, w

    def __call__(self, state, params, config):
        idx, w = self._table()
        p = state.particles
        w = jnp.asarray(w, p.pos.dtype)[..., None]
        return dict(time=state.time, vel=jnp.sum(w * p.vel[idx], axis=1),
                    pos=jnp.sum(w * p.pos[idx], axis=1))



def monitor_groups(particles, points, *, radius=None) -> tuple:
    """Groups of disc rows near each point (K, 2) [m]: the nearest valid disc, or
    with ``radius`` [m] every valid disc whose centre lies within it (at least
    the nearest)."""
    pos = np.asarray(particles.pos, np.float64)
    rows = np.nonzero(np.asarray(particles.valid))[0]
    pts = require_finite("points", points).reshape(-1, pos.shape[1])
    groups = []
    for q in pts:
        dist = np.linalg.norm(pos[rows] - q, axis=1)
        near = rows[dist <= radius] if radius is not None else np.zeros(0, np.int64)
        if near.size == 0:
            near = rows[[int(np.argmin(dist))]]
        groups.append(tuple(int(k) for k in near))
    return tuple(groups)



def slice_groups(particles, axis, positions, half_width) -> tuple:
    """Groups of the discs whose centre coordinate along ``axis`` lies within
    ``half_width`` [m] of each position (at least the nearest disc)."""
    pos = np.asarray(particles.pos, np.float64)
    rows = np.nonzero(np.asarray(particles.valid))[0]
    groups = []
    for x in np.atleast_1d(positions):
        dist = np.abs(pos[rows, axis] - x)
        near = rows[dist <= half_width]
        if near.size == 0:
            near = rows[[int(np.argmin(dist))]]
        groups.append(tuple(int(k) for k in near))
    return tuple(groups)
