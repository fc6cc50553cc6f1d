"""The bonded 3D benchmark (``benchmark.py --bonded``): a UCS step loop on a
bonded sphere specimen, the work a platen test or a calibration runs.

Specimen (jdem's own tools, deterministic for a seed):

* a cell: :func:`jdem.specimen.generate` ``("box", ...)`` compacts ~1,000
  spheres, radii uniform in [0.8, 1.2] mm, between walls to the densest
  packing it makes (sized for solid fraction 0.60; the report gives the
  porosity reached);
* the cell tiled n x n x n (copies one cell edge apart: spheres touching a cell
  wall touch the next copy) and cut to the cube of exactly N spheres around
  the centre (the N centres nearest to it in the max-norm);
* every pair closer than 1.05 (r1 + r2) bonded (:func:`jdem.specimen.bonding.near_pairs`,
  :func:`jdem.bond.bonds_for_pairs`): the rule of YADE's
  ``aabbEnlargeFactor = interactionDetectionFactor = 1.05`` with
  ``setCohesionNow``, so both codes carry the same bonds.

Load: :data:`jdem.lab.UCS` with a fixed platen step of 2e-7 x the height per
step, local damping 0.2 (``lab.local(0.2)``), the default rock
(:func:`jdem.materials.rock_params`, E = 30 GPa, bonds that yield, soften and
break).  The timed loop is the lab layer's own compiled record chunk
(``lab.core.record_chunk``, what ``lab.run`` runs), so contact detection,
bond breakage and the walls are all on; compile time is reported apart.
"""
from __future__ import annotations

import math
import time

import numpy as np
import jax
import jax.numpy as jnp

from jdem import lab, measure, neighbors
from jdem.bond import bonds_for_pairs
from jdem.lab import core as lab_core
from jdem.materials import rock_params
from jdem.specimen import generate
from jdem.specimen.bonding import near_pairs
from jdem.state import make_particles

R_RANGE = (0.8e-3, 1.2e-3)      # [m] radii uniform in this range
SOLID_FRACTION = 0.60
BOND_FACTOR = 1.05              # bond every pair with |x_i - x_j| < 1.05 (r_i + r_j)
STRAIN_PER_STEP = 2e-7
LOCAL_DAMPING = 0.2
DENSITY = 2500.0
CELL_N = 1000                   # spheres in the compacted cell


def bonded_specimen(n, seed=0, cell_n=CELL_N, log=print):
    """``(particles, bonds, info)`` of the specimen described in the module
    docstring: ``n`` spheres exactly."""
    r0, r1 = R_RANGE
    mean_r3 = (r1 ** 4 - r0 ** 4) / (4.0 * (r1 - r0))
    side = (cell_n * 4.0 / 3.0 * math.pi * mean_r3 / SOLID_FRACTION) ** (1.0 / 3.0)
    t0 = time.perf_counter()
    # the densest packing jdem's compaction makes between walls: porosity ~0.40
    # (a target of exactly 0.40 jams at ~0.417 in a walled cell of 1,000)
    cell = generate("box", (side, side, side), r0, r1, seed=seed, bond=False)
    cp = cell.particles
    keep = np.asarray(cp.valid, bool)
    pos0, rad0 = np.asarray(cp.pos, np.float64)[keep], np.asarray(cp.radius, np.float64)[keep]
    tiles = int(math.ceil((n / pos0.shape[0]) ** (1.0 / 3.0) + 1e-9))
    if tiles ** 3 * pos0.shape[0] < n * 1.2:      # room for the cube cut
        tiles += 1
    offs = np.stack(np.meshgrid(*[np.arange(tiles)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pos = (pos0[None] + offs[:, None] * side).reshape(-1, 3)
    rad = np.tile(rad0, offs.shape[0])
    centre = 0.5 * tiles * side
    order = np.argsort(np.max(np.abs(pos - centre), axis=1), kind="stable")[:n]
    order.sort()
    pos, rad = pos[order], rad[order]
    i, j, gap = near_pairs(pos, rad, (BOND_FACTOR - 1.0) * 2.0 * r1)
    sel = gap < (BOND_FACTOR - 1.0) * (rad[i] + rad[j])
    i, j = i[sel], j[sel]
    particles = make_particles(pos, rad, density=DENSITY)
    bonds = bonds_for_pairs(i, j, 3, dtype=particles.pos.dtype)
    lo, hi = (pos - rad[:, None]).min(0), (pos + rad[:, None]).max(0)
    vol = float(np.prod(hi - lo))
    bonded = np.zeros(n, bool)
    bonded[i] = bonded[j] = True
    info = dict(n=n, n_bonds=int(i.size), bonds_per_sphere=2.0 * i.size / n,
                cell_spheres=int(pos0.shape[0]), cell_side_m=side, cell_porosity=float(cell.porosity),
                tiles=tiles, cube_extent_m=(hi - lo).tolist(),
                solid_fraction_of_bounding_box=float(np.sum(4.0 / 3.0 * math.pi * rad ** 3)) / vol,
                spheres_without_bond=int(np.sum(~bonded)), radius_range_m=list(R_RANGE),
                bond_rule=f"|x_i - x_j| < {BOND_FACTOR} (r_i + r_j)", seed=seed,
                build_s=time.perf_counter() - t0)
    log(f"[bonded] specimen: {n} spheres, {i.size} bonds ({info['bonds_per_sphere']:.2f} per "
        f"sphere), cell of {pos0.shape[0]} at porosity {cell.porosity:.3f} tiled {tiles}^3, "
        f"{info['build_s']:.1f} s")
    return particles, bonds, pos, rad, (i, j), info


def specimen_height(particles) -> float:
    """Centre-to-centre height of the specimen [m] (the platen step's length scale)."""
    return float(np.ptp(np.asarray(particles.pos)[:, 2]))


def bonded_setup(particles, bonds, precision):
    """The UCS set-up of the benchmark in ``precision``."""
    params = rock_params(3, radius=float(np.mean(R_RANGE)))
    return lab.UCS.setup((particles, bonds), params,
                         platen_step=STRAIN_PER_STEP * specimen_height(particles),
                         damping=lab.local(LOCAL_DAMPING), max_strain=1e-2, record_every=50,
                         ramp_transits=0.0, precision=precision)


def float64_ops(fn, *args):
    """Primitives of ``fn``'s jaxpr (nested ones included: jit, scan, cond
    branches) with a float64 output, for a float32 program run with x64 on."""
    count = 0

    def walk(jaxpr):
        nonlocal count
        for eqn in jaxpr.eqns:
            if any(getattr(v.aval, "dtype", None) == jnp.float64 for v in eqn.outvars):
                count += 1
            for p in eqn.params.values():
                for q in (p if isinstance(p, (tuple, list)) else (p,)):
                    if hasattr(q, "eqns"):
                        walk(q)
                    elif hasattr(q, "jaxpr") and hasattr(q.jaxpr, "eqns"):
                        walk(q.jaxpr)

    walk(jax.make_jaxpr(fn)(*args).jaxpr)
    return count


def time_bonded(particles, bonds, precision, records_per_chunk, chunks, log=print):
    """Compile and time the lab record block on the bonded specimen.  Returns a
    result dict in the layout of ``benchmark.run_case`` (plus the state)."""
    su = bonded_setup(particles, bonds, precision)
    plan, params, frame = su.plan, su.params, su.frame
    state = su.state
    n = int(np.sum(np.asarray(state.particles.valid)))
    k = records_per_chunk * plan.record_every
    fn = lab_core.record_chunk(plan, records_per_chunk)
    k0 = lambda c: jnp.asarray(c * records_per_chunk, jnp.int32)   # noqa: E731
    every = jnp.asarray(records_per_chunk, jnp.int32)                # n_run: all records
    t0 = time.perf_counter()
    compiled = fn.lower(state, params, frame, k0(0)).compile()
    compile_s = time.perf_counter() - t0
    # float64 values in the float32 chunk (x64 on), counted for the report; one is
    # the recorded fracture degree, a ratio of integer counts (jdem.bond.bond_stats)
    f64 = float64_ops(fn, state, params, frame, k0(0)) \
        if precision == "float32" and jax.config.jax_enable_x64 else None
    t0 = time.perf_counter()
    state, _ = jax.block_until_ready(compiled(state, params, frame, k0(0), every))  # warm-up
    warm_s = time.perf_counter() - t0
    if bool(neighbors.overflowed(state.contacts, plan.config)):
        raise RuntimeError("bonded benchmark: the neighbour list overflowed in the warm-up")
    times, builds = [], []
    b_start = int(state.contacts.n_builds)
    for c in range(chunks):
        b0 = int(state.contacts.n_builds)
        t0 = time.perf_counter()
        state, _ = jax.block_until_ready(compiled(state, params, frame, k0(c + 1), every))
        times.append(time.perf_counter() - t0)
        builds.append(int(state.contacts.n_builds) - b0)
        log(f"  [{precision}] chunk {c}: {k / times[-1]:.1f} steps/s, "
            f"{n * k / times[-1] / 1e6:.2f} M particle-steps/s, {builds[-1]} rebuilds")
    times = np.array(times)
    n_bonds = int(np.sum(np.asarray(bonds.valid)))
    steps = k / float(np.median(times))
    agg = k * chunks / float(times.sum())
    broken = int(np.sum(np.asarray(state.bonds.broken) & np.asarray(state.bonds.valid)))
    res = dict(precision=precision, n=n, n_bonds=n_bonds, dt_s=float(params.dt),
               record_every=plan.record_every, chunk_steps=k, chunks=chunks,
               steps_timed=k * chunks, compile_s=compile_s, warmup_s=warm_s,
               chunk_times_s=times.tolist(), chunk_rebuilds=builds,
               rebuilds_timed=int(state.contacts.n_builds) - b_start,
               steps_per_s=steps, particle_steps_per_s=n * steps, bond_steps_per_s=n_bonds * steps,
               steps_per_s_aggregate=agg,
               throughput=dict(aggregate=dict(ms_per_step=1e3 / agg)),
               float64_primitives_in_float32_chunk=f64,
               bonds_broken_at_end=broken,
               final_axial_strain=float(state.step) * STRAIN_PER_STEP,
               contact_capacity=int(state.contacts.i.shape[0]),
               coordination_end=float(measure.coordination_number(state)),
               overflowed=bool(neighbors.overflowed(state.contacts, plan.config)),
               finite=bool(np.all(np.isfinite(np.asarray(state.particles.pos)))))
    log(f"[bonded {precision}] {steps:.1f} steps/s (median chunk), {n * steps / 1e6:.2f} M "
        f"particle-steps/s, {n_bonds * steps / 1e6:.1f} M bond-steps/s; compile {compile_s:.1f} s"
        + (f"; float64 primitives in the float32 chunk: {f64}" if f64 is not None else ""))
    return res, state, params, plan.config


def write_yade_input(path, pos, rad, pairs, particles, params):
    """The spheres, the bonded pairs, the material, the time step and the platen
    speed of a timed case (``params`` as run) for ``bench/yade_bonded.py`` (NumPy
    .npz), so that YADE runs the very same specimen and load."""
    dt = float(params.dt)
    np.savez(path, pos=pos, rad=rad, i=pairs[0], j=pairs[1], **{k: np.asarray(v) for k, v in dict(
        E=float(params.bond_youngs), nu=float(params.bond_poisson), density=DENSITY,
        phi=float(params.bond_friction_angle), T0=float(params.bond_tensile),
        c0=float(params.bond_cohesion), bond_factor=BOND_FACTOR, local_damping=LOCAL_DAMPING,
        dt=dt, platen_speed=STRAIN_PER_STEP * specimen_height(particles) / dt).items()})
