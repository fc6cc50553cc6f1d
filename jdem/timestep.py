"""Critical time step and density scaling (000 §3.3).

Citations ("000 eq 3-24") refer to the documents listed in REFERENCES.md.

000 eq 3-24 gives the stability limit of the central-difference scheme for one
mass on one spring, dt < 2 sqrt(m / k) = 2 / omega.  For a particle with many
contacts we bound its highest frequency by the Gershgorin row sum of the
stiffness matrix: neighbours moving against it double the load on its springs,

    omega_i^2 <= 2 sum_c (k_n + k_t) / m_i                 (translation)
    omega_i^2 <= 2 sum_c k_t a_i (a_i + a_j) / I_i + bonds  (rotation, arm a)

and the critical step is ``min_i 2 / omega_i`` (never larger than the true
limit).  000 eq 3-26 recommends a tenth of the smallest period,
dt = T_min / 10 = 2 pi / (10 omega_max); :func:`recommended` returns that.

Dashpots shrink the stable step.  The dashpot forces use the velocity of the
last half step, v+ = v- + dt (-k x - c v-) / m, and for one mass, spring and
dashpot (damping ratio zeta, g = c / m = 2 zeta omega) this update is stable for

    dt <= (2 / omega) (sqrt(1 + zeta^2) - zeta) = 2 / (sqrt(omega^2 + g^2 / 4) + g / 2)

(there an eigenvalue of the update map of (x, v) leaves the unit circle at -1).
The damping rate of each particle is bounded by the same row sum,

    g_i <= 2 sum_c c_c / m_i + viscous_damping   (rotation: the bond shear
                                                  dashpots at arm L / 2, over I_i)

with c = 2 zeta sqrt(m* k) for the normal contact and wall dashpots
(``Params.contact_damping``) and the normal and shear dashpots of intact bonds
(``Params.bond_damping``), m* the reduced mass; the critical step is the
smallest of these per-particle limits.  A particle with no spring keeps the
limit of its viscous damping alone, dt < 2 / viscous_damping.  The step
therefore falls as the dashpots grow (zeta = 1: 0.41 of the undamped step,
zeta = 50: 0.01), so no upper bound on the damping ratios is needed:
:func:`check_timestep` refuses a step above the damped limit.  Local
non-viscous damping (000 eq 3-19) is not counted.

Density scaling (000 §3.3.2, "virtual density"): for quasi-static problems the
inertial mass may be raised so that a larger step is stable; the weight keeps
the true (gravitational) mass.  Not for dynamic problems.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jdem import contact
from jdem import bond
from jdem.walls import wall_law
from jdem.kinematics import segment_add
from jdem.state import Config, Params, State
from jdem.validate import InputError, check_materials


def _stiffness_sums(state: State, params: Params, config: Config):
    """Per-particle sums of translational and rotational stiffness (N,) each."""
    p = state.particles
    n = p.pos.shape[0]
    kn, kt, _ = contact.pair_stiffness(state.contacts, p, params, config)
    i, j = state.contacts.i, state.contacts.j
    k_tr = segment_add(kn + kt, i, n) + segment_add(kn + kt, j, n)
    arm = p.radius[i] + p.radius[j]
    k_rot = segment_add(kt * p.radius[i] * arm, i, n) + segment_add(kt * p.radius[j] * arm, j, n)
    w = state.walls
    if w.point.shape[0]:
        _, touch, _, wkn, wkt = wall_law(w, p, params, config)
        k_tr = k_tr + jnp.sum(jnp.where(touch, wkn + wkt, 0.0), axis=0)
        k_rot = k_rot + jnp.sum(jnp.where(touch, wkt * p.radius[None] ** 2, 0.0), axis=0)
    b = state.bonds
    if b.i.shape[0]:
        g = bond.bond_geometry(b, p, params, config.dim, config.bond_section)
        live = b.valid
        bk = jnp.where(live, g.kn + g.ks, 0.0)
        k_tr = k_tr + segment_add(bk, b.i, n) + segment_add(bk, b.j, n)
        # shear spring at the bar's mid point plus bending and twisting springs (002 eq 4);
        # a 2D disc turns only about the normal to the plane, which bends the bar:
        # there is no twist in 2D
        twist = g.ks * g.J if config.dim == 3 else 0.0
        rot = jnp.where(live, g.ks * g.length**2 / 4 + (g.kn * g.I + twist) / g.area, 0.0)
        k_rot = k_rot + segment_add(rot, b.i, n) + segment_add(rot, b.j, n)
    return k_tr, k_rot


def _dashpot_sums(state: State, params: Params, config: Config):
    """Per-particle sums of the dashpot coefficients c = 2 zeta sqrt(m* k) acting on
    translation [N s/m] and rotation [N m s] (N,) each."""
    p = state.particles
    n = p.pos.shape[0]
    i, j = state.contacts.i, state.contacts.j
    kn, _, _ = contact.pair_stiffness(state.contacts, p, params, config)
    m_sum = p.mass[i] + p.mass[j]
    m_eff = p.mass[i] * p.mass[j] / jnp.where(m_sum > 0, m_sum, 1.0)
    c = 2.0 * params.contact_damping * jnp.sqrt(m_eff * kn)   # contact.dashpot
    c_tr = segment_add(c, i, n) + segment_add(c, j, n)
    c_rot = jnp.zeros_like(c_tr)
    w = state.walls
    if w.point.shape[0]:
        _, touch, _, wkn, _ = wall_law(w, p, params, config)
        cw = 2.0 * params.contact_damping * jnp.sqrt(p.mass[None] * jnp.where(touch, wkn, 0.0))
        c_tr = c_tr + jnp.sum(cw, axis=0)
    b = state.bonds
    if b.i.shape[0]:
        mat = bond.bond_material(b, p, params)
        g = bond.bond_geometry(b, p, params, config.dim, config.bond_section, mat)
        live = b.valid & ~b.broken                           # bond dashpots: intact only
        mb = p.mass[b.i] * p.mass[b.j] / jnp.where(live, p.mass[b.i] + p.mass[b.j], 1.0)
        zeta = mat.damping
        visc = lambda k: jnp.where(live, 2.0 * zeta * jnp.sqrt(
            jnp.where(live, mb * k, 0.0)), 0.0)
        cn, cs = visc(g.kn), visc(g.ks)
        c_tr = c_tr + segment_add(cn + cs, b.i, n) + segment_add(cn + cs, b.j, n)
        rot = cs * g.length**2 / 4
        c_rot = c_rot + segment_add(rot, b.i, n) + segment_add(rot, b.j, n)
    return c_tr, c_rot


def damped_limit(w2, g):
    """2 / (sqrt(w2 + g^2 / 4) + g / 2): the stable step of a mass-spring-dashpot
    with omega^2 = w2 and c / m = g.  Without a spring (w2 = 0) it is 2 / g, the
    limit of the dashpot alone (v+ = (1 - dt g) v-); infinite where w2 = g = 0."""
    half = 0.5 * g
    root = jnp.sqrt(w2 + half * half) + half
    moving = root > 0
    return jnp.where(moving, 2.0 / jnp.where(moving, root, 1.0), jnp.inf)


def critical_timestep(state: State, params: Params, config: Config):
    """Largest stable step for the current contacts and bonds [s] (scalar),
    including their dashpots and the viscous damping (module docstring).

    Where nothing touches it is the limit of the viscous damping alone,
    2 / ``viscous_damping`` (infinite without it); use
    :func:`nominal_critical_timestep` for the contacts to come.
    """
    return _critical_and_touching(state, params, config.without_search_grid())[0]


@functools.partial(jax.jit, static_argnames=("config",))
def _critical_and_touching(state: State, params: Params, config: Config):
    """(critical step [s], whether any free particle has a spring), scalars."""
    p = state.particles
    k_tr, k_rot = _stiffness_sums(state, params, config)
    c_tr, c_rot = _dashpot_sums(state, params, config)
    visc = params.viscous_damping
    dt_tr = damped_limit(2.0 * k_tr / p.mass, 2.0 * c_tr / p.mass + visc)
    dt_rot = damped_limit(2.0 * k_rot / p.inertia, 2.0 * c_rot / p.inertia + visc)
    # a degree of freedom that is prescribed cannot go unstable: translation and
    # rotation count apart (a particle held in place may still spin, and one whose
    # spin is held may still move)
    held_rot = p.fixed_rot if p.fixed_rot.ndim == 1 else jnp.all(p.fixed_rot, axis=-1)
    free_tr = p.valid & ~jnp.all(p.fixed_vel, axis=-1)
    free_rot = p.valid & ~held_rot
    dt = jnp.minimum(jnp.where(free_tr, dt_tr, jnp.inf), jnp.where(free_rot, dt_rot, jnp.inf))
    touching = jnp.any((free_tr & (k_tr > 0)) | (free_rot & (k_rot > 0)))
    return jnp.min(dt, initial=jnp.inf), touching


def nominal_critical_timestep(particles, params: Params, config: Config, *, coordination=None,
                              overlap_ratio=0.01):
    """Critical step assuming every particle has ``coordination`` contacts with
    like particles (default 4 in 2D, 6 in 3D); for Hertz at an overlap of
    ``overlap_ratio`` times the radius.  Use it before contacts exist.  The
    contact dashpots and the viscous damping count as in :func:`critical_timestep`."""
    p = particles
    z = coordination or (4 if config.dim == 2 else 6)
    overlap = overlap_ratio * p.radius
    _, kn, kt = contact.normal_law(overlap, 0.5 * p.radius, p.material, p.material, params,
                                   config.contact_model)
    visc = params.viscous_damping
    c = 2.0 * params.contact_damping * jnp.sqrt(0.5 * p.mass * kn)  # like pairs: m* = m / 2
    dt_tr = damped_limit(2.0 * z * (kn + kt) / p.mass, 2.0 * z * c / p.mass + visc)
    dt_rot = damped_limit(2.0 * z * kt * 2 * p.radius**2 / p.inertia, visc)
    return jnp.min(jnp.where(p.valid, jnp.minimum(dt_tr, dt_rot), jnp.inf))


def recommended(critical):
    """000 eq 3-26: dt = T_min / 10 with T_min = pi * dt_crit (eq 3-25)."""
    return np.pi * critical / 10.0


def check_timestep(state: State, params: Params, config: Config):
    """Raise ``InputError`` naming ``params.dt`` if it exceeds the critical step
    (damping included; the message names the damping fields that are on).  The
    material indices are checked first (:func:`jdem.validate.check_materials`)."""
    check_materials(state, params)
    dt = float(params.dt)
    crit, touching = _critical_and_touching(state, params, config.without_search_grid())
    crit = float(crit)
    if not bool(touching):      # the contacts to come
        crit = min(crit, float(nominal_critical_timestep(state.particles, params, config)))
    if dt > crit:
        damped = [f"params.{name} = {float(np.max(np.asarray(getattr(params, name)))):g}"
                  for name in ("contact_damping", "bond_damping", "viscous_damping")
                  if np.any(np.asarray(getattr(params, name)) > 0)]
        with_damping = (f", which includes the damping {', '.join(damped)} (dt_crit = "
                        f"(2 / omega)(sqrt(1 + zeta^2) - zeta))" if damped else "")
        raise InputError(
            f"params.dt = {dt:.4g} s exceeds the critical time step {crit:.4g} s (000 eq 3-24)"
            f"{with_damping}; use at most jdem.timestep.recommended(critical) = "
            f"{recommended(crit):.4g} s")
    return crit


def scale_density(state: State, params: Params, config: Config, target_dt, *, safety=0.8,
                  uniform=False) -> State:
    """000 §3.3.2 virtual density: raise inertial masses so ``target_dt`` is
    stable with margin ``safety`` (dt <= safety * dt_crit of each particle).

    By default each particle is scaled only as much as it needs; ``uniform=True``
    scales every particle by the largest factor any of them needs, keeping the
    mass ratios.  Gravitational mass is untouched.  Quasi-static problems only.
    Only the springs are counted: with dashpots on, :func:`check_timestep` may
    still refuse ``target_dt``.
    """
    p = state.particles
    k_tr, k_rot = _stiffness_sums(state, params, config)
    h = target_dt / safety
    # dt_i = 2 / omega_i >= h  <=>  m >= 2 k h^2 / 4
    need_m = 0.5 * k_tr * h**2
    need_i = 0.5 * k_rot * h**2
    factor = jnp.maximum(1.0, jnp.maximum(need_m / p.mass, need_i / p.inertia))
    if uniform:
        factor = jnp.full_like(factor, jnp.max(jnp.where(p.valid, factor, 1.0)))
    factor = jnp.where(p.valid, factor, 1.0)
    return state._replace(particles=p._replace(mass=p.mass * factor, inertia=p.inertia * factor))
