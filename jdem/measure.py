"""Measurements on a state: energies, coordination, wall stresses.

Citations ("000 eq 4-44") refer to the documents listed in REFERENCES.md.

All functions are pure and jit-able; energies are in J (per metre of thickness
in 2D).  Linked-bar quantities (bond strain energy, fracture degree) live in
:mod:`jdem.bond`.
"""
from __future__ import annotations

import jax.numpy as jnp

from jdem import contact
from jdem import damping, integrate
from jdem.kinematics import dot, unit
from jdem.walls import normal_stress, wall_law
from jdem.state import Config, Params, State


def kinetic_energy(state: State):
    """Translational plus rotational kinetic energy with the inertial masses.

    Velocities are the leapfrog half-step values, so this lags positions by dt/2.
    """
    p = state.particles
    rot = p.angvel**2 if p.angvel.ndim == 1 else jnp.sum(p.angvel**2, axis=-1)
    e = 0.5 * p.mass * dot(p.vel, p.vel) + 0.5 * p.inertia * rot
    return jnp.sum(jnp.where(p.valid, e, 0.0))


def gravity_energy(state: State, params: Params):
    """Potential energy of the weights, -sum m_g g.x (zero at the origin)."""
    p = state.particles
    return -jnp.sum(jnp.where(p.valid, p.gravity_mass * dot(p.pos, params.gravity), 0.0))


def _spring_energy(fn, overlap, shear, kt, model):
    normal = 0.5 * fn * overlap if model == "linear" else 0.4 * fn * overlap  # int H d^1.5 = 2/5 F d
    tangential = 0.5 * dot(shear, shear) / jnp.where(kt > 0, kt, 1.0)
    return normal + jnp.where(kt > 0, tangential, 0.0)


def contact_energy(state: State, params: Params, config: Config):
    """Elastic energy stored in unbonded particle–particle and particle–wall contacts."""
    g, fn, _, kt = contact.pair_law(state.contacts, state.particles, params, config)
    e = jnp.sum(_spring_energy(fn, g.overlap, state.contacts.shear, kt, config.contact_model))
    w = state.walls
    if w.point.shape[0]:
        ov, _, fn, _, kt = wall_law(w, state.particles, params, config)
        e = e + jnp.sum(_spring_energy(fn, ov, w.shear, kt, config.contact_model))
    return e


def total_energy(state: State, params: Params, config: Config):
    """Kinetic + gravitational + contact elastic energy (no bonds)."""
    return kinetic_energy(state) + gravity_energy(state, params) + contact_energy(state, params, config)


def coordination_number(state: State):
    """Mean number of touching unbonded contacts per valid particle."""
    touching = contact.pair_geometry(state.contacts, state.particles).touching
    return 2.0 * jnp.sum(touching) / jnp.maximum(jnp.sum(state.particles.valid), 1)


def basic_observables(state: State, params: Params, config: Config):
    """What :func:`jdem.simulate.run` records by default."""
    out = dict(step=state.step, time=state.time, kinetic_energy=kinetic_energy(state),
               coordination=coordination_number(state))
    if state.walls.point.shape[0]:
        out.update(wall_force=state.walls.force, wall_position=state.walls.point,
                   wall_stress=normal_stress(state.walls))
    return out


def synchronized_kinetic_energy(state: State, params: Params, config: Config):
    """Kinetic energy at the same instant as the positions.

    The leapfrog velocities sit half a step behind the positions; this advances
    them by half a step with the current (damped) forces, v(t) = v(t - dt/2) +
    F(t) dt / (2m), the velocity-Verlet form.  Use it for energy balances.
    """
    _, force, torque = integrate.forces(state, params, config)
    p = state.particles
    force, torque = damping.apply(force, torque, p, params)
    half = 0.5 * params.dt
    vel = jnp.where(p.fixed_vel, p.vel, p.vel + force / p.mass[:, None] * half)
    inertia = p.inertia if torque.ndim == 1 else p.inertia[:, None]
    angvel = jnp.where(p.fixed_rot, p.angvel, p.angvel + torque / inertia * half)
    return kinetic_energy(state._replace(particles=p._replace(vel=vel, angvel=angvel)))


def _outer(a, b):
    return a[..., :, None] * b[..., None, :]


def averaged_stress(state: State, params: Params, config: Config, volume):
    """Averaged stress tensor of the particles, compression positive [Pa], (d, d).

    000 eq 4-44: sigma_ij = (1/V) sum over particles k and their contact points c
    of x_i^c T_j^c (T the force on k at c).  Per pair the two particles' terms
    combine to l (x) f with the branch vector l = x_j - x_i and f the force on i,
    so no contact point is needed; wall contacts use the arm from the particle
    centre to the contact point.  The sign is flipped so that compression is
    positive, as in 002.  ``volume`` [m^3; 2D: m^2 x 1 m] is the region the
    particles fill (e.g. the specimen between its platens).  Uses the stored
    contact, bond and wall forces (no dashpots): meaningful near equilibrium.
    """
    p = state.particles
    g, fn, _, _ = contact.pair_law(state.contacts, p, params, config)
    f_i = jnp.where(g.touching[:, None], -fn[:, None] * g.normal + state.contacts.shear, 0.0)
    total = jnp.sum(_outer(g.branch, f_i), axis=0)
    b = state.bonds
    if b.i.shape[0]:
        bl = p.pos[b.j] - p.pos[b.i]
        bn, _ = unit(bl)
        bf = jnp.where(b.valid[:, None], -b.normal_force[:, None] * bn + b.shear_force, 0.0)
        total = total + jnp.sum(_outer(bl, bf), axis=0)
    w = state.walls
    if w.point.shape[0]:
        ov, touch, fnw, _, _ = wall_law(w, p, params, config)
        fw = jnp.where(touch[..., None], fnw[..., None] * w.normal[:, None] + w.shear, 0.0)
        arm = -(p.radius[None] - 0.5 * ov)[..., None] * w.normal[:, None]
        total = total + jnp.sum(_outer(arm, fw), axis=(0, 1))
    return -total / volume
