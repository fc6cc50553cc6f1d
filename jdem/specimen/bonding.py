"""Bonding a compacted packing: the gap rule that bonds near pairs, the gap that
reaches a target coordination number, floaters (discs with fewer than two
bonds) and the finished :class:`Specimen` (step 4 of the method in
:mod:`jdem.specimen`; 002 §1.4).

Citations ("002 §1.4") refer to the documents listed in REFERENCES.md.
"""
from __future__ import annotations

import time

import numpy as np

from jdem.bond import create_bonds
from jdem.specimen.compaction import Packing
from jdem.specimen.container import Container, Specimen, particle_volume, wall_planes
from jdem.state import empty_bonds, make_particles
from jdem.validate import InputError


def near_pairs(pos, rad, max_gap):
    """All pairs (i < j) with gap |x_i - x_j| - R_i - R_j <= max_gap: i, j, gap (float64)."""
    from scipy.spatial import cKDTree

    if pos.shape[0] < 2:
        z = np.zeros(0, np.int64)
        return z, z, np.zeros(0)
    ij = cKDTree(pos).query_pairs(2.0 * float(rad.max()) + max_gap, output_type="ndarray")
    i, j = ij[:, 0].astype(np.int64), ij[:, 1].astype(np.int64)
    gap = np.linalg.norm(pos[j] - pos[i], axis=1) - rad[i] - rad[j]
    sel = gap <= max_gap
    i, j, gap = i[sel], j[sel], gap[sel]
    order = np.lexsort((j, i))
    return i[order], j[order], gap[order]


def _wall_overlap(pos, rad, c: Container):
    """Largest overlap of any particle with the container walls [m] (<= 0: none)."""
    pts, nrm = wall_planes(c)
    pts, nrm = np.asarray(pts, float), np.asarray(nrm, float)
    dist = np.einsum("wnd,wd->wn", pos[None] - pts[:, None], nrm)
    return float(np.max(rad[None] - dist)) if pos.size else 0.0


def _coordination_curve(i, j, gap, n, floaters):
    """Candidate gap tolerances t (>= 0) and the mean coordination number at each:
    N-bar(t) = 2 #pairs(gap <= t) / #particles, where floaters (no pair within t)
    add one pair each ("attach"), drop out ("remove") or count as 0 ("keep")."""
    gs = np.sort(gap)
    ts = np.concatenate([[0.0], gs[gs > 0]])
    pairs = np.searchsorted(gs, ts, side="right")
    mg = np.full(n, np.inf)
    np.minimum.at(mg, i, gap)
    np.minimum.at(mg, j, gap)
    n_float = n - np.searchsorted(np.sort(mg), ts, side="right")
    if floaters == "attach":
        zbar = 2.0 * (pairs + n_float) / n
    elif floaters == "remove":
        zbar = 2.0 * pairs / np.maximum(n - n_float, 1)
    else:
        zbar = 2.0 * pairs / n
    return ts, zbar, gs, pairs


def gap_for_coordination(target, i, j, gap, n, floaters, max_gap):
    """The gap tolerance (in [0, max_gap]) whose N-bar is closest to ``target``
    (the smallest such); returns (gap_tolerance, N-bar, lowest N-bar, highest N-bar)."""
    ts, zbar, gs, pairs = _coordination_curve(i, j, gap, n, floaters)
    best = int(np.argmin(np.abs(zbar - target)))
    k = int(pairs[best])
    nxt = gs[k] if k < gs.size else max_gap
    g = 0.5 * (ts[best] + nxt) if nxt > ts[best] else ts[best]  # halfway to the next pair
    return float(min(max(g, 0.0), max_gap)), float(zbar[best]), float(zbar.min()), float(zbar.max())


def _handle_floaters(pos, rad, c: Container, g, mode):
    """Particles with no neighbour within the gap tolerance ``g``: "keep" them,
    "remove" them, or "attach" them: move each along the line to its nearest
    connected neighbour by the gap, so that it touches it.  The move shortens no
    other gap by more than that gap, so it creates no overlap with particles whose
    gap was larger; every candidate position is checked against particles and
    walls, and a floater that cannot be attached is removed.
    Returns (pos, rad, n_floaters, n_attached, n_removed)."""
    from scipy.spatial import cKDTree

    n = rad.size
    i, j, _ = near_pairs(pos, rad, g)
    deg = np.bincount(i, minlength=n) + np.bincount(j, minlength=n)
    free = np.nonzero(deg == 0)[0]
    if mode == "keep" or free.size == 0:
        return pos, rad, int(free.size), 0, 0
    keep = np.ones(n, bool)
    if mode == "remove":
        keep[free] = False
        return pos[keep], rad[keep], int(free.size), 0, int(free.size)
    pos = pos.copy()
    connected = deg > 0
    tree = cKDTree(pos)
    pts, nrm = (np.asarray(a, float) for a in wall_planes(c))
    r_max = float(rad.max())
    touch = 1e-4 * float(rad.mean())  # end in (barely) touching contact: gap -1e-4 r_mean
    moved: list[int] = []
    attached = 0
    k_near = min(n - 1, 24)
    _, near = tree.query(pos[free], k=k_near + 1)
    for f, cand in zip(free, np.atleast_2d(near)):
        cand = cand[(cand != f) & (cand < n)]
        if moved:
            cand = np.unique(np.concatenate([cand, np.asarray(moved)]))
        cand = cand[connected[cand]]
        if cand.size == 0:
            keep[f] = False
            continue
        d = pos[cand] - pos[f]
        dist = np.linalg.norm(d, axis=1)
        gaps = dist - rad[cand] - rad[f]
        ok = False
        for t in np.argsort(gaps, kind="stable")[:8]:
            new = pos[f] + d[t] / dist[t] * (gaps[t] + touch)
            # every particle within reach of the new position (tree: unmoved ones)
            others = np.asarray(tree.query_ball_point(new, rad[f] + r_max + touch), np.int64)
            if moved:
                others = np.concatenate([others, np.asarray(moved)])
            others = others[(others != f) & keep[others]]
            og = np.linalg.norm(pos[others] - new, axis=1) - rad[others] - rad[f]
            wall = np.min(np.einsum("wd,wd->w", new[None] - pts, nrm)) - rad[f]
            if og.size and og.min() < -2.0 * touch or wall < 0.0:
                continue
            pos[f] = new
            ok = True
            break
        if ok:
            connected[f] = True
            moved.append(int(f))
            attached += 1
        else:
            keep[f] = False
    return pos[keep], rad[keep], int(free.size), attached, int(np.sum(~keep))


def finish_specimen(pk: Packing, *, seed, density, bond, gap_tolerance, target_coordination,
                    coordination_tolerance, max_gap_tolerance, floaters, overlap_limit,
                    t_start, target_porosity) -> Specimen:
    """Bond the packing (at ``gap_tolerance``, or at the gap that reaches
    ``target_coordination``), handle floaters and return the :class:`Specimen`."""
    c = pk.container
    dim = c.dim
    pos, rad = pk.pos, pk.rad
    r_mean0 = float(rad.mean())
    if target_coordination is not None:
        max_gap = 0.5 * r_mean0 if max_gap_tolerance is None else float(max_gap_tolerance)
        i, j, gap = near_pairs(pos, rad, max_gap)
        g, zbar, z_lo, z_hi = gap_for_coordination(float(target_coordination), i, j, gap,
                                                   rad.size, floaters, max_gap)
        if abs(zbar - target_coordination) > coordination_tolerance:
            phi = 1.0 - float(np.sum(particle_volume(rad, dim))) / c.volume
            hint = ("a looser packing (higher target_porosity)" if target_coordination < z_lo
                    else "a denser packing (lower target_porosity) or a larger max_gap_tolerance")
            raise InputError(
                f"target_coordination = {target_coordination!r} is not reachable within "
                f"+-{coordination_tolerance} at porosity {phi:.4f}: gap tolerances in "
                f"[0, {max_gap:.4g}] m give N-bar from {z_lo:.3f} to {z_hi:.3f}; try {hint}, "
                f"or jdem.specimen.specimen_for_coordination, which varies the packing density")
    else:
        g = 0.05 * r_mean0 if gap_tolerance is None else float(gap_tolerance)
    pos, rad, n_free, n_att, n_rem = _handle_floaters(pos, rad, c, g, floaters)
    n = rad.size
    if n < 2:
        raise InputError(f"the specimen has {n} particle(s) left: size {c.size!r} is too small "
                         f"for r_max = {float(pk.rad.max())!r} or target_porosity too high")
    particles = make_particles(pos, rad, density=density)
    # measure on the arrays as stored (float32 unless x64 is enabled)
    pos = np.asarray(particles.pos, np.float64)
    rad = np.asarray(particles.radius, np.float64)
    r_mean = float(rad.mean())
    i, j, gap = near_pairs(pos, rad, g)
    if bond:
        bonds = create_bonds(particles, dim, gap_tolerance=g)
        n_pairs = int(np.sum(np.asarray(bonds.valid)))
    else:
        bonds = empty_bonds(dim, 0, particles.pos.dtype)
        n_pairs = int(i.size)
    coordination = 2.0 * n_pairs / n
    if target_coordination is not None and \
            abs(coordination - target_coordination) > coordination_tolerance:
        raise InputError(  # (the floaters' moves added pairs beyond the prediction)
            f"target_coordination = {target_coordination!r} was missed: N-bar = "
            f"{coordination:.3f} after bonding with gap_tolerance {g:.4g} m; try another seed "
            f"or a larger coordination_tolerance")
    _, _, ov = near_pairs(pos, rad, 0.0)
    overlap = max(0.0, float(-ov.min()) if ov.size else 0.0, _wall_overlap(pos, rad, c))
    if overlap > overlap_limit * r_mean:
        raise RuntimeError(f"specimen: largest overlap {overlap:.4g} m = {overlap / r_mean:.4g} "
                           f"x the mean radius exceeds overlap_limit = {overlap_limit}")
    porosity = 1.0 - float(np.sum(particle_volume(rad, dim))) / c.volume
    info = dict(pk.info)
    info.update(
        shape=c.shape, size=c.size, n_particles=n, r_min=float(rad.min()), r_max=float(rad.max()),
        r_mean=r_mean, max_overlap=overlap, max_overlap_ratio=overlap / r_mean,
        gap_tolerance=g, n_bonds=n_pairs if bond else 0, n_pairs=n_pairs,
        n_floaters=n_free, n_floaters_attached=n_att, n_floaters_removed=n_rem,
        target_porosity=target_porosity, target_coordination=target_coordination,
        wall_time=time.perf_counter() - t_start)
    if c.centre is not None:
        info.update(centre=c.centre.copy(), radius=c.radius)
    return Specimen(particles=particles, bonds=bonds, box=(c.lo.copy(), c.hi.copy()),
                    porosity=porosity, coordination=coordination, seed=int(seed), info=info)
