"""Contact detection between convex blocks (000 §2.3.3, §3.4.1).

Citations ("000 §3.4.1") refer to the documents listed in REFERENCES.md.

Broad phase: the blocks' bounding circles go through the particles' cell list
(:mod:`jdem.neighbors`), so blocks get the same fixed capacity, overflow flag,
re-allocation verb and history carry-over as discs: a pair (i < j) is listed
while the circles are closer than the skin, and the list is rebuilt when some
centroid has moved half the skin (a bounding circle about the centroid does not
change as the block turns).

Narrow phase, per listed pair: the book treats an edge–edge contact as two
corner–edge contacts and warns that corner–corner contacts need their own
criterion (000 §3.4.1, fig 3-11; corner rounding, eq 3-34, 3-35, is its other
remedy).  Here the reference edge is the edge of either block with the
largest separation from the other block (the separating-axis measure); the
incident edge of the other block is its edge most nearly opposed to it, and is
clipped to the reference edge's extent.  The (at most two) clipped end points
below the reference edge are the contacts: two for an edge–edge contact
(flush faces, however aligned their corners are), one for a corner–edge contact.
Each point's separation is its signed distance from the reference edge's line
(negative: overlap), and the contact point lies halfway across the overlap.

Per pair the result is oriented from block i to block j: ``normal`` points
from i into j, and a positive normal force pushes j along it.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jdem.blocks.geometry import Blocks, world_vertices
from jdem.state import Particles

POINTS_PER_PAIR = 2


class PairGeometry(NamedTuple):
    """Contact geometry of the listed pairs (C pairs, 2 points each).

    normal      (C, 2)    unit normal from block i into block j
    point       (C, 2, 2) contact points [m]
    separation  (C, 2)    signed gap along ``normal`` [m]; negative: overlap
    exists      (C, 2)    bool: the clipped point exists (a pair whose incident
                          edge is clipped away has none)
    length      (C,)      length of the clipped incident edge [m] (0 for a
                          corner–edge contact)
    """

    normal: jnp.ndarray
    point: jnp.ndarray
    separation: jnp.ndarray
    exists: jnp.ndarray
    length: jnp.ndarray


def bounding_circles(blocks: Blocks) -> Particles:
    """The blocks' bounding circles as :class:`jdem.state.Particles` (position,
    radius and validity are what the cell list reads; the rest is zero)."""
    b, f = blocks.pos.shape[0], blocks.pos.dtype
    z1 = jnp.zeros((b,), f)
    z2 = jnp.zeros((b, 2), f)
    return Particles(pos=blocks.pos, pos_lo=z2, vel=blocks.vel, angvel=blocks.angvel, radius=blocks.radius,
                     mass=blocks.mass, gravity_mass=blocks.mass, inertia=blocks.inertia,
                     material=jnp.zeros((b,), jnp.int32), fixed_vel=jnp.zeros((b, 2), bool),
                     fixed_rot=jnp.zeros((b,), bool), ext_force=z2, ext_torque=z1,
                     valid=blocks.valid)


def _edges(verts, valid):
    """Start points, outward unit normals and lengths of a CCW polygon's edges."""
    nxt = jnp.roll(verts, -1, axis=0)
    e = nxt - verts
    length = jnp.sqrt(jnp.sum(e * e, axis=-1))
    safe = jnp.where(valid & (length > 0), length, 1.0)
    normal = jnp.stack([e[:, 1], -e[:, 0]], axis=-1) / safe[:, None]
    return verts, nxt, normal, valid & (length > 0)


def _max_separation(start_a, normal_a, edge_ok_a, verts_b, valid_b):
    """For each edge k of A, the least signed distance of B's vertices from its
    line; returns the largest over the edges and its index."""
    d = normal_a @ verts_b.T - jnp.sum(normal_a * start_a, axis=-1)[:, None]   # (V, V)
    d = jnp.where(valid_b[None, :], d, jnp.inf)
    sep = jnp.where(edge_ok_a, jnp.min(d, axis=1), -jnp.inf)
    k = jnp.argmax(sep)
    return sep[k], k


def _clip(p, q, t, lo, hi):
    """Parameters [s0, s1] of the part of segment p + s (q - p), 0 <= s <= 1,
    with lo <= t . x <= hi; s0 > s1 when nothing is left."""
    a, b = jnp.dot(t, p), jnp.dot(t, q - p)
    tiny = jnp.abs(b) < 1e-30
    safe = jnp.where(tiny, 1.0, b)
    s_lo, s_hi = (lo - a) / safe, (hi - a) / safe
    s0 = jnp.where(tiny, jnp.where((a >= lo) & (a <= hi), 0.0, 2.0),
                   jnp.maximum(0.0, jnp.minimum(s_lo, s_hi)))
    s1 = jnp.where(tiny, jnp.where((a >= lo) & (a <= hi), 1.0, -1.0),
                   jnp.minimum(1.0, jnp.maximum(s_lo, s_hi)))
    return s0, s1


def rounded_core(verts, valid, radius):
    """The core of a convex polygon (V, 2) whose corners are rounded with arcs of
    ``radius`` [m] (000 fig 3-12): every edge moved inward by the radius, each
    vertex to the meeting point of its two moved edges (the centre of its arc,
    on the bisector).  The rounded block is the core grown by the radius."""
    # the neighbours of each valid vertex (valid vertices come first, padding after)
    count = jnp.sum(valid)
    idx = jnp.arange(verts.shape[0])
    prev = jnp.where(idx == 0, count - 1, idx - 1)
    nxt = jnp.where(idx == count - 1, 0, idx + 1)
    e_out = verts[nxt] - verts
    e_in = verts - verts[prev]

    def inward(e):
        length = jnp.sqrt(jnp.sum(e * e, axis=-1, keepdims=True))
        return jnp.stack([-e[:, 1], e[:, 0]], axis=-1) / jnp.where(length > 0, length, 1.0)

    n1, n2 = inward(e_in), inward(e_out)              # CCW: the left normal points in
    cos = jnp.sum(n1 * n2, axis=-1, keepdims=True)
    shift = radius * (n1 + n2) / jnp.maximum(1.0 + cos, 1e-12)
    core = verts + shift
    # padding rows repeat vertex 0 (jdem.blocks.geometry), so that the last valid
    # edge closes the polygon: keep them on the core's vertex 0
    return jnp.where(valid[:, None], core, core[0])


def _closest_vertices(verts_i, valid_i, verts_j, valid_j):
    """The closest pair of vertices of two polygons: (distance, unit vector from
    the vertex of i to that of j, the vertex of i, the vertex of j)."""
    d = verts_j[None, :, :] - verts_i[:, None, :]
    dist2 = jnp.where(valid_i[:, None] & valid_j[None, :], jnp.sum(d * d, axis=-1), jnp.inf)
    k = jnp.argmin(dist2)
    a, b = k // verts_j.shape[0], k % verts_j.shape[0]
    # sqrt only where positive: two coincident vertices (a list's padding rows pair
    # a block with itself) would otherwise give an infinite derivative, and a NaN
    # gradient through the masked row
    apart = dist2[a, b] > 0
    best = jnp.where(apart, jnp.sqrt(jnp.where(apart, dist2[a, b], 1.0)), 0.0)
    return best, d[a, b] / jnp.where(apart, best, 1.0), verts_i[a], verts_j[b]


def pair_geometry_one(verts_i, valid_i, verts_j, valid_j, scale, corner_radius=0.0):
    """Contact geometry of one pair of convex polygons (world vertices (V, 2)).

    ``scale`` [m] sets the tie-break between two equally good reference edges
    (block i's edge is kept unless j's is better by 1e-6 scale), so that the
    choice does not flip at round-off.  ``corner_radius`` [m] rounds every
    corner (000 eq 3-34, 3-35): the cores (:func:`rounded_core`) are clipped as
    below and every gap is the cores' gap less twice the radius, so flat faces
    touch as before (over the straight part of the face) while a corner meets a
    face with its arc (eq 3-35); where the clipped contact of the cores is empty
    (two corners meeting, 000 fig 3-11), the contact is one point on the line
    joining the two nearest arc centres, with the gap |C1 C2| - 2 R (eq 3-34).
    Returns the fields of :class:`PairGeometry` for one pair.
    """
    if isinstance(corner_radius, (int, float)) and corner_radius == 0.0:
        return _clipped_contact(verts_i, valid_i, verts_j, valid_j, scale)[:5]
    return _contact_of_cores(rounded_core(verts_i, valid_i, corner_radius), valid_i,
                             rounded_core(verts_j, valid_j, corner_radius), valid_j, scale,
                             corner_radius)


def _contact_of_cores(core_i, valid_i, core_j, valid_j, scale, radius):
    """:func:`pair_geometry_one` for blocks rounded with ``radius``, given their
    cores (:func:`rounded_core`)."""
    normal, mid, sep, exists, length, apart = _clipped_contact(core_i, valid_i, core_j,
                                                               valid_j, scale)
    # corner meets corner: the cores are apart and the incident edge clipped to the
    # reference edge's extent is empty, so no vertex faces an edge: the nearest
    # features are two vertices (000 fig 3-11, eq 3-34)
    d_vv, n_vv, ci, cj = _closest_vertices(core_i, valid_i, core_j, valid_j)
    corner = (radius > 0) & apart & ~jnp.any(exists)
    vv_point = jnp.stack([0.5 * (ci + cj), 0.5 * (ci + cj)])
    normal = jnp.where(corner, n_vv, normal)
    mid = jnp.where(corner, vv_point, mid)
    sep = jnp.where(corner, jnp.stack([d_vv, jnp.inf]), sep) - 2.0 * radius
    exists = jnp.where(corner, jnp.array([True, False]), exists)
    length = jnp.where(corner, 0.0, length)
    return normal, mid, sep, exists, length


def _clipped_contact(verts_i, valid_i, verts_j, valid_j, scale):
    """The clipped reference-edge contact of two convex polygons (module docstring):
    normal, points, gaps, exists, length, and whether a separating axis exists."""
    si, ei, ni, oki = _edges(verts_i, valid_i)
    sj, ej, nj, okj = _edges(verts_j, valid_j)
    sep_i, ki = _max_separation(si, ni, oki, verts_j, valid_j)
    sep_j, kj = _max_separation(sj, nj, okj, verts_i, valid_i)
    flip = sep_j > sep_i + 1e-6 * scale          # reference edge on block j

    ref_start = jnp.where(flip, sj[kj], si[ki])
    ref_end = jnp.where(flip, ej[kj], ei[ki])
    ref_n = jnp.where(flip, nj[kj], ni[ki])
    inc_start = jnp.where(flip, si, sj)
    inc_end = jnp.where(flip, ei, ej)
    inc_n = jnp.where(flip, ni, nj)
    inc_ok = jnp.where(flip, oki, okj)
    m = jnp.argmin(jnp.where(inc_ok, inc_n @ ref_n, jnp.inf))
    p, q = inc_start[m], inc_end[m]

    t = ref_end - ref_start
    t = t / jnp.sqrt(jnp.sum(t * t))
    s0, s1 = _clip(p, q, t, jnp.dot(t, ref_start), jnp.dot(t, ref_end))
    exists = s0 <= s1
    pts = jnp.stack([p + s0 * (q - p), p + s1 * (q - p)])              # (2, 2)
    sep = pts @ ref_n - jnp.dot(ref_n, ref_start)                      # (2,)
    mid = pts - 0.5 * sep[:, None] * ref_n[None, :]
    length = jnp.where(exists, jnp.abs(s1 - s0) * jnp.sqrt(jnp.sum((q - p) ** 2)), 0.0)
    # the reference normal points out of the reference block into the other
    normal = jnp.where(flip, -ref_n, ref_n)
    apart = jnp.maximum(sep_i, sep_j) > 0
    return normal, mid, sep, jnp.stack([exists, exists & (s1 > s0)]), length, apart


def pair_geometry(blocks: Blocks, i, j, corner_radius=0.0) -> PairGeometry:
    """:func:`pair_geometry_one` for the pairs (i, j) (C,) of a list; corners
    rounded with ``corner_radius`` [m] (0: sharp)."""
    w = world_vertices(blocks)
    valid = blocks.vert_valid
    scale = blocks.radius[i] + blocks.radius[j]
    if isinstance(corner_radius, (int, float)) and corner_radius == 0.0:
        n, pt, sep, ex, length = jax.vmap(pair_geometry_one)(w[i], valid[i], w[j], valid[j],
                                                             scale)
    else:
        # each block's core once, not once per pair
        core = jax.vmap(rounded_core, in_axes=(0, 0, None))(w, valid, corner_radius)
        n, pt, sep, ex, length = jax.vmap(_contact_of_cores, in_axes=(0,) * 5 + (None,))(
            core[i], valid[i], core[j], valid[j], scale, corner_radius)
    return PairGeometry(normal=n, point=pt, separation=sep, exists=ex, length=length)
