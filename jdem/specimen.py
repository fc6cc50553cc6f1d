"""Rock specimen generation: random packings of discs / spheres, compacted with
the jdem engine and bonded (002 §1.4, §2).
Citations ("002 §1.4") refer to the documents listed in REFERENCES.md.

Method
------
1. **Radii.**  Radii are drawn uniformly in ``[r_min, r_max]`` (NumPy generator
   seeded with ``seed``) until their total area (2D: discs of unit thickness,
   pi r^2) or volume (3D: 4/3 pi r^3) is closest to ``(1 - target_porosity)``
   times the container's.  These are the final radii: they are never rescaled,
   so every radius lies in ``[r_min, r_max]`` (up to the float rounding of the
   stored arrays).
2. **Loose placement.**  Random sequential addition places the particles,
   shrunk by a common factor ``s0 < 1``, without overlap inside the container
   (packing fraction 0.45 in 2D, 0.28 in 3D; a cell grid keeps it O(N)).
3. **Compaction by radius expansion** with the jdem engine
   (:func:`jdem.simulate.run`, stages of ``stage_steps`` steps).  The container
   is rigid (:func:`jdem.state.make_walls`: 4 or 6 planes; a ``"disc"`` is the
   regular 64-gon inscribed in the circle).  Contacts are linear and
   frictionless, so the packing can rearrange into a dense state; local damping
   0.4 (000 eq 3-19; it relaxed these packings faster than 0.7) plus a little
   mass-proportional damping; one inertial mass for all particles (000 §3.3.2
   density scaling: quasi-static, only the geometry matters); time step 0.6 x
   :func:`jdem.timestep.nominal_critical_timestep`.  All radii grow by a common
   factor ``s -> s (1 + g)``: ``g`` = 3 % per stage while the packing is loose,
   1 % (falling to 0.25 % as the number of touching contacts per particle
   nears 4 in 2D / 6 in 3D) beyond a packing fraction of 0.74 (2D) / 0.52 (3D).
   Growth waits while the largest overlap exceeds ``overlap_limit``, so the
   packing relaxes between stages; at full size (``s = 1``) it relaxes until
   the largest overlap (particle pairs and walls) is below 0.9 x
   ``overlap_limit`` (the "unloading": frictionless contacts at a porosity above
   jamming push apart until they barely touch).
4. **Porosity.**  With ``target_porosity`` the particle number fixes the
   porosity (step 1).  When the packing jams on the way (overlaps stop
   relaxing), it shrinks 2 %, relaxes and regrows at 0.25 % per stage, up to 3
   times; a target below the jamming porosity still jams and raises
   :class:`jdem.validate.InputError` naming ``target_porosity`` and the densest
   porosity reached.  Without a target (``None``) the generator makes the
   densest packing it can: it starts denser than random close packing, and each
   time the packing jams it removes randomly chosen particles (the volume the
   others still have to gain, plus 0.5 %) and grows on.
5. **Floaters and bonds.**  Particles with no neighbour within the gap
   tolerance are "floaters" (rattlers).  ``floaters="attach"`` (default) moves
   each along the line to its nearest connected neighbour until the two touch
   (this creates no overlap: every other gap shrinks by at most the distance
   moved, which was the smallest gap; walls are checked), so the porosity is
   kept; ``"remove"`` drops them (the porosity rises by their share);
   ``"keep"`` leaves them.  Every pair whose gap ``|x_i - x_j| - R_i - R_j`` is
   at most ``gap_tolerance`` (default 0.05 x the mean radius) is bonded with
   :func:`jdem.bond.create_bonds`.  With ``target_coordination`` the gap
   tolerance in ``[0, max_gap_tolerance]`` (default 0.5 x the mean radius) that
   brings N-bar closest to the target is used; 002 §1.4 varies N-bar through
   the packing (density, size distribution, arrangement, embedding), and
   :func:`specimen_for_coordination` also varies the packing density when the
   gap tolerance alone cannot reach the target.

Units and conventions
---------------------
SI units (m, kg/m^3).  2D discs have unit thickness.  The container's lower
corner is the origin: ``"rectangle"`` ``size=(w, h)`` is ``[0, w] x [0, h]``;
``"box"`` ``size=(w, d, h)`` is ``[0, w] x [0, d] x [0, h]`` (height along z);
``"disc"`` ``size=D`` (the diameter) is the disc of radius ``D/2`` centred at
``(D/2, D/2)``, for Brazilian tests.  The returned particles have their true
masses (``density``), zero velocities and material 0.

What is reported
----------------
``Specimen.porosity``      1 - (sum of particle areas / volumes) / container area / volume
                           (rectangle w h, box w d h, disc pi D^2 / 4)
``Specimen.coordination``  N-bar = 2 n_pairs / n_particles, n_pairs the pairs within
                           the gap tolerance (= the bonds when ``bond=True``)
``Specimen.box``           (lo, hi) of the container the packing was compacted in
``Specimen.info``          n_particles, r_min, r_max, r_mean (of the final radii),
                           max_overlap [m] and max_overlap_ratio (/ mean radius; particle
                           pairs and walls), gap_tolerance [m], n_bonds, n_pairs,
                           n_floaters (found) / _attached / _removed, n_drawn (radii
                           drawn), n_removed_jammed, n_backoffs, contact_z (touching
                           contacts per particle at the end of the compaction), steps,
                           stages, n_builds (neighbour-list builds), dt [s], scale0,
                           compaction_time and wall_time [s], shape, size,
                           target_porosity, target_coordination; for a disc also
                           centre and radius; from specimen_for_coordination also
                           attempts
"""
from __future__ import annotations

import math
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import neighbors
from jdem.bond import create_bonds
from jdem.kinematics import dot, safe_norm
from jdem.measure import kinetic_energy
from jdem.simulate import run
from jdem.state import (Bonds, Config, Particles, State, empty_bonds, make_params,
                        make_particles, make_walls)
from jdem.timestep import nominal_critical_timestep
from jdem.validate import InputError

SHAPES = ("rectangle", "box", "disc")
FLOATERS = ("attach", "remove", "keep")
_DIM = {"rectangle": 2, "box": 3, "disc": 2}
RSA_FRACTION = {2: 0.45, 3: 0.28}      # packing fraction of the loose RSA placement
DENSE_START = {2: 0.14, 3: 0.34}       # starting porosity of the densest mode (jams, then thins)
MIN_POROSITY = {2: 0.10, 3: 0.25}      # targets below this are rejected up front
JAMMING_Z = {2: 4.0, 3: 6.0}           # isostatic contact number (frictionless)
DISC_SIDES = 64
GROWTH_MAX, GROWTH_SLOW, GROWTH_MIN = 0.03, 0.01, 0.0025  # radius growth per stage
SLOW_FRACTION = {2: 0.74, 3: 0.52}     # packing fraction from which growth is slow
BACKOFF, MAX_BACKOFFS = 0.02, 3        # a jammed target: shrink 2 % and regrow, 3 times
LOCAL_DAMPING = 0.4                    # 000 eq 3-19 during compaction (fastest relaxation found)
FINAL_OVERLAP = 0.9                    # relax at full size until overlap <= this x overlap_limit
_PAD = 64                              # particle capacity rounded up to this (compile reuse)


class Specimen(NamedTuple):
    """A generated specimen; see the module docstring for what each field holds."""

    particles: Particles
    bonds: Bonds
    box: tuple
    porosity: float
    coordination: float
    seed: int
    info: dict


# ----------------------------------------------------------------------------- input
class _Container(NamedTuple):
    shape: str
    dim: int
    size: tuple
    lo: np.ndarray
    hi: np.ndarray
    volume: float
    centre: np.ndarray | None
    radius: float | None


def _finite(name, value):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v):
        raise InputError(f"{name} must be finite, got {value!r}")
    return v


def _container(shape, size) -> _Container:
    if not isinstance(shape, str) or shape not in SHAPES:
        raise InputError(f"shape must be one of {SHAPES}, got {shape!r}")
    dim = _DIM[shape]
    want = {"rectangle": 2, "box": 3, "disc": 1}[shape]
    sz = np.atleast_1d(np.asarray(size, dtype=object)).tolist() if size is not None else []
    if len(sz) != want:
        what = {"rectangle": "(width, height)", "box": "(width, depth, height)",
                "disc": "the diameter (one number)"}[shape]
        raise InputError(f"size of a {shape!r} must be {what}, got {size!r}")
    vals = tuple(_finite(f"size[{k}]" if want > 1 else "size", v) for k, v in enumerate(sz))
    for k, v in enumerate(vals):
        if v <= 0:
            raise InputError(f"{f'size[{k}]' if want > 1 else 'size'} must be > 0, got {v!r}")
    if shape == "disc":
        d = vals[0]
        return _Container(shape, 2, vals, np.zeros(2), np.full(2, d), math.pi * d * d / 4,
                          np.full(2, d / 2), d / 2)
    hi = np.asarray(vals, float)
    return _Container(shape, dim, vals, np.zeros(dim), hi, float(np.prod(hi)), None, None)


def _check(c: _Container, r_min, r_max, density, target_porosity, target_coordination,
           gap_tolerance, overlap_limit, seed, floaters="attach"):
    r_min = _finite("r_min", r_min)
    r_max = _finite("r_max", r_max)
    if r_min <= 0:
        raise InputError(f"r_min must be > 0, got {r_min!r}")
    if r_max < r_min:
        raise InputError(f"r_max must be >= r_min = {r_min!r}, got {r_max!r}")
    smallest = min(c.size) if c.shape != "disc" else c.size[0]
    if smallest < 4 * r_max:
        raise InputError(f"size {c.size!r} is too small for particles of r_max = {r_max!r}: "
                         f"every side must be at least 4 r_max = {4 * r_max!r}")
    if np.any(~np.isfinite(np.asarray(density, float))) or np.any(np.asarray(density, float) <= 0):
        raise InputError(f"density must be > 0, got {density!r}")
    if target_porosity is not None:
        phi = _finite("target_porosity", target_porosity)
        if not 0.0 < phi < 1.0:
            raise InputError(f"target_porosity must lie in (0, 1), got {phi!r}")
        if phi < MIN_POROSITY[c.dim]:
            raise InputError(
                f"target_porosity = {phi!r} is out of the reachable range: random packings of "
                f"{'discs' if c.dim == 2 else 'spheres'} without overlap are not denser than "
                f"porosity ~{MIN_POROSITY[c.dim]} (leave target_porosity=None for the densest)")
    if target_coordination is not None:
        z = _finite("target_coordination", target_coordination)
        top = 6.0 if c.dim == 2 else 12.0
        if not 0.0 < z < top:
            raise InputError(f"target_coordination must lie in (0, {top}) in {c.dim}D, got {z!r}")
        if gap_tolerance is not None:
            raise InputError("give either gap_tolerance or target_coordination, not both "
                             f"(gap_tolerance = {gap_tolerance!r})")
    if gap_tolerance is not None:
        g = _finite("gap_tolerance", gap_tolerance)
        if g < 0:
            raise InputError(f"gap_tolerance must be >= 0, got {g!r}")
    lim = _finite("overlap_limit", overlap_limit)
    if not 0.0 < lim < 0.5:
        raise InputError(f"overlap_limit (a fraction of the mean radius) must lie in (0, 0.5), "
                         f"got {lim!r}")
    if floaters not in FLOATERS:
        raise InputError(f"floaters must be one of {FLOATERS}, got {floaters!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")
    return r_min, r_max


# ----------------------------------------------------------------------------- geometry
def _vol(r, dim):
    r = np.asarray(r, float)
    return np.pi * r**2 if dim == 2 else 4.0 / 3.0 * np.pi * r**3


def _mean_vol(r_min, r_max, dim):
    a, b = r_min, r_max
    if dim == 2:
        return np.pi * (a * a + a * b + b * b) / 3.0
    return np.pi * (a + b) * (a * a + b * b) / 3.0


def _draw_radii(rng, r_min, r_max, dim, solid):
    """Uniform radii until their total area / volume is closest to ``solid``."""
    n_guess = int(1.2 * solid / _mean_vol(r_min, r_max, dim)) + 16
    rad = rng.uniform(r_min, r_max, size=n_guess)
    cum = np.cumsum(_vol(rad, dim))
    while cum[-1] < solid:  # (only for extreme draws) draw more, deterministically
        more = rng.uniform(r_min, r_max, size=n_guess)
        rad = np.concatenate([rad, more])
        cum = np.cumsum(_vol(rad, dim))
    k = int(np.searchsorted(cum, solid))  # cum[k] >= solid > cum[k-1]
    if k > 0 and solid - cum[k - 1] < cum[k] - solid:
        k -= 1
    n = max(k + 1, 2)
    return rad[:n].copy()


def _wall_planes(c: _Container):
    """Points on and inward normals of the container's walls."""
    if c.shape == "rectangle":
        w, h = c.size
        return [[0, 0], [w, 0], [0, 0], [0, h]], [[1, 0], [-1, 0], [0, 1], [0, -1]]
    if c.shape == "box":
        w, d, h = c.size
        pts = [[0, 0, 0], [w, 0, 0], [0, 0, 0], [0, d, 0], [0, 0, 0], [0, 0, h]]
        nrm = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
        return pts, nrm
    m = DISC_SIDES  # regular m-gon inscribed in the circle: its sides are the walls
    th = 2.0 * np.pi * (np.arange(m) + 0.5) / m
    out = np.stack([np.cos(th), np.sin(th)], axis=1)
    return c.centre + c.radius * math.cos(math.pi / m) * out, -out


def _rsa(rng, rad, c: _Container, max_tries=20000, batch=8):
    """Random sequential addition of non-overlapping particles of radii ``rad``
    inside the container (largest first; a cell grid keeps it O(N))."""
    n = rad.size
    dim = c.dim
    lo, hi = c.lo, c.hi
    cell = 2.0 * rad.max()
    shape = np.maximum(1, np.ceil((hi - lo) / cell).astype(np.int64))
    k = int((cell / (2.0 * rad.min()) + 1.0) ** dim) + 1
    grid = np.full(tuple(shape + 2) + (k,), -1, np.int64)  # a ring of empty border cells
    count = np.zeros(tuple(shape + 2), np.int64)
    pos = np.zeros((n, dim))
    offs = np.stack(np.meshgrid(*[[-1, 0, 1]] * dim, indexing="ij"), -1).reshape(-1, dim)
    inner = None if c.radius is None else c.radius * math.cos(math.pi / DISC_SIDES)
    for idx in np.argsort(-rad, kind="stable"):
        r = rad[idx]
        for _ in range(max_tries // batch):
            cand = rng.uniform(lo + r, hi - r, size=(batch, dim))
            ok = np.ones(batch, bool)
            if inner is not None:
                ok &= np.sum((cand - c.centre) ** 2, axis=1) <= (inner - r) ** 2
            cc = np.minimum(np.floor((cand - lo) / cell).astype(np.int64) + 1, shape)
            nb = cc[:, None, :] + offs[None]
            ids = grid[tuple(nb[..., a] for a in range(dim))].reshape(batch, -1)
            there = ids >= 0
            safe = np.where(there, ids, 0)
            d2 = np.sum((pos[safe] - cand[:, None, :]) ** 2, axis=-1)
            ok &= ~np.any(there & (d2 < (rad[safe] + r) ** 2), axis=1)
            if ok.any():
                b = int(np.argmax(ok))
                pos[idx] = cand[b]
                key = tuple(cc[b])
                grid[key + (count[key],)] = idx
                count[key] += 1
                break
        else:
            raise RuntimeError(f"specimen: random placement failed after {max_tries} tries "
                               f"(particle {idx}, radius {r:.4g} m)")
    return pos


# ----------------------------------------------------------------------------- compaction
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


def _setup(c: _Container, rad, pos0, s0, density, r_lo, r_hi):
    """State, params and config for the compaction of particles ``rad`` placed at
    ``pos0`` with radii ``rad * s0``; the grid is sized for the final radii."""
    dim = c.dim
    n = rad.size
    cap = _bucket(n)
    # the static configuration depends on the nominal radius range only (one
    # compilation serves every seed)
    r_mean = 0.5 * (r_lo + r_hi)
    r_max, r_min = r_hi, r_lo
    m0 = float(np.mean(density)) * float(_vol(r_mean, dim))  # uniform inertial mass
    p = make_particles(pos0, rad * s0, capacity=cap)
    valid = np.array(p.valid)
    mass = jnp.where(p.valid, m0, 1.0).astype(p.mass.dtype)
    p = p._replace(mass=mass, inertia=mass * (0.5 if dim == 2 else 0.4) * r_mean**2,
                   gravity_mass=jnp.zeros_like(p.gravity_mass))
    skin = 0.3 * r_mean
    cell = 2.0 * r_max + skin
    origin = tuple(float(v) for v in c.lo - cell)
    gshape = tuple(int(math.ceil((h - l) / cell)) + 2 for l, h in zip(c.lo, c.hi))
    k = int(math.ceil(cell**dim * 0.9 / float(_vol(r_min, dim)))) + 3
    cfg = Config(dim=dim, skin=skin, cell_size=cell, grid_origin=origin, grid_shape=gshape,
                 max_per_cell=k)
    pts, nrm = _wall_planes(c)
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


class _Packing(NamedTuple):
    pos: np.ndarray
    rad: np.ndarray
    container: _Container
    info: dict


def _compact(c: _Container, r_min, r_max, seed, target_porosity, overlap_limit, density,
             stage_steps, max_steps, progress) -> _Packing:
    t_start = time.perf_counter()
    dim = c.dim
    rng = np.random.default_rng(seed)
    dense = target_porosity is None
    phi0 = DENSE_START[dim] if dense else float(target_porosity)
    rad = _draw_radii(rng, r_min, r_max, dim, (1.0 - phi0) * c.volume)
    n = rad.size
    r_mean = float(rad.mean())
    fraction = float(np.sum(_vol(rad, dim))) / c.volume
    s0 = min(0.9, (RSA_FRACTION[dim] / fraction) ** (1.0 / dim))
    pos0 = _rsa(rng, rad * s0, c)
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
                    phi = 1.0 - float(np.sum(_vol(rad[valid[:n]] * s_ok, dim))) / c.volume
                    raise InputError(
                        f"target_porosity = {target_porosity!r} is out of the reachable range "
                        f"for this container and size distribution: the packing jammed at "
                        f"porosity {phi:.4f} (largest overlap {mo:.3g} x the mean radius, "
                        f"overlap_limit = {limit!r}); ask for a porosity above ~{phi + 0.01:.2f} "
                        f"or leave target_porosity=None for the densest packing")
                # densest mode: thin the jammed packing out by the volume it still has to
                # gain (plus 0.5 %), choosing particles at random, and grow on
                idx = np.nonzero(valid)[0]
                vols = _vol(rad_cap[idx], dim)
                frac = (1.0 - s**dim) + 0.005
                order = rng.permutation(idx.size)
                k = int(np.searchsorted(np.cumsum(vols[order]), frac * vols.sum())) + 1
                valid[idx[order[:k]]] = False
                n_removed += k
                fraction = float(np.sum(_vol(rad_cap[valid], dim))) / c.volume
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
    return _Packing(pos, rad[keep], c, info)


# ----------------------------------------------------------------------------- bonding
def _pairs(pos, rad, max_gap):
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


def _wall_overlap(pos, rad, c: _Container):
    """Largest overlap of any particle with the container walls [m] (<= 0: none)."""
    pts, nrm = _wall_planes(c)
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


def _gap_for(target, i, j, gap, n, floaters, max_gap):
    """The gap tolerance (in [0, max_gap]) whose N-bar is closest to ``target``
    (the smallest such); returns (gap_tolerance, N-bar, lowest N-bar, highest N-bar)."""
    ts, zbar, gs, pairs = _coordination_curve(i, j, gap, n, floaters)
    best = int(np.argmin(np.abs(zbar - target)))
    k = int(pairs[best])
    nxt = gs[k] if k < gs.size else max_gap
    g = 0.5 * (ts[best] + nxt) if nxt > ts[best] else ts[best]  # halfway to the next pair
    return float(min(max(g, 0.0), max_gap)), float(zbar[best]), float(zbar.min()), float(zbar.max())


def _handle_floaters(pos, rad, c: _Container, g, mode):
    """Particles with no neighbour within the gap tolerance ``g``: "keep" them,
    "remove" them, or "attach" them: move each along the line to its nearest
    connected neighbour by the gap, so that it touches it.  The move shortens no
    other gap by more than that gap, so it creates no overlap with particles whose
    gap was larger; every candidate position is checked against particles and
    walls, and a floater that cannot be attached is removed.
    Returns (pos, rad, n_floaters, n_attached, n_removed)."""
    from scipy.spatial import cKDTree

    n = rad.size
    i, j, _ = _pairs(pos, rad, g)
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
    pts, nrm = (np.asarray(a, float) for a in _wall_planes(c))
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


def _finish(pk: _Packing, *, seed, density, bond, gap_tolerance, target_coordination,
            coordination_tolerance, max_gap_tolerance, floaters, overlap_limit,
            t_start, target_porosity) -> Specimen:
    c = pk.container
    dim = c.dim
    pos, rad = pk.pos, pk.rad
    r_mean0 = float(rad.mean())
    if target_coordination is not None:
        max_gap = 0.5 * r_mean0 if max_gap_tolerance is None else float(max_gap_tolerance)
        i, j, gap = _pairs(pos, rad, max_gap)
        g, zbar, z_lo, z_hi = _gap_for(float(target_coordination), i, j, gap, rad.size,
                                       floaters, max_gap)
        if abs(zbar - target_coordination) > coordination_tolerance:
            phi = 1.0 - float(np.sum(_vol(rad, dim))) / c.volume
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
    i, j, gap = _pairs(pos, rad, g)
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
    _, _, ov = _pairs(pos, rad, 0.0)
    overlap = max(0.0, float(-ov.min()) if ov.size else 0.0, _wall_overlap(pos, rad, c))
    if overlap > overlap_limit * r_mean:
        raise RuntimeError(f"specimen: largest overlap {overlap:.4g} m = {overlap / r_mean:.4g} "
                           f"x the mean radius exceeds overlap_limit = {overlap_limit}")
    porosity = 1.0 - float(np.sum(_vol(rad, dim))) / c.volume
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


# ----------------------------------------------------------------------------- public API
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
    c = _container(shape, size)
    r_min, r_max = _check(c, r_min, r_max, density, target_porosity, target_coordination,
                          gap_tolerance, overlap_limit, seed, floaters)
    _check_steps(stage_steps, max_steps, coordination_tolerance, max_gap_tolerance)
    pk = _compact(c, r_min, r_max, int(seed), target_porosity, overlap_limit, density,
                  int(stage_steps), max_steps, progress)
    return _finish(pk, seed=seed, density=density, bond=bond, gap_tolerance=gap_tolerance,
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
    tol = _finite("coordination_tolerance", coordination_tolerance)
    if tol <= 0:
        raise InputError(f"coordination_tolerance must be > 0, got {tol!r}")
    if max_gap_tolerance is not None and _finite("max_gap_tolerance", max_gap_tolerance) <= 0:
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
    c = _container(shape, size)
    z_top = 6.0 if c.dim == 2 else 12.0
    z_target = _finite("target_N", target_N)
    if not 0.0 < z_target < z_top:
        raise InputError(f"target_N must lie in (0, {z_top}) in {c.dim}D, got {target_N!r}")
    r_min, r_max = _check(c, r_min, r_max, density, target_porosity, None, None,
                          overlap_limit, seed, floaters)
    tol = _finite("tolerance", tolerance)
    if tol <= 0:
        raise InputError(f"tolerance must be > 0, got {tolerance!r}")
    _check_steps(stage_steps, max_steps, tol, max_gap_tolerance)
    if isinstance(max_attempts, bool) or not isinstance(max_attempts, (int, np.integer)) \
            or max_attempts < 1:
        raise InputError(f"max_attempts must be a positive integer, got {max_attempts!r}")
    step = _finite("porosity_step", porosity_step)
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
            pk = _compact(c, r_min, r_max, int(seed), phi, overlap_limit, density,
                          int(stage_steps), max_steps, progress)
        except InputError:
            if phi is None:
                raise
            phi = None  # that porosity jammed: the densest packing is the next best
            continue
        max_gap = 0.5 * float(pk.rad.mean()) if max_gap_rel is None else max_gap_rel
        i, j, gap = _pairs(pk.pos, pk.rad, max_gap)
        _, zbar, z_lo, z_hi = _gap_for(z_target, i, j, gap, pk.rad.size, floaters, max_gap)
        phi_reached = 1.0 - float(np.sum(_vol(pk.rad, c.dim))) / c.volume
        attempts.append((phi_reached, z_lo, z_hi))
        if abs(zbar - z_target) <= tol:
            sp = _finish(pk, seed=seed, density=density, bond=bond, gap_tolerance=None,
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


# ----------------------------------------------------------------------------- editing
def as_arrays(specimen):
    """``(particles, bonds, info)`` from a :class:`Specimen`, a ``(particles, bonds)``
    pair or a ``(particles, bonds, info)`` triple."""
    if hasattr(specimen, "particles") and hasattr(specimen, "bonds"):
        return specimen.particles, specimen.bonds, dict(getattr(specimen, "info", {}) or {})
    if len(specimen) == 3:
        particles, bonds, info = specimen
        return particles, bonds, dict(info or {})
    particles, bonds = specimen
    return particles, bonds, {}


def subset(particles, bonds, keep):
    """The particles with ``keep`` (N,) true and the bonds between them, renumbered.

    Returns ``(particles, bonds, rows)``: ``rows`` (n,) are the kept particles'
    old indices.  Bonds with an end outside the subset are dropped; the others
    keep their state (forces, damage, flags)."""
    keep = np.asarray(keep, bool) & np.asarray(particles.valid, bool)
    rows = np.nonzero(keep)[0]
    new_index = np.cumsum(keep) - 1
    parts = Particles(*[jnp.asarray(np.asarray(a)[keep]) for a in particles])
    bi, bj = np.asarray(bonds.i), np.asarray(bonds.j)
    bv = np.asarray(bonds.valid, bool)
    inside = bv & keep[bi] & keep[bj]
    sel = np.nonzero(inside)[0]
    new_bonds = jax.tree_util.tree_map(lambda a: jnp.asarray(np.asarray(a)[sel]), bonds)
    new_bonds = new_bonds._replace(i=jnp.asarray(new_index[bi[sel]], jnp.int32),
                                   j=jnp.asarray(new_index[bj[sel]], jnp.int32))
    return parts, new_bonds, rows


def flatten_disc(specimen_disc, flat_angle_deg):
    """A Brazilian disc with two flat loading faces ("flattened Brazilian disc"):
    the particles reaching beyond the chords at +-``flat_angle_deg`` / 2 from the
    loaded (vertical) diameter are removed, with their bonds.  Returns
    ``(particles, bonds, info)`` (info with ``radius``, ``centre``,
    ``flat_angle_deg``), usable as the specimen of :data:`jdem.lab.BRAZILIAN`."""
    particles, bonds, info = as_arrays(specimen_disc)
    pos = np.asarray(particles.pos, np.float64)
    rad = np.asarray(particles.radius, np.float64)
    valid = np.asarray(particles.valid, bool)
    if "radius" in info:
        big_r = float(info["radius"])
        centre = np.asarray(info.get("centre", (big_r, big_r)), np.float64)
    else:
        lo, hi = (float(np.min(pos[valid, 1] - rad[valid])), float(np.max(pos[valid, 1] + rad[valid])))
        big_r = 0.5 * (hi - lo)
        x_lo = float(np.min(pos[valid, 0] - rad[valid]))
        x_hi = float(np.max(pos[valid, 0] + rad[valid]))
        centre = np.array([0.5 * (x_lo + x_hi), 0.5 * (hi + lo)])
    half = np.deg2rad(float(flat_angle_deg)) / 2.0
    if not 0.0 <= half < np.pi / 4:
        raise InputError(f"flat_angle_deg must lie in [0, 90), got {flat_angle_deg!r}")
    y_flat = big_r * np.cos(half)
    keep = valid & (np.abs(pos[:, 1] - centre[1]) + rad <= y_flat)
    parts, new_bonds, _ = subset(particles, bonds, keep)
    out_info = dict(info, radius=big_r, centre=tuple(float(c) for c in centre),
                    flat_angle_deg=float(flat_angle_deg))
    return parts, new_bonds, out_info
