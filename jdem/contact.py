"""Unbonded contact laws between discs / spheres (000 §4.2, §6.4).

Citations ("000 eq 4-6") refer to the documents listed in REFERENCES.md.

* ``linear``: normal force k_n * overlap, incremental tangential spring
  dF_t = -k_t du_t (000 eq 4-1, 4-3), Coulomb limit |F_t| <= mu F_n.
* ``hertz``: F_n = H * overlap^(3/2) with H = 2E / (3(1 - nu^2)) sqrt(R1 R2 / (R1 + R2))
  (000 eq 4-6) and tangential stiffness k_t of 000 eq 4-8, same Coulomb limit.

Unlike particles: stiffnesses (and for Hertz the moduli) are mixed by the
harmonic mean k12 = 2 k1 k2 / (k1 + k2) (000 eq 4-9); Poisson ratios by the
mean; friction by ``Config.friction_mixing`` (:func:`pair_friction`): the smaller
coefficient (default), their mean, their geometric mean, or a per-pair table over
material indices (walls take part through their material).

The relative velocity at the contact point includes particle spin
(000 eq 4-11..4-15 in 2D, the same with cross products in 3D).  The tangential
force is stored per pair in the global frame and turned into the current tangent
plane every step (its history survives neighbour-list rebuilds).  An optional
normal dashpot (``Params.contact_damping``, fraction of critical) damps impacts.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from jdem import precision
from jdem.validate import InputError
from jdem.kinematics import (components, computed_once, cross_r_f, dot, floored_norm,
                             project_tangent, relative_velocity, rotate_into_plane, safe_norm,
                             same_kind, scale, segment_add)
from jdem.state import FRICTION_RULE_NAMES, Config, Contacts, Params, Particles


def harmonic_mix(a, b):
    """000 eq 4-9: k12 = 2 k1 k2 / (k1 + k2)."""
    return 2.0 * a * b / jnp.where(a + b > 0, a + b, 1.0)


def mean_mix(a, b):
    """Poisson ratios of unlike particles: the mean."""
    return 0.5 * (a + b)


def geometric_mix(a, b):
    """sqrt(a b)."""
    return jnp.sqrt(a * b)


#: the mixing rules of ``Config.friction_mixing`` by name
FRICTION_RULES = dict(zip(FRICTION_RULE_NAMES, (jnp.minimum, mean_mix, geometric_mix)))


def pair_friction(params: Params, config: Config, mat_a, mat_b):
    """Friction coefficient of every pair of materials ``mat_a``, ``mat_b`` (...).

    ``config.friction_mixing`` is a rule of :data:`FRICTION_RULES` applied to
    ``params.friction`` (differentiable with respect to it), or a symmetric
    (M, M) table of coefficients over the M materials (a fixed property of the
    model: ``params.friction`` is then not used)."""
    rule = config.friction_mixing
    if isinstance(rule, str):
        return pair_property(params.friction, mat_a, mat_b, FRICTION_RULES[rule])
    m = params.friction.shape[-1]
    if len(rule) != m:
        raise InputError(f"Config.friction_mixing is a {len(rule)} x {len(rule)} table but "
                         f"Params has {m} materials")
    table = jnp.asarray(rule, params.friction.dtype)
    return table[0, 0] if m == 1 else table.reshape(-1)[mat_a * m + mat_b]


def pair_property(table, mat_a, mat_b, mix):
    """``mix(table[a], table[b])`` for material indices ``mat_a``, ``mat_b`` (...).

    ``table`` (M,) holds one value per material.  The (M, M) mixed table is formed
    once and looked up per pair (one gather instead of two plus the mixing); with a
    single material the result is a scalar and no per-pair lookup is made.  Either
    way each value is the same ``mix`` of the same two numbers, bit for bit.
    """
    m = table.shape[0]
    if m == 1:
        return mix(table[0], table[0])
    return mix(table[:, None], table[None, :]).reshape(-1)[mat_a * m + mat_b]


def normal_law(overlap, r_eff, mat_a, mat_b, params: Params, model: str):
    """Normal force and tangent stiffnesses for an overlap >= 0.

    overlap, r_eff: (...) [m]; mat_a, mat_b: material indices (...).
    Returns (F_n [N], k_n tangent [N/m], k_t [N/m]); with a single material the
    stiffnesses of the linear law are scalars.
    """
    if model == "linear":
        kn = pair_property(params.kn, mat_a, mat_b, harmonic_mix)
        kt = pair_property(params.ks, mat_a, mat_b, harmonic_mix)
        return kn * overlap, kn, kt
    e = pair_property(params.youngs, mat_a, mat_b, harmonic_mix)
    nu = pair_property(params.poisson, mat_a, mat_b, mean_mix)
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
    """Incremental tangential spring with Coulomb limit (000 eq 4-3).

    Vectors as arrays (..., d) or component tuples (:mod:`jdem.kinematics`);
    returns the new tangential force in the kind of ``shear_old``.
    """
    fs = rotate_into_plane(shear_old, normal)
    fs = same_kind([f - kt * dt * v for f, v in zip(components(fs), components(v_t))], shear_old)
    mag = floored_norm(fs)
    limit = mu * fn
    ratio = jnp.where(mag > limit, limit / mag, 1.0)
    return same_kind([jnp.where(touching, f * ratio, 0.0) for f in components(fs)], shear_old)


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


def _pair_geometry_components(contacts: Contacts, particles: Particles) -> PairGeometry:
    """:func:`pair_geometry` with ``branch`` and ``normal`` as component tuples."""
    p = particles
    i, j = contacts.i, contacts.j
    # x_j - x_i from the compensated positions (jdem.precision): the overlap of
    # two 5 cm coordinates to float32's relative precision of the overlap itself
    branch = tuple(precision.difference(x[j], xl[j], x[i], xl[i])
                   for x, xl in zip(components(p.pos), components(p.pos_lo)))
    dist = safe_norm(branch)
    inv = jnp.where(dist > 0, dist, 1.0)
    normal = tuple(b / inv for b in branch)
    ri, rj = p.radius[i], p.radius[j]
    overlap = ri + rj - dist
    touching = contacts.valid & (overlap > 0) & (dist > 0)
    r_eff = ri * rj / jnp.where(ri + rj > 0, ri + rj, 1.0)
    return PairGeometry(branch, dist, normal, jnp.where(touching, overlap, 0.0), touching, r_eff)


def pair_geometry(contacts: Contacts, particles: Particles) -> PairGeometry:
    """Geometry of every listed pair (see :class:`PairGeometry`); vectors as (C, d) arrays."""
    g = _pair_geometry_components(contacts, particles)
    return g._replace(branch=jnp.stack(g.branch, axis=-1), normal=jnp.stack(g.normal, axis=-1))


def pair_law(contacts: Contacts, particles: Particles, params: Params, config: Config):
    """Geometry and normal law of every listed pair: ``(PairGeometry, F_n, k_n, k_t)``."""
    g = pair_geometry(contacts, particles)
    fn, kn, kt = normal_law(g.overlap, g.r_eff, particles.material[contacts.i],
                            particles.material[contacts.j], params, config.contact_model)
    return g, fn, kn, kt


def contact_forces(contacts: Contacts, particles: Particles, params: Params, config: Config,
                   *, report_depth=False):
    """Forces of all listed pairs.

    Returns ``(contacts, force (N, d), torque (N,) | (N, 3), n_touching (N,))``:
    the list with updated tangential history, the summed contact force and torque
    on each particle, and each particle's number of touching contacts.  With
    ``report_depth`` a fifth entry, ``()`` the deepest overlap of a touching pair
    as a fraction of the pair's smaller radius (0 when nothing touches): above 1,
    one centre has crossed the other particle's surface and the pair is about to
    pass through itself (tunnelling; :mod:`jdem.integrate` stops the run there).

    Vectors are handled as component tuples (see :mod:`jdem.kinematics`).
    """
    p = particles
    n = p.pos.shape[0]
    i, j = contacts.i, contacts.j

    def per_pair_law():
        g = _pair_geometry_components(contacts, p)
        normal, overlap, touching = g.normal, g.overlap, g.touching  # normal: unit, i to j
        fn, kn, kt = normal_law(overlap, g.r_eff, p.material[i], p.material[j], params,
                                config.contact_model)
        # contact point in the middle of the overlap (000 fig 4-4): at a_i n from the
        # centre of i and at -a_j n from the centre of j
        a_i = p.radius[i] - 0.5 * overlap
        a_j = p.radius[j] - 0.5 * overlap
        v_rel = relative_velocity(p.vel, p.angvel, i, j, scale(a_i, normal), scale(-a_j, normal))
        approach = dot(v_rel, normal)  # > 0 when closing
        v_t = project_tangent(v_rel, normal)
        m_eff = p.mass[i] * p.mass[j] / (p.mass[i] + p.mass[j])
        fn_total = jnp.where(touching, jnp.maximum(fn + dashpot(kn, m_eff, approach, params), 0.0),
                             0.0)
        mu = pair_friction(params, config, p.material[i], p.material[j])
        shear = tangential_update(components(contacts.shear), normal, v_t, kt, fn, mu, params.dt,
                                  touching)
        return normal, shear, fn_total, a_i, a_j, touching

    # the law once, into memory (n_pairs >= 0 always: see kinematics.computed_once)
    normal, shear, fn_total, a_i, a_j, touching = computed_once(per_pair_law,
                                                                contacts.n_pairs >= 0)
    force_i = tuple(-fn_total * nc + s for s, nc in zip(shear, normal))
    # torques a_i n x F_i on i and (-a_j n) x (-F_i) on j: with n x n = 0 both are
    # multiples of n x shear
    n_cross_shear = cross_r_f(normal, shear)
    as_list = lambda v: list(v) if isinstance(v, tuple) else [v]  # noqa: E731 (2D: scalar)
    # one scatter per side of (C, d + torque components) rows: fewer, wider
    # scatters than one per component (a tenth of the 3D step); rows not touching
    # carry exactly zero force and are left out of the sums
    add = lambda rows, index: segment_add(rows, index, n, where=touching)  # noqa: E731
    rows_i = jnp.stack(list(force_i) + as_list(scale(a_i, n_cross_shear)), axis=1)
    rows_j = jnp.stack([-f for f in force_i] + as_list(scale(a_j, n_cross_shear)), axis=1)
    total = add(rows_i, i) + add(rows_j, j)
    d = len(force_i)
    force = total[:, :d]
    torque = total[:, d:] if total.shape[1] > d + 1 else total[:, d]
    ones = touching.astype(jnp.int32)
    count = add(ones, i) + add(ones, j)
    contacts = contacts._replace(shear=jnp.stack(shear, axis=-1))
    if not report_depth:
        return contacts, force, torque, count
    r_small = jnp.minimum(p.radius[i], p.radius[j])
    overlap = 2.0 * (p.radius[i] - a_i)
    depth = jnp.max(jnp.where(touching, overlap / jnp.where(r_small > 0, r_small, 1.0), 0.0),
                    initial=0.0)
    return contacts, force, torque, count, depth


def pair_stiffness(contacts: Contacts, particles: Particles, params: Params, config: Config):
    """Normal and tangential tangent stiffness of every touching listed pair (C,),
    zero elsewhere; used for the critical time step and averaged quantities."""
    g, _, kn, kt = pair_law(contacts, particles, params, config)
    return jnp.where(g.touching, kn, 0.0), jnp.where(g.touching, kt, 0.0), g.touching
