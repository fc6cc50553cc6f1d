"""Critical time step and density scaling (000 §3.3).

000 eq 3-24 gives the stability limit of the central-difference scheme for one
mass on one spring, dt < 2 sqrt(m / k) = 2 / omega.  For a particle with many
contacts we bound its highest frequency by the Gershgorin row sum of the
stiffness matrix: neighbours moving against it double the load on its springs,

    omega_i^2 <= 2 sum_c (k_n + k_t) / m_i                 (translation)
    omega_i^2 <= 2 sum_c k_t a_i (a_i + a_j) / I_i + bonds  (rotation, arm a)

and the critical step is ``min_i 2 / omega_i`` (never larger than the true
limit).  000 eq 3-26 recommends a tenth of the smallest period,
dt = T_min / 10 = 2 pi / (10 omega_max); :func:`recommended` returns that.

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
from jdem.validate import InputError


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
        g = bond.bond_geometry(b, p, params, config.dim)
        live = b.valid
        bk = jnp.where(live, g.kn + g.ks, 0.0)
        k_tr = k_tr + segment_add(bk, b.i, n) + segment_add(bk, b.j, n)
        # shear spring at the bar's mid point plus bending and twisting springs (002 eq 4)
        rot = jnp.where(live, g.ks * g.length**2 / 4 + (g.kn * g.I + g.ks * g.J) / g.area, 0.0)
        k_rot = k_rot + segment_add(rot, b.i, n) + segment_add(rot, b.j, n)
    return k_tr, k_rot


@functools.partial(jax.jit, static_argnames=("config",))
def critical_timestep(state: State, params: Params, config: Config):
    """Largest stable step for the current contacts and bonds [s] (scalar).

    Infinite when nothing touches; use :func:`nominal_critical_timestep` then.
    """
    p = state.particles
    k_tr, k_rot = _stiffness_sums(state, params, config)
    w2 = jnp.maximum(2.0 * k_tr / p.mass, 2.0 * k_rot / p.inertia)
    w2 = jnp.where(p.valid & ~jnp.all(p.fixed_vel, axis=-1), w2, 0.0)
    wmax = jnp.sqrt(jnp.max(w2, initial=0.0))
    return jnp.where(wmax > 0, 2.0 / jnp.where(wmax > 0, wmax, 1.0), jnp.inf)


def nominal_critical_timestep(particles, params: Params, config: Config, *, coordination=None,
                              overlap_ratio=0.01):
    """Critical step assuming every particle has ``coordination`` contacts with
    like particles (default 4 in 2D, 6 in 3D); for Hertz at an overlap of
    ``overlap_ratio`` times the radius.  Use it before contacts exist."""
    p = particles
    z = coordination or (4 if config.dim == 2 else 6)
    overlap = overlap_ratio * p.radius
    _, kn, kt = contact.normal_law(overlap, 0.5 * p.radius, p.material, p.material, params,
                                   config.contact_model)
    w2 = 2.0 * z * (kn + kt) / p.mass
    w2 = jnp.maximum(w2, 2.0 * z * kt * 2 * p.radius**2 / p.inertia)
    wmax = jnp.sqrt(jnp.max(jnp.where(p.valid, w2, 0.0)))
    return 2.0 / wmax


def recommended(critical):
    """000 eq 3-26: dt = T_min / 10 with T_min = pi * dt_crit (eq 3-25)."""
    return np.pi * critical / 10.0


def check_timestep(state: State, params: Params, config: Config):
    """Raise ``InputError`` naming ``params.dt`` if it exceeds the critical step."""
    dt = np.asarray(params.dt)
    crit = np.asarray(critical_timestep(state, params, config))
    if not np.all(np.isfinite(crit)):
        crit = np.minimum(crit, np.asarray(nominal_critical_timestep(state.particles, params, config)))
    if np.any(dt > crit):
        k = int(np.argmax(np.asarray(dt - crit).reshape(-1)))
        raise InputError(
            f"params.dt = {float(np.asarray(dt).reshape(-1)[k % dt.size]):.4g} s exceeds the critical "
            f"time step {float(np.asarray(crit).reshape(-1)[k % crit.size]):.4g} s (000 eq 3-24); "
            f"use at most jdem.timestep.recommended(critical) = "
            f"{float(recommended(np.min(crit))):.4g} s")
    return crit


def scale_density(state: State, params: Params, config: Config, target_dt, *, safety=0.8,
                  uniform=False) -> State:
    """000 §3.3.2 virtual density: raise inertial masses so ``target_dt`` is
    stable with margin ``safety`` (dt <= safety * dt_crit of each particle).

    By default each particle is scaled only as much as it needs; ``uniform=True``
    scales every particle by the largest factor any of them needs, keeping the
    mass ratios.  Gravitational mass is untouched.  Quasi-static problems only.
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
