"""Small vector helpers shared by contacts, bonds and walls, generic over 2D / 3D.

Citations ("000 eq 4-11") refer to the documents listed in REFERENCES.md.

In 2D an angular velocity or torque is a scalar about the out-of-plane axis
(shape ``(...,)``); in 3D it is a vector (shape ``(..., 3)``).  These helpers
hide that difference so force laws are written once.

A vector field is either an array ``(..., d)`` or a *component tuple*: ``d``
arrays of shape ``(...)``, one per axis (see :func:`components`).  Every helper
takes either and returns the same kind it was given.  The per-pair force laws
work on component tuples: XLA on CPU then runs each component as a contiguous
(R,) loop and keeps each intermediate array once, whereas on ``(R, d)`` rows
with d = 2 or 3 it vectorises poorly and recomputes shared per-pair terms in
every fused consumer (about 3x slower for the 3D contact kernel).

Reductions over the short axis (d = 2 or 3) are written out component by
component: ``a[..., 0] * b[..., 0] + ...`` vectorises over the long axis, while
``jnp.sum(a * b, axis=-1)`` over a minor axis of length 3 runs several times
slower on XLA:CPU.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def components(v):
    """The ``d`` components of a vector field: ``v`` itself if it is a component
    tuple, else the tuple ``(v[..., 0], ..., v[..., d-1])``."""
    if isinstance(v, tuple):
        return v
    return tuple(v[..., k] for k in range(v.shape[-1]))


def same_kind(parts, v):
    """Return ``parts`` in the kind of ``v``: a tuple, or stacked on a last axis."""
    return tuple(parts) if isinstance(v, tuple) else jnp.stack(parts, axis=-1)


def dim_of(v):
    """Number of components d of a vector field."""
    return len(v) if isinstance(v, tuple) else v.shape[-1]


def scale(s, v):
    """Each row of the vector field ``v`` times the scalar field ``s`` (...).

    ``v`` may also be a scalar field of the shape of ``s`` (a 2D spin or torque).
    """
    if isinstance(v, tuple):
        return tuple(s * c for c in v)
    if v.ndim == jnp.ndim(s):
        return s * v
    return s[..., None] * v


def rows(field, index):
    """Rows ``index`` (R,) of a per-particle field: an (N,) scalar field gives (R,)
    (a 2D spin), an (N, d) array a component tuple of d (R,) arrays."""
    if field.ndim == 1:
        return field[index]
    return tuple(c[index] for c in components(field))


def _cross3(a, b):
    ax, ay, az = components(a)
    bx, by, bz = components(b)
    return same_kind([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], b)


def cross_w_r(w, r):
    """Velocity ``w x r`` of a point at offset ``r`` (..., d) on a body spinning at ``w``."""
    if dim_of(r) == 2:
        rx, ry = components(r)
        return same_kind([-w * ry, w * rx], r)
    return _cross3(w, r)


def cross_r_f(r, f):
    """Torque ``r x f`` of force ``f`` (..., d) at offset ``r``; scalar in 2D."""
    if dim_of(r) == 2:
        rx, ry = components(r)
        fx, fy = components(f)
        return rx * fy - ry * fx
    return _cross3(r, f)


def relative_velocity(vel, spin, i, j, arm_i, arm_j):
    """Velocity of the point at offset ``arm_i`` on body i relative to the point at
    ``arm_j`` on body j, (v_i + w_i x arm_i) - (v_j + w_j x arm_j) (000 eq 4-11..4-15).

    vel (N, d) and spin ((N,) in 2D, (N, 3) in 3D) are per-particle fields; i, j (R,)
    the rows; the arms component tuples of (R,) arrays.  Returns a component tuple.
    """
    return tuple((vi + si) - (vj + sj) for vi, vj, si, sj in
                 zip(rows(vel, i), rows(vel, j), cross_w_r(rows(spin, i), arm_i),
                     cross_w_r(rows(spin, j), arm_j)))


def dot(a, b):
    """Row-wise dot product over the components (written out, see the module note)."""
    pa, pb = components(a), components(b)
    out = pa[0] * pb[0]
    for k in range(1, len(pa)):
        out = out + pa[k] * pb[k]
    return out


def safe_norm(v, eps=0.0):
    """Euclidean norm over the components whose gradient is finite at zero."""
    sq = dot(v, v)
    pos = sq > eps * eps
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def floored_norm(v):
    """Euclidean norm floored at the smallest normal number of its dtype: never zero,
    so it can divide, and its gradient is finite everywhere (zero below the floor).

    Written as one ``sqrt`` of a ``maximum``: XLA:CPU then computes it once,
    whereas the masked form of :func:`safe_norm` used as a divisor made it
    recompute the whole per-pair chain inside every consumer.
    """
    sq = dot(v, v)
    return jnp.sqrt(jnp.maximum(sq, jnp.finfo(sq.dtype).tiny))


def unit(v):
    """Unit vector along the components, and the length; zero vectors give a zero unit."""
    n = safe_norm(v)
    den = jnp.where(n > 0, n, 1.0)
    if isinstance(v, tuple):
        return tuple(c / den for c in v), n
    return v / den[..., None], n


def project_tangent(vec, normal):
    """Remove the component of ``vec`` along the unit ``normal``."""
    along = dot(vec, normal)
    if isinstance(vec, tuple):
        return tuple(v - along * n for v, n in zip(vec, components(normal)))
    return vec - along[..., None] * normal


def rotate_into_plane(vec, normal):
    """Turn a stored tangential vector into the current tangent plane, keeping its
    length (the usual incremental-history update when the contact normal rotates)."""
    old = safe_norm(vec)
    proj = project_tangent(vec, normal)
    new = safe_norm(proj)
    return scale(jnp.where(new > 0, old / jnp.where(new > 0, new, 1.0), 0.0), proj)


def segment_add(values, index, n, where=None):
    """Sum rows of ``values`` (R, ...) into ``n`` bins given by ``index`` (R,) (scatter-add).

    ``values`` may also be a component tuple of (R,) arrays; the result is then an
    (n, d) array.  Rows with ``where`` False are left out (sent past the last bin
    and dropped).  Their values must be zero, so the sums are the same either way;
    leaving them out matters on GPUs, where a scatter is a set of atomic adds and
    the padding rows of a list (all pointing at particle 0) would serialise on one
    address.
    """
    if where is not None:
        index = jnp.where(where, index, n)
    if isinstance(values, tuple):
        return jnp.stack([segment_add(c, index, n) for c in values], axis=-1)
    return jnp.zeros((n,) + values.shape[1:], values.dtype).at[index].add(values, mode="drop")


COMPUTED_ONCE_MIN_ROWS = 16384  # see computed_once


def computed_once(fn, always_true, min_rows=None):
    """``fn()``, evaluated as a computation of its own so that its outputs are
    arrays in memory, each computed once.

    XLA:CPU fuses a long elementwise chain (e.g. the per-pair contact law) into
    every fused consumer of its results and recomputes it there: for the 3D
    contact kernel a dozen times (shear columns, force and torque rows for both
    sides).  A branch of a conditional is not fused with the code around it, so
    ``fn`` runs inside ``lax.cond(always_true, fn, zeros)``.  ``always_true`` must
    be a traced boolean scalar that is true (the zero branch is never meant to
    run); it has to be traced, or XLA folds the conditional away.  Under ``vmap``
    a batched predicate turns the conditional into a select (both branches are
    evaluated, the zero one costs nothing); gradients pass through ``fn``.

    Small problems (outputs below ``min_rows`` rows, default
    ``COMPUTED_ONCE_MIN_ROWS``) call ``fn`` directly: there the conditional's
    fixed cost per step outweighs the recomputation (the contact law of a
    1,047-disc UCS forward run took 2.76 s with it, 2.40 s without);
    ``min_rows=0`` keeps the conditional at every size (the bond law, see
    :func:`jdem.bond.bond_forces`).  Other backends than the CPU call ``fn``
    directly too: this works around XLA:CPU's fusion, and on a GPU a conditional
    may wait for the host to read its predicate (the GPU figures in the README
    were measured without it).  The results are the same either way.
    """
    shapes = jax.eval_shape(fn)
    if (jax.default_backend() != "cpu"
            or max(s.size for s in jax.tree_util.tree_leaves(shapes))
            < (COMPUTED_ONCE_MIN_ROWS if min_rows is None else min_rows)):
        return fn()
    zeros = lambda: jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)  # noqa: E731
    return jax.lax.cond(always_true, fn, zeros)
