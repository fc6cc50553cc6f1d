"""Compaction of a loose placement with the jdem engine: radius growth in rigid
walls until the target porosity, with local damping (000 eq 3-19) and
relaxation of the overlaps (step 3 of the method in :mod:`jdem.specimen`).

Citations ("000 eq 3-19") refer to the documents listed in REFERENCES.md.
"""
from __future__ import annotations

import math
import time
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jdem import neighbors
from jdem.kinematics import dot, safe_norm
from jdem.measure import kinetic_energy
from jdem.simulate import run
from jdem.specimen.container import (RSA_FRACTION, Container, draw_radii, particle_volume,
                                     random_sequential_addition, wall_planes)
from jdem.state import Config, State, empty_bonds, make_params, make_particles, make_walls
from jdem.timestep import nominal_critical_timestep
from jdem.validate import InputError


DENSE_START = {2: 0.14, 3: 0.34}       # starting porosity of the densest mode (jams, then thins)
JAMMING_Z = {2: 4.0, 3: 6.0}           # isostatic contact number (frictionless)
GROWTH_MAX, GROWTH_SLOW, GROWTH_MIN = 0.03, 0.01, 0.0025  # radius growth per stage
SLOW_FRACTION = {2: 0.74, 3: 0.52}     # packing fraction from which growth is slow
BACKOFF, MAX_BACKOFFS = 0.02, 3        # a jammed target: shrink 2 % and regrow, 3 times
LOCAL_DAMPING = 0.4                    # 000 eq 3-19 during compaction (fastest relaxation found)
FINAL_OVERLAP = 0.9                    # relax at full size until overlap <= this x overlap_limit
_PAD = 64                              # particle capacity rounded up to this (compile reuse)


def _observe(state, params, config):
    """Largest overlap (pairs and walls), kinetic energy and touching pairs."""
    p = state.particles
    c = state.contacts
    dist = safe_norm(p.pos[c.j] - p.pos[c.i])
    ov = jnp.where(c.valid, p.radius[c.i] + p.radius[c.j] - dist, -jnp.inf)
    w = state.walls
    dw = dot(p.pos[None] - w.point[:, None], w.normal[:, None])
    ovw = jnp.where(p.valid[None] & w.valid[:, None], p.radius[None] - dw, -jnp.inf)
    return dict(max_overlap=jnp.maximum(jnp.max(ov, initial=0.0), jnp.max(ovw, initial=0.0)),
                kinetic=kinetic_energy(state), n_touch=jnp.sum(ov > 0))


def _bucket(n):
    return int(math.ceil(n / _PAD) * _PAD)


def _setup(c: Container, rad, pos0, s0, density, r_lo, r_hi):
    """State, params and config for the compaction of particles ``rad`` placed at
    ``pos0`` with radii ``rad * s0``; the grid is sized for the final radii."""
    dim = c.dim
    n = rad.size
    cap = _bucket(n)
    # the static configuration depends on the nominal radius range only (one
    # compilation serves every seed)
    r_mean = 0.5 * (r_lo + r_hi)
    r_max, r_min = r_hi, r_lo
    m0 = float(np.mean(density)) * float(particle_volume(r_mean, dim))  # uniform inertial mass
    p = make_particles(pos0, rad * s0, capacity=cap)
    valid = np.array(p.valid)
    mass = jnp.where(p.valid, m0, 1.0).astype(p.mass.dtype)
    p = p._replace(mass=mass, inertia=mass * (0.5 if dim == 2 else 0.4) * r_mean**2,
                   gravity_mass=jnp.zeros_like(p.gravity_mass))
    skin = 0.3 * r_mean
    cell = 2.0 * r_max + skin
    origin = tuple(float(v) for v in c.lo - cell)
    gshape = tuple(int(math.ceil((h - l) / cell)) + 2 for l, h in zip(c.lo, c.hi))
    k = int(math.ceil(cell**dim * 0.9 / float(particle_volume(r_min, dim)))) + 3
    cfg = Config(dim=dim, skin=skin, cell_size=cell, grid_origin=origin, grid_shape=gshape,
                 max_per_cell=k)
    pts, nrm = wall_planes(c)
    walls = make_walls(pts, nrm, n_particles=cap)
    # as jdem.simulate.make_state, but the neighbour list has room for a dense packing
    # and its capacity depends only on the padded particle capacity, so that every
    # seed reuses one compilation (jdem.simulate.run re-allocates if ever needed)
    contacts = neighbors.build(neighbors.empty(p, (4 if dim == 2 else 9) * cap), p, cfg)
    state = State(particles=p, contacts=contacts, walls=walls,
                  bonds=empty_bonds(dim, 0, p.pos.dtype), step=jnp.zeros((), jnp.int32),
                  time=jnp.zeros((), p.pos.dtype), first_bad_step=jnp.full((), -1, jnp.int32))
    kn = 1e8
    params = make_params(dim, kn=kn, ks=1e-3 * kn, friction=0.0, local_damping=LOCAL_DAMPING)
    pf = p._replace(radius=jnp.where(p.valid, jnp.asarray(np.resize(rad, cap), p.radius.dtype),
                                     0.0))
    # time step: 0.6 x the critical step of a particle with 6 (2D) / 12 (3D) contacts, and
    # at most 0.9 x that of a largest particle ringed by smallest ones (plus two walls)
    theta = math.asin(1.0 / (1.0 + r_hi / r_lo))
    z_ring = (math.pi / theta if dim == 2 else 2.0 / (1.0 - math.cos(theta))) + 2.0
    crit = lambda z: float(nominal_critical_timestep(pf, params, cfg, coordination=z))
    dt = min(0.6 * crit(6 if dim == 2 else 12), 0.9 * crit(z_ring))
    params = params._replace(dt=jnp.asarray(dt, params.dt.dtype),
                             viscous_damping=jnp.asarray(0.002 / dt, params.dt.dtype))
    return state, params, cfg, valid


class Packing(NamedTuple):
    """A compacted packing (host arrays): centres ``pos`` (N, d) [m], radii ``rad``
    (N,) [m], its ``container`` and the compaction ``info``."""

    pos: np.ndarray
    rad: np.ndarray
    container: Container
    info: dict


def compact(c: Container, r_min, r_max, seed, target_porosity, overlap_limit, density,
            stage_steps, max_steps, progress) -> Packing:
    """Draw radii, place them and grow them in the rigid container until the target
    porosity (the densest state when it is None) with overlaps below the limit."""
    t_start = time.perf_counter()
    dim = c.dim
    rng = np.random.default_rng(seed)
    dense = target_porosity is None
    phi0 = DENSE_START[dim] if dense else float(target_porosity)
    rad = draw_radii(rng, r_min, r_max, dim, (1.0 - phi0) * c.volume)
    n = rad.size
    r_mean = float(rad.mean())
    fraction = float(np.sum(particle_volume(rad, dim))) / c.volume
    s0 = min(0.9, (RSA_FRACTION[dim] / fraction) ** (1.0 / dim))
    pos0 = random_sequential_addition(rng, rad * s0, c)
    state, params, cfg, valid = _setup(c, rad, pos0, s0, density, r_min, r_max)
    cap = valid.size
    rad_cap = np.zeros(cap)
    rad_cap[:n] = rad
    dtype = state.particles.radius.dtype
    limit = float(overlap_limit)
    z_ref = JAMMING_Z[dim]
    l_d = c.volume ** (1.0 / dim) / (2.0 * r_mean)           # size in diameters
    max_hold = max(10 * stage_steps, int(30 * l_d))          # relaxation budget per jam
    if max_steps is None:
        max_steps = 40 * max_hold + 200 * stage_steps

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(desc="specimen compaction", unit="step", leave=False)
    s, steps, stages, hold, n_removed, backoffs = s0, 0, 0, 0, 0, 0
    s_ok = s0
    mo, z = 0.0, 0.0
    hold_hist: list[float] = []

    def set_radii(st, scale):
        r = jnp.asarray(np.where(valid, rad_cap * scale, 0.0), dtype)
        return st._replace(particles=st.particles._replace(radius=r, valid=jnp.asarray(valid)))

    state = set_radii(state, s)
    try:
        while True:
            res = run(state, params, cfg, stage_steps, record_every=stage_steps,
                      observe=_observe, progress=False)
            state, cfg = res.state, res.config
            steps += stage_steps
            stages += 1
            nv = int(valid.sum())
            mo = float(res.history["max_overlap"][-1]) / r_mean
            z = 2.0 * float(res.history["n_touch"][-1]) / nv
            if bar is not None:
                bar.update(stage_steps)
                bar.set_postfix(scale=f"{s:.4f}", overlap=f"{mo:.4f}", z=f"{z:.2f}", n=nv)
            if s < 1.0 and mo <= limit:          # relaxed enough: grow
                s_ok = s
                f = fraction * s**dim
                if backoffs or f >= SLOW_FRACTION[dim]:
                    g = GROWTH_MIN if backoffs else max(GROWTH_MIN, GROWTH_SLOW * (1.0 - z / z_ref))
                else:  # loose: fast, but not far past the slow-down fraction
                    g = min(GROWTH_MAX, (SLOW_FRACTION[dim] / f) ** (1.0 / dim) - 1.0 + GROWTH_MIN)
                s = min(1.0, s * (1.0 + g))
                state = set_radii(state, s)
                hold, hold_hist = 0, []
                continue
            if s >= 1.0 and mo <= FINAL_OVERLAP * limit:
                break                            # full size and relaxed: done
            hold += stage_steps
            hold_hist.append(mo)
            stalled = len(hold_hist) >= 6 and hold_hist[-1] > 0.9 * hold_hist[-6]
            if hold > max_hold or stalled:       # jammed
                if s >= 1.0 and mo <= limit:
                    break                        # within the limit anyway
                if not dense and backoffs < MAX_BACKOFFS:
                    # shrink a little, let the packing rearrange, regrow slowly
                    backoffs += 1
                    s = s / (1.0 + BACKOFF)
                    hold, hold_hist = 0, []
                    state = set_radii(state, s)
                    continue
                if not dense:
                    solid = float(np.sum(particle_volume(rad[valid[:n]] * s_ok, dim)))
                    phi = 1.0 - solid / c.volume
                    raise InputError(
                        f"target_porosity = {target_porosity!r} is out of the reachable range "
                        f"for this container and size distribution: the packing jammed at "
                        f"porosity {phi:.4f} (largest overlap {mo:.3g} x the mean radius, "
                        f"overlap_limit = {limit!r}); ask for a porosity above ~{phi + 0.01:.2f} "
                        f"or leave target_porosity=None for the densest packing")
                # densest mode: thin the jammed packing out by the volume it still has to
                # gain (plus 0.5 %), choosing particles at random, and grow on
                idx = np.nonzero(valid)[0]
                vols = particle_volume(rad_cap[idx], dim)
                frac = (1.0 - s**dim) + 0.005
                order = rng.permutation(idx.size)
                k = int(np.searchsorted(np.cumsum(vols[order]), frac * vols.sum())) + 1
                valid[idx[order[:k]]] = False
                n_removed += k
                fraction = float(np.sum(particle_volume(rad_cap[valid], dim))) / c.volume
                hold, hold_hist = 0, []
                state = set_radii(state, s)
            if steps >= max_steps:
                raise RuntimeError(
                    f"specimen compaction did not converge in max_steps = {max_steps} steps "
                    f"(scale {s:.4f}, largest overlap {mo:.3g} x the mean radius)")
    finally:
        if bar is not None:
            bar.close()
    p = state.particles
    keep = valid[:n]
    pos = np.asarray(p.pos, np.float64)[:n][keep]
    info = dict(steps=steps, stages=stages, compaction_time=time.perf_counter() - t_start,
                scale0=s0, n_removed_jammed=n_removed, n_backoffs=backoffs,
                n_builds=int(state.contacts.n_builds), dt=float(params.dt),
                contact_z=z, n_drawn=n)
    return Packing(pos, rad[keep], c, info)
