"""Block generation: a region cut by joint sets, or polygons read from a file
(000 §2.3.3: the block system is made by the joints that cut the rock mass).

Citations ("000 §2.3.3") refer to the documents listed in REFERENCES.md.

A joint set is a family of parallel traces (dip, spacing, offset).  Every
trace cuts the region through (the cut of a convex polygon by a line gives two
convex polygons, so the blocks stay convex).  A set with ``persistence`` p < 1
is a trace of joint segments and rock bridges: along the trace, joint pieces of
length ``trace_length`` alternate with bridges of length
``trace_length (1 / p - 1)``.  The cut is made everywhere, and the faces that
lie on a bridge are glued afterwards (:func:`bridge_mask` with
:func:`jdem.blocks.cycle.glue_joints`), so a bridge carries the tension and
cohesion of intact rock until it breaks.
"""
from __future__ import annotations

import pathlib
from typing import NamedTuple

import numpy as np

from jdem.blocks.geometry import signed_area
from jdem.validate import InputError


class JointSet(NamedTuple):
    """A family of parallel joint traces in the x–y plane (y up).

    dip          angle of the traces below the horizontal [deg], dipping towards +x
    spacing      normal distance between traces [m]
    offset       normal position of one trace from the origin [m]
    persistence  fraction of a trace that is joint (1: fully persistent)
    trace_length length of one joint piece [m] (only with persistence < 1)
    """

    dip: float
    spacing: float
    offset: float = 0.0
    persistence: float = 1.0
    trace_length: float = 1.0

    def normal(self):
        d = np.deg2rad(self.dip)
        return np.array([np.sin(d), np.cos(d)])

    def direction(self):
        d = np.deg2rad(self.dip)
        return np.array([np.cos(d), -np.sin(d)])


def _check_set(js: JointSet, k: int):
    for name in ("dip", "spacing", "offset", "persistence", "trace_length"):
        if not np.isfinite(float(getattr(js, name))):
            raise InputError(f"joint set {k}: {name} must be finite, got {getattr(js, name)!r}")
    if js.spacing <= 0:
        raise InputError(f"joint set {k}: spacing must be > 0, got {js.spacing!r}")
    if not 0 < js.persistence <= 1:
        raise InputError(f"joint set {k}: persistence must be in (0, 1], got {js.persistence!r}")
    if js.trace_length <= 0:
        raise InputError(f"joint set {k}: trace_length must be > 0, got {js.trace_length!r}")


def split_polygon(poly, normal, c, *, min_area=1e-12):
    """Cut a convex polygon (n, 2) by the line normal . x = c; returns the
    pieces (0, 1 or 2 polygons) with an area above ``min_area`` times the
    polygon's."""
    p = np.asarray(poly, dtype=np.float64)
    s = p @ normal - c
    if np.all(s >= 0) or np.all(s <= 0):
        return [p]
    below, above = [], []
    n = len(p)
    for k in range(n):
        a, b = p[k], p[(k + 1) % n]
        sa, sb = s[k], s[(k + 1) % n]
        if sa <= 0:
            below.append(a)
        if sa >= 0:
            above.append(a)
        if (sa < 0 < sb) or (sb < 0 < sa):
            x = a + (b - a) * (sa / (sa - sb))
            below.append(x)
            above.append(x)
    area = abs(signed_area(p))
    return [np.array(q) for q in (below, above)
            if len(q) >= 3 and abs(signed_area(q)) > min_area * area]


def cut_region(region, joint_sets) -> list:
    """Convex blocks from a convex ``region`` (n, 2) [m] cut by every trace of
    each :class:`JointSet`.  Returns a list of (k, 2) vertex arrays."""
    region = np.asarray(region, dtype=np.float64)
    if region.ndim != 2 or region.shape[1] != 2 or region.shape[0] < 3:
        raise InputError(f"region must be an (n >= 3, 2) polygon, got shape {region.shape}")
    blocks = [region]
    for k, js in enumerate(joint_sets):
        js = JointSet(*js) if not isinstance(js, JointSet) else js
        _check_set(js, k)
        nrm = js.normal()
        proj = region @ nrm
        first = np.ceil((proj.min() - js.offset) / js.spacing)
        last = np.floor((proj.max() - js.offset) / js.spacing)
        for m in np.arange(first, last + 1):
            c = js.offset + m * js.spacing
            blocks = [piece for b in blocks for piece in split_polygon(b, nrm, c)]
    return blocks


def bridge_mask(points, normals, joint_sets, *, tol=1e-9):
    """(C, 2) bool: the contact points of the pairs whose face lies on a rock
    bridge of a non-persistent joint set (module docstring).

    points (C, 2, 2) and normals (C, 2) as :func:`jdem.blocks.detect.pair_geometry`
    gives them.  A face is judged by its centre (the mean of its two points):
    on one of the set's traces, its normal along the set's, and in a bridge
    interval along the trace (measured from the trace's foot point nearest the
    origin).  Use as ``glue_joints(..., where=lambda p, n: bridge_mask(p, n, sets))``.
    """
    pts = np.asarray(points, dtype=np.float64).mean(axis=-2)          # (C, 2)
    nrm = np.asarray(normals, dtype=np.float64)
    out = np.zeros(pts.shape[:-1], bool)
    for js in joint_sets:
        js = JointSet(*js) if not isinstance(js, JointSet) else js
        if js.persistence >= 1:
            continue
        n, d = js.normal(), js.direction()
        dist = (pts @ n - js.offset) / js.spacing
        on_trace = np.abs(dist - np.round(dist)) * js.spacing < max(tol, 1e-6 * js.spacing)
        parallel = np.abs(nrm @ n) > 1 - 1e-6
        period = js.trace_length / js.persistence
        along = np.mod(pts @ d, period)
        out |= on_trace & parallel & (along > js.trace_length)
    return np.repeat(out[:, None], 2, axis=1)


def read_polygons(path) -> list:
    """Block polygons from a text file: one block per line, its vertices as
    ``x,y`` pairs separated by spaces (``0,0 1,0 1,1 0,1``); ``#`` starts a
    comment, blank lines are skipped.  Coordinates in metres."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise InputError(f"block file {str(path)!r} does not exist or is not a file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(f"block file {str(path)!r} is not UTF-8 text: {e}") from None
    polys = []
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            verts = [tuple(float(v) for v in pair.split(",")) for pair in line.split()]
        except ValueError:
            raise InputError(f"{path}:{lineno}: expected x,y pairs, got {line!r}") from None
        if any(len(v) != 2 for v in verts) or len(verts) < 3:
            raise InputError(f"{path}:{lineno}: a block needs at least 3 x,y pairs, got {line!r}")
        polys.append(np.array(verts))
    if not polys:
        raise InputError(f"block file {str(path)!r} holds no block")
    return polys


def write_polygons(path, polygons) -> None:
    """Write polygons in the format :func:`read_polygons` reads."""
    with open(path, "w", encoding="utf-8") as f:
        f.write("# one block per line: x,y pairs [m]\n")
        for p in polygons:
            f.write(" ".join(f"{float(x)!r},{float(y)!r}" for x, y in np.asarray(p)) + "\n")
