"""One explicit dynamic-relaxation step (000 §2.3.1–2.3.2).

Citations ("000 eq 2-15") refer to the documents listed in REFERENCES.md.

The force–displacement cycle of 000 eq 2-4..2-17:

1. refresh the neighbour list if some particle moved half the skin;
2. forces from unbonded contacts, linked-bar bonds and walls, plus gravity and
   applied loads (the sum F_sum, M_sum of 000 eq 2-15);
3. damping (000 §3.2);
4. velocities from the central-difference update v += F/m dt (000 eq 2-15),
   except for prescribed degrees of freedom, which keep their velocity;
5. positions x += v dt (000 eq 2-16, 2-17); walls move with their velocity
   (both summed with compensation, :mod:`jdem.precision`).

``step`` works on one system; ``step_batched`` on a leading batch axis of state
and params, refreshing the neighbour lists of the whole batch together so that
the expensive rebuild is not paid at every step under ``vmap``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from jdem import contact, damping, neighbors, walls as walls_mod
from jdem import bond, precision
from jdem.state import Config, Params, State


def forces(state: State, params: Params, config: Config):
    """All forces and torques on the particles for the current (listed) contacts.

    Returns ``(state, force (N, d), torque)`` where ``state`` carries the updated
    contact, wall and bond histories.
    """
    return _forces(state, params, config)[:3]


def _forces(state: State, params: Params, config: Config, always_true=None):
    """:func:`forces` plus the deepest contact overlap over the smaller radius
    (``always_true``: see :func:`jdem.bond.bond_forces`)."""
    p = state.particles
    contacts, f, t, _, depth = contact.contact_forces(state.contacts, p, params, config,
                                                      report_depth=True)
    bonds = state.bonds
    if bonds.i.shape[0] > 0:
        bonds, fb, tb = bond.bond_forces(bonds, p, params, config.dim, state.step,
                                         config.bond_section, always_true)
        f, t = f + fb, t + tb
    walls, fw, tw, _ = walls_mod.wall_forces(state.walls, p, params, config)
    f = f + fw + p.ext_force + p.gravity_mass[:, None] * params.gravity
    t = t + tw + p.ext_torque
    return state._replace(contacts=contacts, walls=walls, bonds=bonds), f, t, depth


def _expand(mask, like):
    return mask.reshape(mask.shape + (1,) * (like.ndim - mask.ndim))


def physics_step(state: State, params: Params, config: Config, boundary=None,
                 always_true=None) -> State:
    """Advance one step assuming the neighbour list is current.

    ``boundary`` (optional) is a pair ``(fn, data)`` of boundary conditions that
    act from outside the particle system (e.g. :mod:`jdem.waves`):
    ``fn(state, params, data) -> (state, force)`` is called first; it may set the
    velocity of prescribed (``fixed_vel``) components, e.g. an input velocity
    history, and returns an extra force (N, d) [N] that is added to the particle
    forces like ``ext_force``.  ``data`` is a pytree (traced, differentiable).
    ``always_true``: see :func:`jdem.bond.bond_forces` (:func:`step_batched`
    passes one from outside its ``vmap``).
    """
    extra = ()
    if boundary is not None:
        fn, data = boundary
        state, *extra = fn(state, params, data)
    state, force, torque, depth = _forces(state, params, config, always_true)
    if extra:
        force = force + extra[0]
        if len(extra) > 1:
            torque = torque + extra[1]
    p = state.particles
    force, torque = damping.apply(force, torque, p, params)
    dt = params.dt
    free_v = ~p.fixed_vel & _expand(p.valid, p.vel)
    free_w = ~p.fixed_rot & _expand(p.valid, p.angvel)
    vel = jnp.where(free_v, p.vel + force / p.mass[:, None] * dt, p.vel)  # 000 eq 2-15
    angvel = jnp.where(free_w, p.angvel + torque / _expand(p.inertia, torque) * dt, p.angvel)
    # 000 eq 2-16, 2-17, summed with compensation (jdem.precision)
    pos, pos_lo = precision.add(p.pos, p.pos_lo, jnp.where(_expand(p.valid, vel), vel, 0.0) * dt)
    particles = p._replace(pos=pos, pos_lo=pos_lo, vel=vel, angvel=angvel)
    ok = healthy(particles, dt, depth)
    bad = jnp.where((state.first_bad_step < 0) & ~ok, state.step, state.first_bad_step)
    return state._replace(particles=particles, walls=walls_mod.advance(state.walls, dt),
                          step=state.step + 1, time=state.time + dt, first_bad_step=bad)


def healthy(particles, dt, depth):
    """The divergence guard of one step, cheap enough to run at every step: all
    positions and velocities finite, no valid particle moving more than half its
    radius in one step (explicit contact dynamics resolve an approach over many
    steps: ~30 per contact period at the recommended step, 000 eq 3-26), and no
    pair overlapping by more than its smaller radius (``depth`` from
    :func:`jdem.contact.contact_forces`: the pair is passing through itself).
    Returns a () bool.  The host loop names the quantity, particle and step
    that failed (:func:`jdem.simulate.diagnose`)."""
    p = particles
    finite = jnp.all(jnp.isfinite(p.pos)) & jnp.all(jnp.isfinite(p.vel)) \
        & jnp.all(jnp.isfinite(p.angvel))
    return finite & (max_step_travel(p, dt) <= 0.5) & (depth <= 1.0)


def max_step_travel(particles, dt):
    """() largest |v| dt / r over the valid particles: the distance a particle
    moves in one step, in its own radii."""
    p = particles
    speed = jnp.sqrt(jnp.sum(p.vel * p.vel, axis=-1))
    return jnp.max(jnp.where(p.valid, speed * dt / jnp.where(p.radius > 0, p.radius, 1.0), 0.0),
                   initial=0.0)


def refresh_neighbors(state: State, config: Config) -> State:
    contacts = neighbors.update(state.contacts, state.particles, config, state.bonds)
    return state._replace(contacts=contacts)


def step(state: State, params: Params, config: Config, boundary=None) -> State:
    """One full step of one system: neighbour refresh, then physics
    (``boundary`` as in :func:`physics_step`)."""
    return physics_step(refresh_neighbors(state, config), params, config, boundary)


def step_batched(state: State, params: Params, config: Config, boundary=None) -> State:
    """One step of a batch (leading axis on every leaf of ``state`` and ``params``,
    and of the boundary data when ``boundary = (fn, data)`` is given).

    The whole batch is rebuilt when any member needs it (rebuilding early is
    always correct), so the rebuild sits in one un-batched ``lax.cond``.
    """
    need = jax.vmap(neighbors.needs_rebuild, in_axes=(0, 0, None))(
        state.contacts, state.particles, config)
    build = jax.vmap(lambda c, p, b: neighbors.build(c, p, config, b))
    contacts = jax.lax.cond(jnp.any(need), lambda c: build(c, state.particles, state.bonds),
                            lambda c: c, state.contacts)
    state = state._replace(contacts=contacts)
    # true, traced and the same for every member: the bond law's conditional
    # (jdem.bond.bond_forces) stays a conditional under the vmap below
    always_true = jnp.all(state.step >= 0)
    if boundary is None:
        return jax.vmap(lambda s, p: physics_step(s, p, config, None, always_true))(
            state, params)
    fn, data = boundary
    one = lambda s, p, d: physics_step(s, p, config, (fn, d), always_true)
    return jax.vmap(one)(state, params, data)
