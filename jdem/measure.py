"""Measurements on a state: energies, coordination, wall stresses, averaged
stress and strain (whole assembly or a measurement window), reactions.

Citations ("000 eq 4-44") refer to the documents listed in REFERENCES.md.

All functions are pure and jit-able; energies are in J (per metre of thickness
in 2D).  Linked-bar quantities (bond strain energy, fracture degree) live in
:mod:`jdem.bond`.
"""
from __future__ import annotations

import jax.numpy as jnp

from jdem import contact
from jdem import damping, integrate, precision
from jdem.kinematics import dot, unit
from jdem.walls import normal_stress, wall_law
from jdem.state import Config, Params, State
from jdem.validate import InputError


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


def in_window(particles, window):
    """(N,) bool: valid particles whose centre lies in the measurement circle
    (2D) / sphere (3D) ``window = (centre (d,), radius)`` [m]."""
    centre, radius = window
    d = particles.pos - jnp.asarray(centre, particles.pos.dtype)
    return particles.valid & (dot(d, d) <= jnp.asarray(radius, particles.pos.dtype) ** 2)


def _ball(r, dim):
    """Area pi r^2 (2D, unit thickness) or volume 4/3 pi r^3 (3D); traceable."""
    return jnp.pi * r**2 if dim == 2 else 4.0 / 3.0 * jnp.pi * r**3


def window_volume(window, dim):
    """Volume of the measurement window [m^3; 2D: m^2 x 1 m]."""
    return _ball(window[1], dim)


def _lens(r, big_r, d, dim):
    """Area (2D) / volume (3D) of the intersection of a particle of radius ``r``
    with the window of radius ``big_r`` at centre distance ``d`` (all (N,))."""
    inside = d <= jnp.abs(big_r - r)
    apart = d >= r + big_r
    full = _ball(jnp.minimum(r, big_r), dim)
    dd = jnp.where(inside | apart, 0.5 * (r + big_r + jnp.abs(big_r - r)), d)  # safe in the formulas
    if dim == 2:
        c1 = jnp.clip((dd**2 + r**2 - big_r**2) / (2 * dd * r), -1.0, 1.0)
        c2 = jnp.clip((dd**2 + big_r**2 - r**2) / (2 * dd * big_r), -1.0, 1.0)
        kite = (-dd + r + big_r) * (dd + r - big_r) * (dd - r + big_r) * (dd + r + big_r)
        part = r**2 * jnp.arccos(c1) + big_r**2 * jnp.arccos(c2) - 0.5 * jnp.sqrt(
            jnp.maximum(kite, 0.0))
    else:
        part = jnp.pi * (r + big_r - dd)**2 * (dd**2 + 2 * dd * big_r - 3 * big_r**2 + 2 * dd * r
                                               + 6 * r * big_r - 3 * r**2) / (12 * dd)
    return jnp.where(inside, full, jnp.where(apart, 0.0, part))


def window_solid_correction(particles, window):
    """The volume of the particles counted in a window (centres inside) over the
    volume of all particles that lies inside it (exact disc–circle /
    sphere–sphere intersections): near 1 for a window many particles wide, off
    by the order of a diameter over the window's otherwise.  The stress of a
    window is the moment sum over V_w times this ratio, which is the
    measurement-circle rule sigma = (1 - n) / (sum of counted V_p) x sum, with
    n the window's porosity."""
    p = particles
    dim = p.pos.shape[1]
    centre, big_r = window
    dvec = p.pos - jnp.asarray(centre, p.pos.dtype)
    d = jnp.sqrt(dot(dvec, dvec))
    counted = jnp.sum(jnp.where(in_window(p, window), _ball(p.radius, dim), 0.0))
    inside = jnp.sum(jnp.where(p.valid, _lens(p.radius, jnp.asarray(big_r, p.pos.dtype), d, dim),
                               0.0))
    return counted / jnp.where(inside > 0, inside, 1.0)


def averaged_stress(state: State, params: Params, config: Config, volume=None, *, window=None):
    """Averaged stress tensor of the particles, compression positive [Pa], (d, d).

    000 eq 4-44: sigma_ij = (1/V) sum over particles k and their contact points c
    of x_i^c T_j^c, T the force on k at c, x^c taken from the centre of k (the
    forces on a particle at rest sum to zero, so the origin does not matter).
    A pair's contact point lies on the branch line at (L + R_i - R_j) / 2 from
    x_i (the middle of the overlap, or of the gap of a bond), so when both ends
    are counted their terms combine to l (x) f with the branch vector
    l = x_j - x_i and f the force on i; wall contacts use the arm from the
    centre to the contact point.  The sign is flipped so that compression is
    positive, as in 002.

    ``volume`` [m^3; 2D: m^2 x 1 m] is the region the particles fill (e.g. the
    specimen between its platens); every valid particle is counted.  With
    ``window = (centre (d,), radius)`` [m] only the particles whose centre lies
    in that measurement circle (2D) / sphere (3D) are counted (000 eq 4-45: the
    forces inside cancel and what is left are the contacts on the window's
    boundary) and ``volume`` defaults to the window's.  Counting whole particles
    by their centres makes an error of the order of a particle diameter over
    the window's (000 §4.3); the default volume is therefore the window's times
    :func:`window_solid_correction` (the porosity rule), which removes most of
    it: on a strained triangular lattice a window of 10 radii is 1.4 % off
    without it and 0.03 % with it (tests/test_specimen_tools.py).  Uses the
    stored contact, bond and wall forces (no dashpots): meaningful near
    equilibrium.
    """
    p = state.particles
    if window is None:
        if volume is None:
            raise InputError("averaged_stress needs a volume or a window")
        weight = p.valid
    else:
        weight = in_window(p, window)
        if volume is None:
            volume = window_volume(window, p.pos.shape[1]) * window_solid_correction(p, window)
    w = weight.astype(p.pos.dtype)

    def pair_sum(i, j, branch, f_i):
        dist = jnp.sqrt(dot(branch, branch))
        n = branch / jnp.where(dist > 0, dist, 1.0)[:, None]
        arm_i = 0.5 * (dist + p.radius[i] - p.radius[j])   # from x_i to the contact point
        arm_j = dist - arm_i                                 # from x_j, along -n
        lever = w[i] * arm_i + w[j] * arm_j
        return jnp.sum(_outer(lever[:, None] * n, f_i), axis=0)

    c = state.contacts
    g, fn, _, _ = contact.pair_law(c, p, params, config)
    f_i = jnp.where(g.touching[:, None], -fn[:, None] * g.normal + c.shear, 0.0)
    total = pair_sum(c.i, c.j, g.branch, f_i)
    b = state.bonds
    if b.i.shape[0]:
        bl = p.pos[b.j] - p.pos[b.i]
        bn, _ = unit(bl)
        bf = jnp.where(b.valid[:, None], -b.normal_force[:, None] * bn + b.shear_force, 0.0)
        total = total + pair_sum(b.i, b.j, bl, bf)
    wl = state.walls
    if wl.point.shape[0]:
        ov, touch, fnw, _, _ = wall_law(wl, p, params, config)
        fw = jnp.where(touch[..., None], fnw[..., None] * wl.normal[:, None] + wl.shear, 0.0)
        arm = -(p.radius[None] - 0.5 * ov)[..., None] * wl.normal[:, None]
        total = total + jnp.sum(w[None, :, None, None] * _outer(arm, fw), axis=(0, 1))
    return -total / volume


def averaged_strain(reference_pos, state: State, window=None):
    """Averaged strain of the particles since ``reference_pos``, compression
    positive, (d, d).

    The displacement gradient alpha_ij = d u_j / d x_i of 000 eq 4-46 is taken as
    the least-squares fit u_k = u_0 + alpha^T (x_k - x_0) to the displacements of
    the counted particles (every valid one, or those whose reference centre lies
    in ``window = (centre, radius)``); for a homogeneous deformation it equals the
    boundary integral of eq 4-46 … 4-63, and it needs no boundary crossing
    points.  Returns -(alpha + alpha^T) / 2 (eq 4-64, sign flipped so that
    shortening is positive, as the stress).  Small strains; (reference) positions
    (N, d) [m].
    """
    p = state.particles
    ref = jnp.asarray(reference_pos, p.pos.dtype)
    weight = p.valid if window is None else in_window(p._replace(pos=ref), window)
    w = weight.astype(p.pos.dtype)[:, None]
    n = jnp.maximum(jnp.sum(w), 1.0)
    u = precision.difference(p.pos, p.pos_lo, ref, 0.0)   # compensated (jdem.precision)
    x = ref - jnp.sum(w * ref, axis=0) / n
    u = u - jnp.sum(w * u, axis=0) / n
    xx = jnp.sum(_outer(w * x, x), axis=0)
    xu = jnp.sum(_outer(w * x, u), axis=0)
    alpha = jnp.linalg.solve(xx, xu)                         # alpha_ij = d u_j / d x_i
    return -0.5 * (alpha + alpha.T)


def reaction_forces(state: State, params: Params, config: Config):
    """Reactions (N, d) [N] on the prescribed velocity components (``fixed_vel``):
    the force the support must exert to hold the prescribed motion against the
    contact, bond, wall, applied and gravity forces of the current state,
    R = m a_prescribed - F; prescribed velocities are held constant, so
    R = -F.  Zero on free components and invalid rows.  With every prescribed
    particle in equilibrium, the reactions balance the applied loads."""
    _, force, _ = integrate.forces(state, params, config)
    p = state.particles
    held = p.fixed_vel & p.valid[:, None]
    return jnp.where(held, -force, 0.0)


def reaction_observables(state: State, params: Params, config: Config):
    """:func:`basic_observables` plus ``reaction_force`` (N, d), the reactions of
    :func:`reaction_forces`, and their sum ``reaction_total`` (d,) [N]; pass it as
    ``observe`` to :func:`jdem.simulate.run`.  Recording (N, d) per record costs
    memory: N d x 8 bytes a record in float64."""
    r = reaction_forces(state, params, config)
    return dict(basic_observables(state, params, config), reaction_force=r,
                reaction_total=jnp.sum(r, axis=0))
