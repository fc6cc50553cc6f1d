"""The public builders: :func:`generate` (a specimen of a given porosity) and
:func:`specimen_for_coordination` (a specimen whose bonded coordination number
is a target, 002 §1.4).

Citations ("002 §1.4") refer to the documents listed in REFERENCES.md.
"""
from __future__ import annotations

import time

import numpy as np

from jdem.specimen.bonding import finish_specimen, gap_for_coordination, near_pairs
from jdem.specimen.compaction import compact
from jdem.specimen.container import (MIN_POROSITY, Specimen, check_inputs, finite_number,
                                     make_container, particle_volume)
from jdem.validate import InputError


def generate(shape, size, r_min, r_max, *, seed=0, density=2500.0, target_porosity=None,
             target_coordination=None, bond=True, gap_tolerance=None, overlap_limit=0.01,
             floaters="attach", coordination_tolerance=0.15, max_gap_tolerance=None,
             progress=False, stage_steps=200, max_steps=None) -> Specimen:
    """Generate a compacted (and bonded) specimen; see the module docstring.

    shape            "rectangle" (2D, size=(w, h)), "box" (3D, size=(w, d, h)) or
                     "disc" (2D, size=diameter)
    r_min, r_max     radius range [m]; radii are uniform in it
    seed             seeds every random choice: equal seeds give identical arrays
    density          particle density [kg/m^3] for the returned particles
    target_porosity  porosity to reach (None: the densest packing the method makes)
    target_coordination  mean coordination number N-bar to reach by choosing the gap
                     tolerance in [0, max_gap_tolerance] (default 0.5 mean radius);
                     InputError when not within coordination_tolerance
    bond             bond every pair within the gap tolerance (jdem.bond.create_bonds)
    gap_tolerance    [m] bonding distance, default 0.05 x the mean radius
    overlap_limit    largest overlap allowed, as a fraction of the mean radius
    floaters         particles with no neighbour within the gap tolerance: "attach"
                     (moved onto their nearest neighbour), "remove" or "keep"
    progress         show a tqdm bar during the compaction
    stage_steps      engine steps per expansion / relaxation stage
    max_steps        give up (RuntimeError) after this many steps (default: ample)
    """
    t_start = time.perf_counter()
    c = make_container(shape, size)
    r_min, r_max = check_inputs(c, r_min, r_max, density, target_porosity, target_coordination,
                          gap_tolerance, overlap_limit, seed, floaters)
    _check_steps(stage_steps, max_steps, coordination_tolerance, max_gap_tolerance)
    pk = compact(c, r_min, r_max, int(seed), target_porosity, overlap_limit, density,
                  int(stage_steps), max_steps, progress)
    return finish_specimen(pk, seed=seed, density=density, bond=bond, gap_tolerance=gap_tolerance,
                   target_coordination=target_coordination,
                   coordination_tolerance=coordination_tolerance,
                   max_gap_tolerance=max_gap_tolerance, floaters=floaters,
                   overlap_limit=overlap_limit, t_start=t_start, target_porosity=target_porosity)


def _check_steps(stage_steps, max_steps, coordination_tolerance, max_gap_tolerance):
    if isinstance(stage_steps, bool) or not isinstance(stage_steps, (int, np.integer)) \
            or stage_steps < 1:
        raise InputError(f"stage_steps must be a positive integer, got {stage_steps!r}")
    if max_steps is not None and (isinstance(max_steps, bool) or
                                  not isinstance(max_steps, (int, np.integer)) or max_steps < 1):
        raise InputError(f"max_steps must be a positive integer or None, got {max_steps!r}")
    tol = finite_number("coordination_tolerance", coordination_tolerance)
    if tol <= 0:
        raise InputError(f"coordination_tolerance must be > 0, got {tol!r}")
    if max_gap_tolerance is not None and finite_number("max_gap_tolerance", max_gap_tolerance) <= 0:
        raise InputError(f"max_gap_tolerance must be > 0, got {max_gap_tolerance!r}")


def specimen_for_coordination(target_N, shape, size, r_min, r_max, *, tolerance=0.15,
                              target_porosity=None, max_gap_tolerance=None, max_attempts=4,
                              porosity_step=0.04, seed=0, density=2500.0, bond=True,
                              overlap_limit=0.01, floaters="attach", progress=False,
                              stage_steps=200, max_steps=None) -> Specimen:
    """A specimen whose mean coordination number N-bar is ``target_N`` +- ``tolerance``.

    002 §1.4 reaches different N-bar by changing the packing (particle number,
    size distribution, arrangement, embedding).  Here: the packing is compacted
    at ``target_porosity`` (None: the densest), then the bonding gap tolerance is
    chosen in [0, ``max_gap_tolerance``] (default 0.5 x the mean radius) to bring
    N-bar closest to the target.  If even a zero tolerance gives too many
    contacts, the packing is remade ``porosity_step`` looser; if the largest
    tolerance gives too few, ``porosity_step`` denser (down to the densest), at
    most ``max_attempts`` packings in all.  Raises :class:`InputError` naming
    ``target_N`` and the N-bar ranges reached at each porosity tried.
    ``info["attempts"]`` lists (porosity, lowest N-bar, highest N-bar) per packing.
    """
    t_start = time.perf_counter()
    c = make_container(shape, size)
    z_top = 6.0 if c.dim == 2 else 12.0
    z_target = finite_number("target_N", target_N)
    if not 0.0 < z_target < z_top:
        raise InputError(f"target_N must lie in (0, {z_top}) in {c.dim}D, got {target_N!r}")
    r_min, r_max = check_inputs(c, r_min, r_max, density, target_porosity, None, None,
                          overlap_limit, seed, floaters)
    tol = finite_number("tolerance", tolerance)
    if tol <= 0:
        raise InputError(f"tolerance must be > 0, got {tolerance!r}")
    _check_steps(stage_steps, max_steps, tol, max_gap_tolerance)
    if isinstance(max_attempts, bool) or not isinstance(max_attempts, (int, np.integer)) \
            or max_attempts < 1:
        raise InputError(f"max_attempts must be a positive integer, got {max_attempts!r}")
    step = finite_number("porosity_step", porosity_step)
    if not 0.0 < step < 0.5:
        raise InputError(f"porosity_step must lie in (0, 0.5), got {porosity_step!r}")
    max_gap_rel = None if max_gap_tolerance is None else float(max_gap_tolerance)
    phi = None if target_porosity is None else float(target_porosity)
    attempts = []
    tried = set()
    for _ in range(int(max_attempts)):
        key = None if phi is None else round(phi, 6)
        if key in tried:
            break
        tried.add(key)
        try:
            pk = compact(c, r_min, r_max, int(seed), phi, overlap_limit, density,
                          int(stage_steps), max_steps, progress)
        except InputError:
            if phi is None:
                raise
            phi = None  # that porosity jammed: the densest packing is the next best
            continue
        max_gap = 0.5 * float(pk.rad.mean()) if max_gap_rel is None else max_gap_rel
        i, j, gap = near_pairs(pk.pos, pk.rad, max_gap)
        _, zbar, z_lo, z_hi = gap_for_coordination(z_target, i, j, gap, pk.rad.size, floaters,
                                                   max_gap)
        phi_reached = 1.0 - float(np.sum(particle_volume(pk.rad, c.dim))) / c.volume
        attempts.append((phi_reached, z_lo, z_hi))
        if abs(zbar - z_target) <= tol:
            sp = finish_specimen(pk, seed=seed, density=density, bond=bond, gap_tolerance=None,
                         target_coordination=z_target, coordination_tolerance=tol,
                         max_gap_tolerance=max_gap, floaters=floaters,
                         overlap_limit=overlap_limit, t_start=t_start,
                         target_porosity=target_porosity)
            sp.info["attempts"] = attempts
            return sp
        if z_target < z_lo:                  # too many contacts even at zero gap: looser
            phi = phi_reached + step
            if phi >= 0.95:
                break
        else:                                # too few even at the largest gap: denser
            if phi is None:
                break
            phi = phi_reached - step
            if phi < MIN_POROSITY[c.dim]:
                phi = None
    reached = "; ".join(f"porosity {p:.3f}: N-bar {lo:.2f} to {hi:.2f}" for p, lo, hi in attempts)
    raise InputError(
        f"target_N = {target_N!r} is not reachable within +-{tol}: gap tolerances up to "
        f"{'0.5 x the mean radius' if max_gap_rel is None else f'{max_gap_rel:.4g} m'} gave "
        f"{reached or 'no packing'}; a larger max_gap_tolerance or a different size "
        f"distribution may help")
