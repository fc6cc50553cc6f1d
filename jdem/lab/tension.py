"""Direct tension of a bonded specimen between grips.

Walls can only push, so the specimen is pulled through *grips*: the particles
whose centres lie within ``grip_depth`` of its bottom and top faces have every
velocity component and their spin prescribed.  The bottom grip is fixed, the
top grip moves away along the loading axis (the last axis) at
``loading_rate`` times the wave speed, after a ramp (as the platen tests,
:mod:`jdem.lab.platen`).  The tensile force is the reaction on the top grip:
the internal forces (bonds and contacts) its particles feel, recomputed at
every record by :func:`jdem.integrate.forces`.

History: ``axial_strain`` = (H - h0) / h0 with H the distance between the grips'
mean centres (extension positive), ``axial_stress`` = tensile force / area
(tension positive), area = width (x depth in 3D), plus the bond counts and
energies of the platen tests and ``kinetic_ratio``.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import bond as bond_mod
from jdem import integrate, measure, precision, timestep
from jdem.batch import broadcast_batch, is_batched, member
from jdem.lab import damping as damping_mod
from jdem.lab.core import LabTest, Plan, Setup, in_precision, n_records_for, ramp
from jdem.lab.platen import (DEFAULT_LOADING_RATE, DEFAULT_RAMP_TRANSITS, DEFAULT_RECORDS,
                             bulk_density, extent, slice_widths)
from jdem.materials import rock_bond_value
from jdem.simulate import make_state
from jdem.specimen import as_arrays
from jdem.validate import InputError


class GripFrame(NamedTuple):
    """h0 grip distance [m]; w0 (d-1,) lateral extents [m]; area [m^2]; ``top``,
    ``bottom`` (N,) grip masks; ``velocity`` () full speed of the top grip [m/s];
    ``background`` [1/s] (:mod:`jdem.lab.damping`); ``z0`` (N,) axial particle
    coordinates at set-up [m], from which the grips' displacements are measured
    (:mod:`jdem.precision`)."""

    h0: jnp.ndarray
    w0: jnp.ndarray
    area: jnp.ndarray
    top: jnp.ndarray
    bottom: jnp.ndarray
    velocity: jnp.ndarray
    background: jnp.ndarray
    z0: jnp.ndarray


def _mean(x, mask):
    return jnp.sum(jnp.where(mask, x, 0.0)) / jnp.maximum(jnp.sum(mask), 1)


def observe(state, params, config, frame):
    """One record: the grips' mean axial displacements since set-up, the reaction
    on the top grip, counts, energies."""
    top, bottom = frame.top, frame.bottom
    _, force, _ = integrate.forces(state, params, config)
    ax = config.dim - 1
    p = state.particles
    u = precision.difference(p.pos[:, ax], p.pos_lo[:, ax], frame.z0, 0.0)
    stats = bond_mod.bond_stats(state.bonds)
    return dict(
        step=state.step, top_disp=_mean(u, top), bottom_disp=_mean(u, bottom),
        top_force=jnp.sum(jnp.where(top, force[:, ax], 0.0)),
        width=slice_widths(state.particles, config.dim),
        fracture_degree=stats["fracture_degree"], n_broken=stats["n_broken"],
        n_tension=stats["n_tension"], n_shear=stats["n_shear"],
        bond_energy=bond_mod.bond_strain_energy(state.bonds, state.particles, params,
                                                config.dim),
        contact_energy=measure.contact_energy(state, params, config),
        kinetic_energy=measure.kinetic_energy(state),
    )


def derive(raw, frame: GripFrame, plan: Plan) -> dict:
    """History (module docstring); records on axis 0."""
    h = {"step": raw["step"]}
    extension = raw["top_disp"] - raw["bottom_disp"]
    h["height"] = frame.h0 + extension
    h["axial_strain"] = jax.lax.stop_gradient(extension / frame.h0)
    h["axial_stress"] = -raw["top_force"] / frame.area
    w0 = frame.w0[None]
    lat = (w0 - raw["width"]) / w0
    h["width"] = raw["width"]
    h["lateral_strain"] = jnp.mean(lat, axis=-1)
    for k in ("fracture_degree", "n_broken", "n_tension", "n_shear", "bond_energy",
              "contact_energy", "kinetic_energy"):
        h[k] = raw[k]
    h["kinetic_ratio"] = raw["kinetic_energy"] / jnp.maximum(
        raw["bond_energy"] + raw["contact_energy"], 1e-300)
    return h


def load(state, k, frame: GripFrame, plan: Plan):
    """Record ``k``: the top grip's speed along the ramp."""
    p = state.particles
    ax = p.pos.shape[-1] - 1
    v = frame.velocity * ramp(k, plan).astype(p.vel.dtype)
    target = jnp.zeros_like(p.vel)
    target = target.at[..., ax].set(jnp.where(frame.top, v[..., None], 0.0))
    grip = frame.top | frame.bottom
    vel = jnp.where(grip[..., None], target, p.vel)
    return state._replace(particles=p._replace(vel=vel))


def boundary(state, params, frame: GripFrame):
    """Background damping against the grips' affine field."""
    p = state.particles
    ax = p.pos.shape[-1] - 1
    z = p.pos[:, ax]
    f, t = damping_mod.affine_force(p, frame.background, ax, _mean(z, frame.bottom), 0.0,
                                    _mean(z, frame.top), _mean(p.vel[:, ax], frame.top))
    return state, f, t


def setup(specimen, params, *, max_strain=1e-3, loading_rate=None, damping=None,
          grip_depth=None, record_every=None, ramp_transits=DEFAULT_RAMP_TRANSITS,
          dt=None, precision=precision.DEFAULT) -> Setup:
    """Direct tension of one specimen (module docstring); ``params`` as for the
    platen tests (unbatched or with a member axis for a sweep).

    max_strain   extension reached at the end
    grip_depth   grip layer thickness [m] from each face (default 2 x largest radius)
    precision    "float32" (default) or "float64" (:mod:`jdem.precision`)
    """
    damping = damping_mod.check(damping_mod.smooth() if damping is None else damping)
    if not (np.isfinite(max_strain) and max_strain > 0):
        raise InputError(f"max_strain must be > 0, got {max_strain!r}")
    rate = DEFAULT_LOADING_RATE if loading_rate is None else float(loading_rate)
    if not (np.isfinite(rate) and rate > 0):
        raise InputError(f"loading_rate must be > 0, got {loading_rate!r}")
    particles, bonds, _ = as_arrays(specimen)
    dim = int(particles.pos.shape[1])
    ax = dim - 1
    valid = np.asarray(particles.valid, bool)
    rad = np.asarray(particles.radius, np.float64)
    depth = 2.0 * float(rad[valid].max()) if grip_depth is None else float(grip_depth)
    lo, hi = extent(particles, ax)
    if not 0 < depth < 0.25 * (hi - lo):
        raise InputError(f"grip_depth must lie in (0, a quarter of the height "
                         f"{0.25 * (hi - lo):.4g} m), got {depth!r}")
    z = np.asarray(particles.pos, np.float64)[:, ax]
    bottom = valid & (z - lo <= depth)
    top = valid & (hi - z <= depth)
    free_state, config = make_state(particles, bonds=bonds)
    fixed_vel = np.asarray(particles.fixed_vel).copy()
    fixed_vel[bottom | top] = True
    fixed_rot = np.asarray(particles.fixed_rot).copy()
    fixed_rot[bottom | top] = True
    gripped = particles._replace(fixed_vel=jnp.asarray(fixed_vel), fixed_rot=jnp.asarray(fixed_rot),
                                 vel=jnp.where(jnp.asarray(bottom | top)[:, None], 0.0,
                                               particles.vel))
    state, config = make_state(gripped, config, bonds=bonds)
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=jnp.asarray(a).dtype), params)
    batched = is_batched(params)
    n_par = int(np.shape(params.dt)[0]) if batched else 1
    members = [member(params, b) for b in range(n_par)] if batched else [params]
    if dt is None:   # the critical step of the free specimen (prescribed rows have none)
        dt = timestep.recommended(min(float(timestep.critical_timestep(free_state, m, config))
                                      for m in members))
    dt = float(dt)
    params = damping_mod.damped_params(params, damping)
    params = params._replace(dt=jnp.full(np.shape(params.dt), dt, jnp.asarray(params.dt).dtype))
    youngs = float(np.max(np.asarray(rock_bond_value(params, "bond_youngs"))))
    rho = bulk_density(particles)
    wave = math.sqrt(youngs / rho)
    h0 = float(z[top].mean() - z[bottom].mean())
    speed = rate * wave
    transit_steps = (hi - lo) / (wave * dt)
    load_steps = max_strain * h0 / (speed * dt)
    ramp_steps = ramp_transits * transit_steps
    if record_every is None:
        record_every = max(1, int((load_steps + 0.5 * ramp_steps) / DEFAULT_RECORDS))
    record_every = int(record_every)
    ramp_records = int(math.ceil(ramp_steps / record_every))
    n_records = n_records_for(load_steps, record_every, ramp_records)
    widths = [extent(particles, a)[1] - extent(particles, a)[0] for a in range(dim - 1)]
    dtype = jnp.asarray(params.dt).dtype
    frame = GripFrame(
        h0=jnp.asarray(h0, dtype), w0=jnp.asarray(np.asarray(slice_widths(particles, dim)), dtype),
        area=jnp.asarray(float(np.prod(widths)), dtype), top=jnp.asarray(top),
        bottom=jnp.asarray(bottom), velocity=jnp.asarray(speed, dtype),
        background=jnp.asarray(damping_mod.background_coefficient(damping, youngs, rho, h0),
                               dtype),
        z0=jnp.asarray(z, dtype))
    if batched:
        state = broadcast_batch(state, n_par)
        frame = broadcast_batch(frame, n_par)
    plan = Plan(test=TENSION, config=config, n_records=n_records, record_every=record_every,
                preload_records=0, ramp_records=ramp_records, batched=batched, damping=damping,
                options=(("loading_rate", rate), ("max_strain", float(max_strain))))
    return in_precision(Setup(state, params, frame, plan), precision)


TENSION = LabTest("tension", setup, load, boundary, observe, derive)
