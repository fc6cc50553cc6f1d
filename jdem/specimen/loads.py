"""Faces of a specimen and the loads applied on them: the particles on a
straight face, and pressure / traction boundaries as ``ext_force``.

A face load is a dead load: the force on each face particle is fixed when it is
computed (it does not follow the face as it deforms or rotates), which is the
small-strain boundary condition of 000 §4.4.  Add it to the particles with
``particles._replace(ext_force=particles.ext_force + load)`` and take it off the
same way; the reactions of prescribed particles are
:func:`jdem.measure.reaction_forces`.
"""
from __future__ import annotations

import numpy as np

from jdem.validate import InputError, require_finite, require_positive

#: outward normals of the faces of an axis-aligned specimen, by name (2D and 3D;
#: in 3D "bottom" / "top" are -z / +z, "front" / "back" -y / +y)
FACES = {
    2: {"left": (-1.0, 0.0), "right": (1.0, 0.0), "bottom": (0.0, -1.0), "top": (0.0, 1.0)},
    3: {"left": (-1.0, 0.0, 0.0), "right": (1.0, 0.0, 0.0), "front": (0.0, -1.0, 0.0),
        "back": (0.0, 1.0, 0.0), "bottom": (0.0, 0.0, -1.0), "top": (0.0, 0.0, 1.0)},
}


def outward_normal(side, dim):
    """The unit outward normal (d,) of ``side``: a face name of :data:`FACES` or
    a non-zero vector of length ``dim``."""
    if isinstance(side, str):
        if side not in FACES[dim]:
            raise InputError(f"side must be one of {tuple(FACES[dim])} or a normal vector, "
                             f"got {side!r}")
        return np.asarray(FACES[dim][side])
    n = require_finite("side", side).reshape(-1)
    if n.shape != (dim,) or np.linalg.norm(n) == 0:
        raise InputError(f"side must be a non-zero {dim}D normal vector, got {side!r}")
    return n / np.linalg.norm(n)


def valid_rows(particles, among=None):
    """Indices of the valid particles, restricted to ``among`` (index array) if
    given; an empty selection raises :class:`InputError`."""
    rows = np.nonzero(np.asarray(particles.valid))[0]
    if among is not None:
        rows = np.intersect1d(rows, np.asarray(among, np.int64))
    if rows.size == 0:
        raise InputError("among selects no valid particle")
    return rows


def face_particles(particles, side, *, tolerance=None, among=None):
    """Indices of the particles on the straight face ``side`` (name or outward
    normal): those whose outer edge n . x + r lies within ``tolerance`` [m]
    (default half the smallest radius) of the outermost edge.  Returns
    ``(rows, normal, position)``: rows (B,), the unit outward normal (d,) and
    the face position along it [m]."""
    pos = np.asarray(particles.pos, np.float64)
    rad = np.asarray(particles.radius, np.float64)
    n = outward_normal(side, pos.shape[1])
    rows = valid_rows(particles, among)
    tol = 0.5 * rad[rows].min() if tolerance is None else float(
        require_positive("tolerance", tolerance, allow_zero=True))
    edge = pos[rows] @ n + rad[rows]
    outer = float(edge.max())
    return rows[edge >= outer - tol], n, outer


def face_area(particles, rows, normal):
    """Area [m^2; 2D: m x 1 m] of the face covered by ``rows``: the extent of
    the particles projected on the face plane (2D: a length; 3D: the bounding
    rectangle along the two in-plane axes closest to the coordinate axes)."""
    pos = np.asarray(particles.pos, np.float64)[rows]
    rad = np.asarray(particles.radius, np.float64)[rows]
    dim = pos.shape[1]
    if dim == 2:
        t = np.array([-normal[1], normal[0]])
        s = pos @ t
        return float((s + rad).max() - (s - rad).min())
    axes = np.argsort(np.abs(normal))[:2]
    area = 1.0
    for a in axes:
        area *= float((pos[:, a] + rad).max() - (pos[:, a] - rad).min())
    return area


def surface_load(particles, side, traction, *, area=None, tolerance=None, among=None):
    """External forces (N, d) [N] that apply the uniform ``traction`` (d,) [Pa]
    on the face ``side`` (see :func:`face_particles`).

    The total force traction x area (``area`` [m^2; 2D: m x 1 m], default
    :func:`face_area`) is shared among the face particles in proportion to
    their projected size (2D: diameter; 3D: r^2), so it is applied exactly.
    Zero on every other row."""
    rows, n, _ = face_particles(particles, side, tolerance=tolerance, among=among)
    dim = n.size
    t = require_finite("traction", traction).reshape(-1)
    if t.shape != (dim,):
        raise InputError(f"traction must be a vector of length {dim} [Pa], got {traction!r}")
    a = face_area(particles, rows, n) if area is None else float(require_positive("area", area))
    rad = np.asarray(particles.radius, np.float64)[rows]
    share = rad if dim == 2 else rad ** 2
    out = np.zeros(np.shape(particles.pos), np.float64)
    out[rows] = (share / share.sum())[:, None] * (t * a)[None]
    return out


def pressure_load(particles, side, pressure, *, area=None, tolerance=None, among=None):
    """External forces (N, d) [N] of a uniform ``pressure`` [Pa] (compression
    positive: it pushes the face inwards, traction -p n) on the face ``side``;
    see :func:`surface_load`."""
    p = float(require_finite("pressure", pressure))
    n = outward_normal(side, np.shape(particles.pos)[1])
    return surface_load(particles, side, -p * n, area=area, tolerance=tolerance, among=among)
