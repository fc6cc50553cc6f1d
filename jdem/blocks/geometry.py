"""Rigid convex polygonal blocks in 2D: the bodies of the block method (000 ch. 2).

Citations ("000 eq 2-22") refer to the documents listed in REFERENCES.md.

A block is a convex polygon with its vertices stored counter-clockwise relative
to its centroid, so its shape never changes; its place is the centroid ``pos``
and the rotation ``angle`` (000 eq 2-22 maps a local vertex to global
coordinates; the angle is kept exactly rather than as the incremental SIN / COS
of 000 eq 2-23, 2-24, which then need no renormalisation).

Capacity: ``B`` blocks of at most ``V`` vertices.  A polygon with n < V vertices
repeats its first vertex in the padding rows, so that edge k always runs from
vertex k to vertex k + 1 (the last real edge closes on the first vertex) and
the padding edges have zero length; ``vert_valid`` masks them.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jdem.validate import InputError

Array = jnp.ndarray


class Blocks(NamedTuple):
    """Rigid blocks; capacity ``B`` rows of at most ``V`` vertices.

    pos         (B, 2)    centroid [m]
    angle       (B,)      rotation from the reference shape [rad], counter-clockwise
    vel         (B, 2)    centroid velocity [m/s] (at the half step)
    angvel      (B,)      angular velocity [rad/s]
    verts       (B, V, 2) vertices relative to the centroid in the reference
                          orientation [m], counter-clockwise, padded with vertex 0
    vert_valid  (B, V)    bool: vertex k (and edge k -> k+1) is real
    radius      (B,)      bounding radius about the centroid [m] (broad phase)
    mass        (B,)      [kg]
    inertia     (B,)      polar moment about the centroid [kg m^2]
    material    (B,)      int index into the joint tables of ``BlockParams``
    fixed       (B,)      bool: the block's velocity and spin are prescribed
                          (they keep their value; a fixed block may still move)
    ext_force   (B, 2)    applied force [N]
    ext_torque  (B,)      applied moment [N m]
    valid       (B,)      bool: row holds a real block
    """

    pos: Array
    angle: Array
    vel: Array
    angvel: Array
    verts: Array
    vert_valid: Array
    radius: Array
    mass: Array
    inertia: Array
    material: Array
    fixed: Array
    ext_force: Array
    ext_torque: Array
    valid: Array


def signed_area(vertices):
    """Signed area [m^2] of a polygon (n, 2) (NumPy, shoelace): positive when the
    vertices run counter-clockwise."""
    v = np.asarray(vertices, dtype=np.float64)
    x, y = v[:, 0], v[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def polygon_properties(vertices):
    """Area [m^2], centroid (2,) [m] and polar second moment of area about the
    centroid [m^4] of a simple polygon (NumPy; shoelace formulae).

    vertices  (n, 2) in either order; the area returned is positive and the
              vertices of a clockwise polygon are reversed by :func:`make_blocks`.
    """
    v = np.asarray(vertices, dtype=np.float64)
    x, y = v[:, 0], v[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    a2 = cross.sum()                       # twice the signed area
    if abs(a2) == 0.0:
        raise InputError("a block polygon has zero area")
    cx = ((x + xn) * cross).sum() / (3.0 * a2)
    cy = ((y + yn) * cross).sum() / (3.0 * a2)
    # second moments about the origin, then moved to the centroid
    ixx = ((y * y + y * yn + yn * yn) * cross).sum() / 12.0
    iyy = ((x * x + x * xn + xn * xn) * cross).sum() / 12.0
    area = 0.5 * a2
    polar = (ixx + iyy) - area * (cx * cx + cy * cy)
    return abs(area), np.array([cx, cy]), abs(polar)


def _check_convex(v, k):
    e = np.roll(v, -1, axis=0) - v
    cross = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
    scale = np.max(np.abs(cross)) if cross.size else 0.0
    if np.any(cross < -1e-12 * scale):
        raise InputError(f"block {k} is not convex (vertex order after orienting "
                         f"counter-clockwise: {v.tolist()})")
    if np.any(np.linalg.norm(e, axis=1) == 0.0):
        raise InputError(f"block {k} has two equal consecutive vertices")


def make_blocks(polygons, density, *, fixed=None, vel=None, angvel=None, material=None,
                capacity=None, max_vertices=None, dtype=None) -> Blocks:
    """Blocks from a list of convex polygons (each (n_k, 2) global vertices [m]).

    density   [kg/m^3] (per unit thickness in 2D), a number or one per block
    fixed     indices or a (B,) bool mask of blocks whose motion is prescribed
    vel, angvel  initial velocities (B, 2) [m/s], (B,) [rad/s]
    material  (B,) ints: each block's row in the joint tables (default 0)
    capacity  rows to allocate (default: the number of polygons)
    max_vertices  V (default: the largest polygon)
    dtype     float dtype (default: JAX's default float)
    """
    polys = [np.asarray(p, dtype=np.float64) for p in polygons]
    if not polys:
        raise InputError("make_blocks needs at least one polygon, got none")
    n = len(polys)
    for k, p in enumerate(polys):
        if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 3:
            raise InputError(f"polygon {k} must be an (n >= 3, 2) array of vertices, "
                             f"got shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise InputError(f"polygon {k} has a non-finite vertex")
    cap = n if capacity is None else int(capacity)
    if cap < n:
        raise InputError(f"capacity={cap} is below the number of polygons ({n})")
    nv = max(p.shape[0] for p in polys) if max_vertices is None else int(max_vertices)
    dens = np.broadcast_to(np.asarray(density, dtype=np.float64), (n,))
    if np.any(~np.isfinite(dens)) or np.any(dens <= 0):
        raise InputError(f"density must be finite and > 0, got {np.asarray(density)!r}")
    pos = np.zeros((cap, 2))
    verts = np.zeros((cap, nv, 2))
    vvalid = np.zeros((cap, nv), bool)
    radius = np.zeros(cap)
    mass = np.ones(cap)
    inertia = np.ones(cap)
    for k, p in enumerate(polys):
        if p.shape[0] > nv:
            raise InputError(f"polygon {k} has {p.shape[0]} vertices, above "
                             f"max_vertices={nv}")
        area, c, polar = polygon_properties(p)
        local = (p if signed_area(p) > 0 else p[::-1]) - c
        _check_convex(local, k)
        m = local.shape[0]
        verts[k, :m] = local
        verts[k, m:] = local[0]
        vvalid[k, :m] = True
        pos[k] = c
        radius[k] = np.max(np.linalg.norm(local, axis=1))
        mass[k] = dens[k] * area
        inertia[k] = dens[k] * polar
    fixed_mask = np.zeros(cap, bool)
    if fixed is not None:
        f = np.asarray(fixed)
        if f.dtype == bool:
            if f.shape != (n,) and f.shape != (cap,):
                raise InputError(f"fixed mask must have shape ({n},), got {f.shape}")
            fixed_mask[:f.shape[0]] = f
        else:
            if f.size and (f.min() < 0 or f.max() >= n):
                raise InputError(f"fixed block index out of range 0..{n - 1}: {f.tolist()}")
            fixed_mask[f.astype(int)] = True
    v0 = np.zeros((cap, 2))
    w0 = np.zeros(cap)
    if vel is not None:
        v = np.asarray(vel, dtype=np.float64)
        if v.shape not in ((n, 2), (2,)):
            raise InputError(f"vel must have shape ({n}, 2) or (2,), got {v.shape}")
        v0[:n] = v
    if angvel is not None:
        w = np.asarray(angvel, dtype=np.float64)
        if w.shape not in ((n,), ()):
            raise InputError(f"angvel must have shape ({n},) or (), got {w.shape}")
        w0[:n] = w
    mat = np.zeros(cap, np.int32)
    if material is not None:
        mm = np.asarray(material)
        if mm.shape != (n,) or not np.issubdtype(mm.dtype, np.integer) or np.any(mm < 0):
            raise InputError(f"material must be ({n},) non-negative ints, got {mm!r}")
        mat[:n] = mm
    valid = np.arange(cap) < n
    f = jnp.zeros(()).dtype if dtype is None else dtype
    a = lambda x: jnp.asarray(x, f)   # noqa: E731
    return Blocks(pos=a(pos), angle=a(np.zeros(cap)), vel=a(v0), angvel=a(w0),
                  verts=a(verts), vert_valid=jnp.asarray(vvalid), radius=a(radius),
                  mass=a(mass), inertia=a(inertia), material=jnp.asarray(mat),
                  fixed=jnp.asarray(fixed_mask),
                  ext_force=a(np.zeros((cap, 2))), ext_torque=a(np.zeros(cap)),
                  valid=jnp.asarray(valid))


def rotation(angle):
    """Rotation matrices (..., 2, 2) for angles (...) [rad]."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)


def world_vertices(blocks: Blocks):
    """Global vertex coordinates (B, V, 2) [m] (000 eq 2-22)."""
    rot = rotation(blocks.angle)
    return blocks.pos[:, None, :] + jnp.einsum("bij,bvj->bvi", rot, blocks.verts)


def rectangle(x0, y0, width, height):
    """The four corners (4, 2) of an axis-aligned rectangle, counter-clockwise [m]."""
    return np.array([[x0, y0], [x0 + width, y0], [x0 + width, y0 + height],
                     [x0, y0 + height]], dtype=np.float64)
