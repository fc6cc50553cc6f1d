"""Unbonded contact laws between discs / spheres (000 §4.2, §6.4).

* ``linear``: normal force k_n * overlap, incremental tangential spring
  dF_t = -k_t du_t (000 eq 4-1, 4-3), Coulomb limit |F_t| <= mu F_n.
* ``hertz``: F_n = H * overlap^(3/2) with H = 2E / (3(1 - nu^2)) sqrt(R1 R2 / (R1 + R2))
  (000 eq 4-6) and tangential stiffness k_t of 000 eq 4-8, same Coulomb limit.

Unlike particles: stiffnesses (and for Hertz the moduli) are mixed by the
harmonic mean k12 = 2 k1 k2 / (k1 + k2) (000 eq 4-9); Poisson ratios by the
mean; friction by the smaller coefficient.

The relative velocity at the contact point includes particle spin
(000 eq 4-11..4-15 in 2D, the same with cross products in 3D).  The tangential
force is stored per pair in the global frame and turned into the current tangent
plane every step (its history survives neighbour-list rebuilds).  An optional
normal dashpot (``Params.contact_damping``, fraction of critical) damps impacts.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from jdem.kinematics import cross_r_f, cross_w_r, dot, rotate_into_plane, safe_norm, segment_add
from jdem.state import Config, Contacts, Params, Particles


def harmonic_mix(a, b):
    """000 eq 4-9: k12 = 2 k1 k2 / (k1 + k2)."""
    return 2.0 * a * b / jnp.where(a + b > 0, a + b, 1.0)


def normal_law(overlap, r_eff, mat_a, mat_b, params: Params, model: str):
    """Normal force and tangent stiffnesses for an overlap >= 0.

    overlap, r_eff: (...) [m]; mat_a, mat_b: material indices (...).
    Returns (F_n [N], k_n tangent [N/m], k_t [N/m]).
    """
    if model == "linear":
        kn = harmonic_mix(params.kn[mat_a], params.kn[mat_b])
        kt = harmonic_mix(params.ks[mat_a], params.ks[mat_b])
        return kn * overlap, kn, kt
    e = harmonic_mix(params.youngs[mat_a], params.youngs[mat_b])
    nu = 0.5 * (params.poisson[mat_a] + params.poisson[mat_b])
    h = 2.0 * e / (3.0 * (1.0 - nu**2)) * jnp.sqrt(r_eff)  # 000 eq 4-6
    root = jnp.sqrt(jnp.where(overlap > 0, overlap, 0.0))
    fn = h * overlap * root
    kn = 1.5 * h * root
    # 000 eq 4-8: k_t = (E/(1+nu))^(2/3) [12 (1-nu) R* F_n]^(1/3) / (2-nu)
    cube = 12.0 * (1.0 - nu) * r_eff * fn
    cube_root = jnp.where(cube > 0, jnp.where(cube > 0, cube, 1.0) ** (1.0 / 3.0), 0.0)
    kt = (e / (1.0 + nu)) ** (2.0 / 3.0) * cube_root / (2.0 - nu)
    return fn, kn, kt


def tangential_update(shear_old, normal, v_t, kt, fn, mu, dt, touching):
    """Incremental tangential spring with Coulomb limit.  Shapes (..., d)."""
    fs = rotate_into_plane(shear_old, normal) - (kt * dt)[..., None] * v_t
    mag = safe_norm(fs)
    limit = mu * fn
    scale = jnp.where(mag > limit, limit / jnp.where(mag > 0, mag, 1.0), 1.0)
    return jnp.where(touching[..., None], fs * scale[..., None], 0.0)


def dashpot(kn, m_eff, approach_rate, params: Params):
    """Normal viscous force 2 zeta sqrt(m k) * approach rate (000 eq 3-1)."""
    return 2.0 * params.contact_damping * jnp.sqrt(m_eff * kn) * approach_rate


class PairGeometry(NamedTuple):
    """Geometry of every listed pair (C rows): ``branch`` x_j - x_i (C, d), ``dist``,
    unit ``normal`` from i to j, ``overlap`` (0 where not touching), ``touching``
    and the effective radius ``r_eff`` = R_i R_j / (R_i + R_j)."""

    branch: jnp.ndarray
    dist: jnp.ndarray
    normal: jnp.ndarray
    overlap: jnp.ndarray
    touching: jnp.ndarray
    r_eff: jnp.ndarray


def pair_geometry(contacts: Contacts, particles: Particles) -> PairGeometry:
    p = particles
    i, j = contacts.i, contacts.j
    branch = p.pos[j] - p.pos[i]
    dist = safe_norm(branch)
    normal = branch / jnp.where(dist > 0, dist, 1.0)[:, None]
    ri, rj = p.radius[i], p.radius[j]
    overlap = ri + rj - dist
    touching = contacts.valid & (overlap > 0) & (dist > 0)
    r_eff = ri * rj / jnp.where(ri + rj > 0, ri + rj, 1.0)
    return PairGeometry(branch, dist, normal, jnp.where(touching, overlap, 0.0), touching, r_eff)


def pair_law(contacts: Contacts, particles: Particles, params: Params, config: Config):
    """Geometry and normal law of every listed pair: ``(PairGeometry, F_n, k_n, k_t)``."""
    g = pair_geometry(contacts, particles)
    fn, kn, kt = normal_law(g.overlap, g.r_eff, particles.material[contacts.i],
                            particles.material[contacts.j], params, config.contact_model)
    return g, fn, kn, kt


def contact_forces(contacts: Contacts, particles: Particles, params: Params, config: Config):
    """Forces of all listed pairs.

    Returns ``(contacts, force (N, d), torque (N,) | (N, 3), n_touching (N,))``:
    the list with updated tangential history, the summed contact force and torque
    on each particle, and each particle's number of touching contacts.
    """
    p = particles
    n = p.pos.shape[0]
    i, j = contacts.i, contacts.j
    g, fn, kn, kt = pair_law(contacts, p, params, config)
    normal, overlap, touching = g.normal, g.overlap, g.touching  # normal: unit, from i to j
    ri, rj = p.radius[i], p.radius[j]
    # contact point in the middle of the overlap (000 fig 4-4)
    arm_i = (ri - 0.5 * overlap)[:, None] * normal
    arm_j = -(rj - 0.5 * overlap)[:, None] * normal
    v_rel = (p.vel[i] + cross_w_r(p.angvel[i], arm_i)) - (p.vel[j] + cross_w_r(p.angvel[j], arm_j))
    approach = dot(v_rel, normal)  # > 0 when closing
    v_t = v_rel - approach[:, None] * normal

    m_eff = p.mass[i] * p.mass[j] / (p.mass[i] + p.mass[j])
    fn_total = jnp.where(touching, jnp.maximum(fn + dashpot(kn, m_eff, approach, params), 0.0), 0.0)
    mu = jnp.minimum(params.friction[p.material[i]], params.friction[p.material[j]])
    shear = tangential_update(contacts.shear, normal, v_t, kt, fn, mu, params.dt, touching)

    force_i = -fn_total[:, None] * normal + shear
    torque_i = cross_r_f(arm_i, force_i)
    torque_j = cross_r_f(arm_j, -force_i)
    # rows not touching carry exactly zero force and are left out of the sums
    add = lambda rows, index: segment_add(rows, index, n, where=touching)
    force = add(force_i, i) - add(force_i, j)
    torque = add(torque_i, i) + add(torque_j, j)
    ones = touching.astype(jnp.int32)
    count = add(ones, i) + add(ones, j)
    return contacts._replace(shear=shear), force, torque, count


def pair_stiffness(contacts: Contacts, particles: Particles, params: Params, config: Config):
    """Normal and tangential tangent stiffness of every touching listed pair (C,),
    zero elsewhere; used for the critical time step and averaged quantities."""
    g, _, kn, kt = pair_law(contacts, particles, params, config)
    return jnp.where(g.touching, kn, 0.0), jnp.where(g.touching, kt, 0.0), g.touching
