"""Discs and blocks in one model: the particles of the engine and the rigid
blocks of :mod:`jdem.blocks` advance together and touch each other.

Citations ("000 eq 2-15") refer to the documents listed in REFERENCES.md.

A disc of radius R touches a convex block where its centre c lies closer than
R to the polygon (a disc is a rounded corner of radius R, 000 fig 3-12).  The
signed distance d of c from the polygon is its distance to the nearest edge
when c is outside, and minus its depth below the nearest edge's line when
inside; the overlap is R - d, the normal n points from the block to the disc
(from the nearest boundary point to c, or the nearest edge's outward normal
inside), and the contact point lies half the overlap inside the disc's
surface, as for a disc on a wall.  The contact uses the particles' law
(:mod:`jdem.contact`: the normal law with the block as a body of infinite
radius, as walls are, a normal dashpot on the reduced mass, the incremental
tangential spring with the Coulomb limit, 000 eq 4-3) between the disc's
material and ``block_material``, an index into the same ``Params`` tables.
Its tangential springs are kept densely for every (block, disc) pair, as the
walls keep theirs: blocks in such a model are few.

One coupled step: the disc–block forces at the current positions; then the
particles' step (:func:`jdem.integrate.step`) with those forces added to the
discs, and the blocks' step (:func:`jdem.blocks.cycle.step`) with their
reactions added to the blocks: both see the state at the start of the step, as
every force of 000 eq 2-15 does, and action equals reaction.  The two share
one time step, which must respect both critical steps (:func:`check_timestep`).
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import integrate, neighbors, precision, timestep
from jdem.blocks import cycle, detect
from jdem.blocks.geometry import world_vertices
from jdem.kinematics import cross_r_f, cross_w_r
from jdem.contact import (dashpot, harmonic_mix, normal_law, pair_friction, pair_property,
                          tangential_update)
from jdem.simulate import SimulationDiverged, scan_first
from jdem.state import Config, Params, State
from jdem.validate import InputError, n_materials


class Coupled(NamedTuple):
    """discs   the particles' :class:`jdem.state.State` (2D)
    blocks  the blocks' :class:`jdem.blocks.cycle.BlockState`
    shear   (K, N, 2) tangential spring force of every (block, disc) pair on the
            disc [N] (zero where they do not touch)
    on_blocks  (K, 2) force the discs put on each block in the last step [N]"""

    discs: State
    blocks: cycle.BlockState
    shear: jnp.ndarray
    on_blocks: jnp.ndarray


class DiscBlockContacts(NamedTuple):
    """Every (block, disc) pair, (K, N) leading axes: ``overlap`` [m] (0 where not
    touching), ``normal`` (K, N, 2) from the block to the disc, ``point`` (K, N,
    2) [m], ``touching`` bool, ``fn`` [N] normal force with its dashpot,
    ``force`` (K, N, 2) [N] on the disc (the block gets minus it)."""

    overlap: jnp.ndarray
    normal: jnp.ndarray
    point: jnp.ndarray
    touching: jnp.ndarray
    fn: jnp.ndarray
    force: jnp.ndarray


class CoupledRun(NamedTuple):
    """What :func:`run` returns: the final ``model``, the ``history`` (NumPy
    arrays, records along axis 0, and ``wall_time``), and the two ``config``
    and ``block_config`` in force at the end (a list that overflowed has grown)."""

    model: Coupled
    history: dict
    config: Config
    block_config: Config


def couple(discs: State, blocks: cycle.BlockState) -> Coupled:
    """A coupled model from a particle state and a block state (both 2D), with
    no disc–block spring yet."""
    if discs.particles.pos.shape[-1] != 2:
        raise InputError(f"discs and blocks couple in 2D; the particles have dimension "
                         f"{discs.particles.pos.shape[-1]}")
    k, n = blocks.blocks.pos.shape[0], discs.particles.pos.shape[0]
    dtype = discs.particles.pos.dtype
    return Coupled(discs=discs, blocks=blocks, shear=jnp.zeros((k, n, 2), dtype),
                   on_blocks=jnp.zeros((k, 2), dtype))


def disc_block_geometry(blocks, particles):
    """Signed distance of every disc centre from every block and where they meet.

    Returns ``(overlap (K, N) [m] (R - distance, may be negative), normal (K, N,
    2) unit, from the block to the disc, point (K, N, 2) [m] the contact point,
    half the overlap inside the disc's surface)``."""
    w = world_vertices(blocks)                                   # (K, V, 2)
    a = w[:, None, :, :]                                         # (K, 1, V, 2)
    b = jnp.roll(w, -1, axis=1)[:, None, :, :]
    edge = b - a
    length2 = jnp.sum(edge * edge, axis=-1)                      # (K, 1, V)
    edge_ok = blocks.vert_valid[:, None, :] & (length2 > 0)
    safe2 = jnp.where(edge_ok, length2, 1.0)
    # the centre relative to each edge start, kept exact for float32 positions
    c = particles.pos[None, :, None, :]
    rel = precision.difference(c, particles.pos_lo[None, :, None, :], a, jnp.zeros_like(a))
    t = jnp.clip(jnp.sum(rel * edge, axis=-1) / safe2, 0.0, 1.0)
    to_c = rel - t[..., None] * edge                             # nearest edge point -> c
    dist2 = jnp.where(edge_ok, jnp.sum(to_c * to_c, axis=-1), jnp.inf)
    outward = jnp.stack([edge[..., 1], -edge[..., 0]], axis=-1) / jnp.sqrt(safe2)[..., None]
    height = jnp.where(edge_ok, jnp.sum(rel * outward, axis=-1), -jnp.inf)   # (K, N, V)
    inside = jnp.max(height, axis=-1) <= 0.0
    nearest = jnp.argmin(dist2, axis=-1)
    face = jnp.argmax(height, axis=-1)
    pick = lambda arr, k: jnp.take_along_axis(arr, k[..., None, None], axis=-2)[..., 0, :]
    to_near = pick(to_c, nearest)
    d_out2 = jnp.take_along_axis(dist2, nearest[..., None], axis=-1)[..., 0]
    positive = ~inside & (d_out2 > 0)
    d_out = jnp.sqrt(jnp.where(positive, d_out2, 1.0))
    normal = jnp.where(inside[..., None], pick(outward, face),
                       to_near / d_out[..., None])
    signed = jnp.where(inside, jnp.max(height, axis=-1), d_out)
    radius = particles.radius[None, :]
    overlap = radius - signed
    point = particles.pos[None] - normal * (radius - 0.5 * overlap)[..., None]
    return overlap, normal, point


def disc_block_forces(blocks, particles, shear, params: Params, config: Config,
                      block_material=0):
    """The contact forces between every block and every disc (module docstring).

    Returns ``(shear (K, N, 2), disc force (N, 2) [N], disc torque (N,) [N m],
    block force (K, 2) [N], block moment (K,) [N m], DiscBlockContacts)``."""
    overlap, normal, point = disc_block_geometry(blocks, particles)
    touching = blocks.valid[:, None] & particles.valid[None, :] & (overlap > 0)
    overlap = jnp.where(touching, overlap, 0.0)
    mat_d = jnp.broadcast_to(particles.material[None, :], overlap.shape)
    mat_b = jnp.full(overlap.shape, block_material, mat_d.dtype)
    r_eff = jnp.broadcast_to(particles.radius[None, :], overlap.shape)
    fn, kn, kt = normal_law(overlap, r_eff, mat_d, mat_b, params, config.contact_model)
    # velocities of the two bodies at the contact point
    arm_d = point - particles.pos[None]                          # disc centre -> point
    arm_b = point - blocks.pos[:, None, :]                       # block centroid -> point
    v_d = particles.vel[None] + cross_w_r(particles.angvel[None], arm_d)
    v_b = blocks.vel[:, None, :] + cross_w_r(blocks.angvel[:, None], arm_b)
    v_rel = v_d - v_b
    approach = -jnp.sum(v_rel * normal, axis=-1)                 # > 0 closing
    v_t = v_rel + approach[..., None] * normal
    # reduced mass; a fixed block counts as infinitely heavy (m_eff = the disc's)
    m_d, m_b = particles.mass[None, :], blocks.mass[:, None]
    both = m_d + m_b                  # 0 only for padding rows, masked below
    m_eff = jnp.where(blocks.fixed[:, None], m_d, m_d * m_b / jnp.where(both > 0, both, 1.0))
    fn_total = jnp.where(touching, jnp.maximum(fn + dashpot(kn, m_eff, approach, params), 0.0),
                         0.0)
    mu = pair_friction(params, config, mat_d, mat_b)
    shear = tangential_update(shear, normal, v_t, kt, fn, mu, params.dt, touching)
    force = fn_total[..., None] * normal + shear                 # on the disc
    disc_force = jnp.sum(force, axis=0)
    disc_torque = jnp.sum(cross_r_f(arm_d, force), axis=0)
    block_force = -jnp.sum(force, axis=1)
    block_moment = -jnp.sum(cross_r_f(arm_b, force), axis=1)
    info = DiscBlockContacts(overlap=overlap, normal=normal, point=point, touching=touching,
                             fn=fn_total, force=force)
    return shear, disc_force, disc_torque, block_force, block_moment, info


def _added(state, params, data):
    """The particles' boundary hook (:func:`jdem.integrate.physics_step`): add the
    disc–block force and torque."""
    return state, data[0], data[1]


def step(model: Coupled, params: Params, block_params: cycle.BlockParams, config: Config,
         block_config: Config, *, block_material=0, sharp_corners=False,
         coulomb_only=False) -> Coupled:
    """One coupled step (module docstring); ``sharp_corners`` and ``coulomb_only``
    as in :func:`jdem.blocks.cycle.contact_forces`."""
    b = model.blocks.blocks
    shear, f_d, t_d, f_b, m_b, _ = disc_block_forces(
        b, model.discs.particles, model.shear, params, config, block_material)
    discs = integrate.step(model.discs, params, config, boundary=(_added, (f_d, t_d)))
    pushed = model.blocks._replace(blocks=b._replace(ext_force=b.ext_force + f_b,
                                                     ext_torque=b.ext_torque + m_b))
    blocks = cycle.step(pushed, block_params, block_config, sharp_corners, coulomb_only)
    blocks = blocks._replace(blocks=blocks.blocks._replace(ext_force=b.ext_force,
                                                           ext_torque=b.ext_torque))
    return Coupled(discs=discs, blocks=blocks, shear=shear, on_blocks=f_b)


def default_observe(model: Coupled) -> dict:
    """Disc positions (N, 2) and velocities, block positions (K, 2), angles (K,),
    velocities, the force of the discs on each block (K, 2) [N] and the step."""
    p, b = model.discs.particles, model.blocks.blocks
    return dict(disc_pos=p.pos, disc_vel=p.vel, block_pos=b.pos, block_angle=b.angle,
                block_vel=b.vel, on_blocks=model.on_blocks, step=model.discs.step)


@functools.partial(jax.jit, static_argnames=("config", "block_config", "n_records",
                                             "record_every", "observe", "block_material",
                                             "sharp_corners", "coulomb_only"))
def rollout(model: Coupled, params: Params, block_params: cycle.BlockParams, config: Config,
            block_config: Config, n_records: int, record_every: int, observe=None,
            block_material=0, sharp_corners=False, coulomb_only=False, n_run=None):
    """``n_records`` x ``record_every`` coupled steps as a pure function (jit, vmap,
    grad).  ``observe(model) -> dict`` is recorded after each block of steps
    (default :func:`default_observe`), with ``overflowed``: whether either
    neighbour list (the discs' or the blocks') has overflowed by then.
    ``n_run`` as in :func:`jdem.blocks.cycle.rollout`.
    Returns ``(model, history)``, each record stacked on a leading axis."""
    observe = observe or default_observe

    def chunk(m, _):
        m = jax.lax.fori_loop(0, record_every, lambda _, x: step(
            x, params, block_params, config, block_config, block_material=block_material,
            sharp_corners=sharp_corners, coulomb_only=coulomb_only), m)
        rec = observe(m)
        rec["overflowed"] = (neighbors.overflowed(m.discs.contacts, config)
                             | neighbors.overflowed(m.blocks.contacts, block_config))
        return m, rec

    return scan_first(jax.checkpoint(chunk), model, jnp.arange(n_records), n_run)


def contact_limit(model: Coupled, params: Params, config: Config, block_material=0):
    """The stable step of the disc–block springs [s]: a disc pressed by a block's
    spring (k_n + k_t, the particles' linear law between the disc's material
    and ``block_material``) and, on its other side, by the same spring of a
    neighbour moving against it (the doubling of :mod:`jdem.timestep`), with
    the contact dashpot; the lightest disc decides.  Linear contact law only."""
    if config.contact_model != "linear":
        raise InputError(f"discs and blocks couple through the linear contact law; config."
                         f"contact_model = {config.contact_model!r}")
    p = model.discs.particles
    mat_b = jnp.full(p.material.shape, block_material, p.material.dtype)
    kn = pair_property(params.kn, p.material, mat_b, harmonic_mix)
    kt = pair_property(params.ks, p.material, mat_b, harmonic_mix)
    c = 2.0 * params.contact_damping * jnp.sqrt(p.mass * kn)
    dt = timestep.damped_limit(2.0 * (kn + kt) / p.mass,
                               2.0 * c / p.mass + params.viscous_damping)
    return float(jnp.min(jnp.where(p.valid, dt, jnp.inf)))


def check_timestep(model: Coupled, params: Params, block_params: cycle.BlockParams,
                   config: Config, block_material=0) -> float:
    """Raise ``InputError`` unless both systems share one step that is below
    the particles' critical step (:func:`jdem.timestep.check_timestep`), the
    blocks' (:func:`jdem.blocks.cycle.critical_timestep`) and the disc–block
    springs' (:func:`contact_limit`).  Returns the smallest of the three [s]."""
    dt, dt_b = float(params.dt), float(block_params.dt)
    if dt != dt_b:
        raise InputError(f"params.dt = {dt!r} s and block_params.dt = {dt_b!r} s must be "
                         f"equal: the discs and the blocks advance together")
    n_mat = n_materials(params)
    if not 0 <= int(block_material) < n_mat:
        raise InputError(f"block_material = {block_material!r} is not a material of params "
                         f"(it has {n_mat})")
    crit = timestep.check_timestep(model.discs, params, config)   # raises above it
    limits = {"the blocks": float(cycle.critical_timestep(model.blocks.blocks, block_params)),
              "the disc-block contacts": contact_limit(model, params, config, block_material)}
    for what, limit in limits.items():
        if dt > limit:
            raise InputError(f"params.dt = {dt:.4g} s exceeds the critical step of {what}, "
                             f"{limit:.4g} s (000 eq 3-24)")
    return min(crit, *limits.values())


def run(model: Coupled, params: Params, block_params: cycle.BlockParams, config: Config,
        block_config: Config, n_steps: int, *, record_every: int = 100, observe=None,
        block_material=0, progress=True):
    """Host loop over :func:`rollout` chunks (:func:`jdem.blocks.cycle.run_in_chunks`):
    checks the time step first (:func:`check_timestep`), grows a neighbour list
    and runs a chunk again when it overflowed, shows progress, and raises
    :class:`jdem.simulate.SimulationDiverged` with the last good model (the
    start of the chunk) when a body's state turns non-finite, a disc fails the
    particles' divergence guard, or a block moves half its list's skin in a step
    (:func:`jdem.blocks.cycle.blocks_healthy`).

    Returns a :class:`CoupledRun`."""
    if int(record_every) < 1 or int(n_steps) < 1:
        raise InputError(f"n_steps and record_every must be >= 1, got {n_steps!r}, "
                         f"{record_every!r}")
    check_timestep(model, params, block_params, config, block_material)
    g, g_b = np.asarray(params.gravity), np.asarray(block_params.gravity)
    if not np.array_equal(g, g_b):
        raise InputError(f"params.gravity = {g.tolist()} and block_params.gravity = "
                         f"{g_b.tolist()} must be equal: the discs and the blocks share a "
                         f"world")
    sharp = not bool(np.any(np.asarray(block_params.corner_radius) > 0))
    coulomb_only = not bool(np.any(np.asarray(block_params.cy_friction0) > 0))
    dt = float(params.dt)

    def chunk(n, k, records):
        nonlocal model, config, block_config
        new, hist = rollout(model, params, block_params, config, block_config, n,
                            int(record_every), observe, int(block_material), sharp,
                            coulomb_only, jnp.int32(k))
        if bool(neighbors.overflowed(new.discs.contacts, config)):
            contacts, config = neighbors.reallocate(
                model.discs.contacts, model.discs.particles, config, model.discs.bonds)
            model = model._replace(discs=model.discs._replace(contacts=contacts))
            return None
        if bool(neighbors.overflowed(new.blocks.contacts, block_config)):
            contacts, block_config = neighbors.reallocate(
                model.blocks.contacts, detect.bounding_circles(model.blocks.blocks),
                block_config)
            model = model._replace(blocks=model.blocks._replace(contacts=contacts))
            return None
        discs_ok = all(bool(jnp.all(jnp.isfinite(x)))
                       for x in jax.tree_util.tree_leaves(new.discs.particles)
                       if jnp.issubdtype(x.dtype, jnp.floating))
        if not discs_ok or int(new.discs.first_bad_step) >= 0 \
                or not cycle.blocks_healthy(new.blocks.blocks, dt, block_config.skin):
            raise SimulationDiverged(int(model.discs.step), model,
                                     cycle.stack_records(records))
        model = new
        return hist

    records, wall = cycle.run_in_chunks(chunk, n_steps, record_every, "discs + blocks",
                                        progress)
    history = cycle.stack_records(records)
    history["wall_time"] = wall
    return CoupledRun(model, history, config, block_config)
