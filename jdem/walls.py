"""Rigid planar walls: prescribed velocity or servo-controlled normal stress
(000 §4.4.1, servo law 000 eq 4-69).
Citations ("000 eq 4-69") refer to the documents listed in REFERENCES.md.

A wall is an infinite plane through ``point`` with unit ``normal`` pointing into
the particle domain.  Particle–wall contacts use the same contact law as
particle pairs (the wall has a material index; for Hertz it acts as a sphere of
infinite radius).  The tangential history of every (wall, particle) pair is kept
densely in ``Walls.shear`` (W, N, d): walls are few, so no list is needed.

Servo control follows the PFC/Itasca reading of 000 eq 4-69: the wall's normal
speed is proportional to the stress error,

    v = G (sigma_target - sigma_measured),   G = alpha A / (sum k_n * dt),

where sum k_n is the total normal stiffness of the particles touching the wall
and 0 < alpha < 1 (``servo_gain``) keeps the wall from over-shooting in one step.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jdem import precision
from jdem.contact import dashpot, normal_law, pair_friction, tangential_update
from jdem.kinematics import components, computed_once, cross_r_f, cross_w_r, dot, scale
from jdem.state import Config, Params, Particles, Walls


def wall_law(walls: Walls, particles: Particles, params: Params, config: Config):
    """Overlap of every (wall, particle) pair and the contact law there.

    Returns ``(overlap, touching, F_n, k_n, k_t)``, each (W, N); ``overlap`` is 0
    where not touching.  For Hertz the wall acts as a sphere of infinite radius.
    """
    p = particles
    gap = precision.difference(p.pos[None], p.pos_lo[None], walls.point[:, None, :],
                               walls.point_lo[:, None, :])
    dist = dot(gap, walls.normal[:, None, :])  # (W, N)
    overlap = p.radius[None] - dist
    touching = walls.valid[:, None] & p.valid[None] & (overlap > 0)
    overlap = jnp.where(touching, overlap, 0.0)
    mat_p = jnp.broadcast_to(p.material[None], overlap.shape)
    mat_w = jnp.broadcast_to(walls.material[:, None], overlap.shape)
    r_eff = jnp.broadcast_to(p.radius[None], overlap.shape)
    fn, kn, kt = normal_law(overlap, r_eff, mat_p, mat_w, params, config.contact_model)
    return overlap, touching, fn, kn, kt


def wall_forces(walls: Walls, particles: Particles, params: Params, config: Config):
    """Contact forces between every wall and every particle.

    Returns ``(walls, force (N, d), torque, n_touching (N,))``; ``walls.force``
    (W, d) is set to the total force the particles exert on each wall and
    ``walls.n_contacts`` to the number touching it.
    """
    p = particles
    if walls.point.shape[0] == 0:
        zero_t = jnp.zeros_like(p.ext_torque)
        return walls, jnp.zeros_like(p.pos), zero_t, jnp.zeros(p.pos.shape[:1], jnp.int32)
    # vectors as component tuples of (W, N) arrays (see jdem.kinematics)
    normal = tuple(c[:, None] for c in components(walls.normal))  # (W, 1) each

    def per_pair_law():
        overlap, touching, fn, kn, kt = wall_law(walls, p, params, config)
        arm = scale(-(p.radius[None] - 0.5 * overlap), normal)  # centre -> contact point
        spin = p.angvel[None] if p.angvel.ndim == 1 else tuple(c[None] for c in components(p.angvel))
        v_rel = tuple(v[None] + s - vw[:, None] for v, s, vw in
                      zip(components(p.vel), cross_w_r(spin, arm), components(walls.vel)))
        approach = -dot(v_rel, normal)  # > 0 when the particle closes on the wall
        v_t = tuple(v + approach * n for v, n in zip(v_rel, normal))
        fn_total = jnp.where(touching, jnp.maximum(fn + dashpot(kn, p.mass[None], approach, params),
                                                   0.0), 0.0)
        mu = pair_friction(params, config, p.material[None], walls.material[:, None])
        shear = tangential_update(components(walls.shear), normal, v_t, kt, fn, mu, params.dt,
                                  touching)
        return arm, shear, fn_total, touching, jnp.where(touching, kn, 0.0)

    # the law once, into memory (counts are >= 0: see kinematics.computed_once)
    arm, shear, fn_total, touching, kn_touching = computed_once(
        per_pair_law, jnp.all(walls.n_contacts >= 0))
    force_pw = tuple(fn_total * n + s for n, s in zip(normal, shear))  # on the particle
    torque_pw = cross_r_f(arm, force_pw)
    walls = walls._replace(shear=jnp.stack(shear, axis=-1),
                           force=-jnp.stack([jnp.sum(f, axis=1) for f in force_pw], axis=-1),
                           n_contacts=jnp.sum(touching, axis=1).astype(jnp.int32))
    kn_sum = jnp.sum(kn_touching, axis=1)
    walls = _servo(walls, kn_sum, params)
    force = jnp.stack([jnp.sum(f, axis=0) for f in force_pw], axis=-1)
    if isinstance(torque_pw, tuple):
        torque = jnp.stack([jnp.sum(t, axis=0) for t in torque_pw], axis=-1)
    else:
        torque = jnp.sum(torque_pw, axis=0)
    return walls, force, torque, jnp.sum(touching, axis=0)


def normal_stress(walls: Walls):
    """Compressive normal stress the particles put on each wall [Pa], (W,)."""
    return -dot(walls.force, walls.normal) / walls.area


def _servo(walls: Walls, kn_sum, params: Params) -> Walls:
    """000 eq 4-69: set the normal speed of servo walls from the stress error."""
    k = jnp.maximum(kn_sum, jnp.min(params.kn))  # a free wall still moves at a finite rate
    gain = walls.servo_gain * walls.area / (k * params.dt)
    speed = jnp.clip(gain * (walls.target_stress - normal_stress(walls)), -walls.servo_vmax,
                     walls.servo_vmax)
    tangential = walls.vel - dot(walls.vel, walls.normal)[:, None] * walls.normal
    servo_vel = tangential + speed[:, None] * walls.normal
    return walls._replace(vel=jnp.where(walls.servo[:, None], servo_vel, walls.vel))


def advance(walls: Walls, dt) -> Walls:
    """Move every wall by its velocity over one step."""
    point, point_lo = precision.add(walls.point, walls.point_lo, walls.vel * dt)
    return walls._replace(point=point, point_lo=point_lo)


def crossed_pair(walls: Walls):
    """Two facing walls (opposite normals, both valid) that have passed each
    other: their gap (p_b - p_a) . n_a is no longer positive, so no particle can
    lie between them.  Host-side (NumPy) on one system's walls; returns
    ``(a, b, gap [m])`` of the first such pair, or ``None``."""
    point, normal = np.asarray(walls.point), np.asarray(walls.normal)
    valid = np.asarray(walls.valid)
    for a in range(point.shape[0]):
        for b in range(a + 1, point.shape[0]):
            if valid[a] and valid[b] and float(normal[a] @ normal[b]) < -0.999:
                gap = float((point[b] - point[a]) @ normal[a])
                if gap <= 0.0:
                    return a, b, gap
    return None

