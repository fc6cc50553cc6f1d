"""Small vector helpers shared by contacts, bonds and walls, generic over 2D / 3D.

In 2D an angular velocity or torque is a scalar about the out-of-plane axis
(shape ``(...,)``); in 3D it is a vector (shape ``(..., 3)``).  These helpers
hide that difference so force laws are written once.

Reductions over the short last axis (d = 2 or 3) are written out component by
component: XLA on CPU vectorises ``a[..., 0] * b[..., 0] + ...`` over the long
axis, while ``jnp.sum(a * b, axis=-1)`` over a minor axis of length 3 runs
several times slower.
"""
from __future__ import annotations

import jax.numpy as jnp


def _cross3(a, b):
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


def cross_w_r(w, r):
    """Velocity ``w x r`` of a point at offset ``r`` (..., d) on a body spinning at ``w``."""
    if r.shape[-1] == 2:
        return jnp.stack([-w * r[..., 1], w * r[..., 0]], axis=-1)
    return _cross3(w, r)


def cross_r_f(r, f):
    """Torque ``r x f`` of force ``f`` (..., d) at offset ``r``; scalar in 2D."""
    if r.shape[-1] == 2:
        return r[..., 0] * f[..., 1] - r[..., 1] * f[..., 0]
    return _cross3(r, f)


def dot(a, b):
    """Row-wise dot product over the last axis (written out, see the module note)."""
    out = a[..., 0] * b[..., 0]
    for k in range(1, a.shape[-1]):
        out = out + a[..., k] * b[..., k]
    return out


def safe_norm(v, eps=0.0):
    """Euclidean norm over the last axis whose gradient is finite at zero."""
    sq = dot(v, v)
    pos = sq > eps * eps
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def unit(v):
    """Unit vector along the last axis, and the length; zero vectors give a zero unit."""
    n = safe_norm(v)
    return v / jnp.where(n > 0, n, 1.0)[..., None], n


def project_tangent(vec, normal):
    """Remove the component of ``vec`` along the unit ``normal``."""
    return vec - dot(vec, normal)[..., None] * normal


def rotate_into_plane(vec, normal):
    """Turn a stored tangential vector into the current tangent plane, keeping its
    length (the usual incremental-history update when the contact normal rotates)."""
    old = safe_norm(vec)
    proj = project_tangent(vec, normal)
    new = safe_norm(proj)
    scale = jnp.where(new > 0, old / jnp.where(new > 0, new, 1.0), 0.0)
    return proj * scale[..., None]


def split_rotation(w, normal):
    """Split a rotation quantity into its twist (along ``normal``, scalar) and bending
    part.  2D: twist is 0 and bending is ``w`` itself."""
    if normal.shape[-1] == 2:
        return jnp.zeros_like(w), w
    tw = dot(w, normal)
    return tw, w - tw[..., None] * normal


def segment_add(values, index, n, where=None):
    """Sum rows of ``values`` (R, ...) into ``n`` bins given by ``index`` (R,) (scatter-add).

    Rows with ``where`` False are left out (sent past the last bin and dropped).
    Their values must be zero, so the sums are the same either way; leaving them
    out matters on GPUs, where a scatter is a set of atomic adds and the padding
    rows of a list (all pointing at particle 0) would serialise on one address.
    """
    if where is not None:
        index = jnp.where(where, index, n)
    return jnp.zeros((n,) + values.shape[1:], values.dtype).at[index].add(values, mode="drop")
