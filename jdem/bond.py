"""Linked-bar strain-softening bond (002 §1, eq 1-13, 16).

Citations ("002 eq 5") refer to the documents listed in REFERENCES.md.

A bond joins two particles 1 = ``i`` and 2 = ``j`` by a bar of length
L = R1 + R2 and cross-section A_c (002 eq 1).  Forces and moments are updated
incrementally and explicitly (002 eq 3, 4); the trial normal force is limited by
a tension cut-off with linear softening of the tensile strength (002 eq 6, 7) and
the trial shear force by a Mohr-Coulomb criterion with linear softening of the
cohesion (002 eq 8, 9).  When the tensile strength or the cohesion reaches zero
the bond is broken and behaves as a compression-only frictional contact.  Once
inequality 11 is met the bond stops transmitting moments.

Only evolving quantities live in :class:`jdem.state.Bonds`; the geometry and
stiffnesses (002 eq 1, 2, 5) are recomputed from the radii and ``Params`` by
:func:`bond_geometry` so that they stay differentiable.

Sign conventions (see :mod:`jdem.state`): F_n > 0 is compression; ``shear_force``,
``twist`` and ``bend`` are the shear force and moments acting on particle 1
(``i``); ``u_n`` is the total opening (separation positive) and ``u_s`` the total
tangential displacement of 1 relative to 2.
"""
from __future__ import annotations

import itertools
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jdem.kinematics import (components, computed_once, cross_r_f, dot, floored_norm,
                             project_tangent, relative_velocity, rotate_into_plane, rows,
                             safe_norm, scale, segment_add, unit)
from jdem.state import Bonds, Particles, Params, aligned_rows, empty_bonds

Array = jnp.ndarray


def _den(x):
    """A denominator that is never zero (zeros replaced by 1); pair with a ``where``
    on the result so that masked rows and their gradients stay finite."""
    return jnp.where(x != 0, x, jnp.ones_like(x))


class BondGeometry(NamedTuple):
    """Per-bond geometry and stiffness (002 eq 1, 2, 5); zero for invalid rows.

    area    (B,)  A_c [m^2] (2D: min(2R1, 2R2) x 1 m; 3D: pi min(R1, R2)^2)
    length  (B,)  L = R1 + R2 [m]
    kn      (B,)  K_n = E A_c / L [N/m]
    ks      (B,)  K_s = G A_c / L [N/m], G = E / (2 (1 + nu))
    J       (B,)  polar moment pi min(2R1, 2R2)^4 / 32 [m^4] (002 eq 5)
    I       (B,)  second moment J / 2 [m^4] (002 eq 5); with ``section = "slab"``
                  (2D) the unit-thickness bar's 1 m x min(2R1, 2R2)^3 / 12, J = 2 I
    r_min   (B,)  min(R1, R2) [m] (outer fibre distance of ineq 11)
    """

    area: Array
    length: Array
    kn: Array
    ks: Array
    J: Array
    I: Array
    r_min: Array


class BondMaterial(NamedTuple):
    """Elastic and strength values of every bond row, () when ``Params`` holds one
    value for all bonds, (B,) when it holds one per material (see
    :func:`bond_material`).

    youngs, shear_modulus  E, G [Pa] of the bar
    tensile, cohesion      T0, c0 [Pa]
    tan_phi                tan of the internal friction angle
    tensile_strain, shear_strain   eps_lim, gamma_lim
    damping                fraction of critical of the bond dashpots
    """

    youngs: Array
    shear_modulus: Array
    tensile: Array
    cohesion: Array
    tan_phi: Array
    tensile_strain: Array
    shear_strain: Array
    damping: Array


def bond_material(bonds: Bonds, particles: Particles, params: Params) -> BondMaterial:
    """The bond values of every row.

    With scalar ``bond_*`` fields every bond has them.  With per-material fields
    (shape (M,), indexed by ``Particles.material``) a bond between particles of
    materials a (radius R1) and b (R2) is the bar of 002 Fig 3 made of two
    halves in series, R1 of material a and R2 of material b, so that

        E = (R1 + R2) / (R1 / E_a + R2 / E_b)

    and likewise G from G_a = E_a / (2 (1 + nu_a)); its strengths, friction
    angle, fracture strains and damping are those of the weaker material (the
    smaller of the two values).  For a = b this is the material's own value.
    """
    def shear(e, nu):
        return e / (2.0 * (1.0 + nu))

    per_material = jnp.ndim(params.bond_youngs) > 0
    if not per_material:
        return BondMaterial(
            youngs=params.bond_youngs, shear_modulus=shear(params.bond_youngs,
                                                           params.bond_poisson),
            tensile=params.bond_tensile, cohesion=params.bond_cohesion,
            tan_phi=jnp.tan(params.bond_friction_angle),
            tensile_strain=params.bond_tensile_strain, shear_strain=params.bond_shear_strain,
            damping=params.bond_damping)
    ma, mb = particles.material[bonds.i], particles.material[bonds.j]
    r1, r2 = particles.radius[bonds.i], particles.radius[bonds.j]
    length = _den(r1 + r2)

    def series(modulus):
        return length / (r1 / modulus[ma] + r2 / modulus[mb])

    weaker = lambda v: jnp.minimum(v[ma], v[mb])
    g = shear(params.bond_youngs, params.bond_poisson)
    return BondMaterial(
        youngs=series(params.bond_youngs), shear_modulus=series(g),
        tensile=weaker(params.bond_tensile), cohesion=weaker(params.bond_cohesion),
        tan_phi=jnp.tan(weaker(params.bond_friction_angle)),
        tensile_strain=weaker(params.bond_tensile_strain),
        shear_strain=weaker(params.bond_shear_strain), damping=weaker(params.bond_damping))


def bond_geometry(bonds: Bonds, particles: Particles, params: Params, dim: int,
                  section: str = "circular", material: BondMaterial | None = None
                  ) -> BondGeometry:
    """Cross-section, length, stiffnesses and moments of area of every bond row;
    ``section`` the 2D bending section (:class:`jdem.state.Config` ``bond_section``);
    E and G of each bond from ``material`` (default: :func:`bond_material`)."""
    valid = bonds.valid
    r1 = particles.radius[bonds.i]
    r2 = particles.radius[bonds.j]
    r_min = jnp.minimum(r1, r2)
    if dim == 2:
        area = 2.0 * r_min                       # 002 eq 1 (2D, unit thickness)
    else:
        area = jnp.pi * r_min ** 2               # 002 eq 1 (3D)
    length = r1 + r2
    mat = bond_material(bonds, particles, params) if material is None else material
    kn = mat.youngs * area / _den(length)        # 002 eq 2
    ks = mat.shear_modulus * area / _den(length)
    if dim == 2 and section == "slab":           # a bar of unit thickness, width 2 r_min
        inertia = (2.0 * r_min) ** 3 / 12.0
        polar = 2.0 * inertia
    else:
        polar = jnp.pi * (2.0 * r_min) ** 4 / 32.0   # 002 eq 5
        inertia = 0.5 * polar
    z = lambda a: jnp.where(valid, a, jnp.zeros_like(a))
    return BondGeometry(area=z(area), length=z(length), kn=z(kn), ks=z(ks), J=z(polar),
                        I=z(inertia), r_min=z(r_min))


def create_bonds(particles: Particles, dim: int, *, gap_tolerance: float,
                 capacity: int | None = None) -> Bonds:
    """Bond every pair of valid particles whose gap |x_i - x_j| - R_i - R_j is at
    most ``gap_tolerance`` [m] (overlaps have a negative gap).

    Host-side (NumPy), O(N) with a uniform cell grid of edge 2 max(R) + tolerance.
    Rows are i < j, sorted by (i, j); every evolving field starts at zero and
    ``break_step`` at -1.  ``capacity`` (default: the number found, rounded up
    by :func:`jdem.state.aligned_rows`) pads with invalid rows; a capacity
    below the number found raises ``ValueError``.
    """
    pos = np.asarray(particles.pos, dtype=np.float64)
    rad = np.asarray(particles.radius, dtype=np.float64)
    valid = np.asarray(particles.valid, dtype=bool)
    if pos.ndim != 2 or pos.shape[1] != dim:
        raise ValueError(f"particles.pos must have shape (N, {dim}), got {pos.shape}")
    tol = float(gap_tolerance)
    if not np.isfinite(tol):
        raise ValueError(f"gap_tolerance must be finite, got {gap_tolerance!r}")

    idx = np.nonzero(valid)[0]
    p, r = pos[idx], rad[idx]
    n = idx.size
    pairs_i, pairs_j = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    reach = 2.0 * (r.max() if n else 0.0) + max(tol, 0.0)   # largest bondable centre distance
    if n >= 2 and reach > 0:
        cell = np.floor((p - p.min(axis=0)) / reach).astype(np.int64) + 1  # +1: neighbours >= 0
        shape = cell.max(axis=0) + 2
        strides = np.ones(dim, np.int64)
        for a in range(dim - 2, -1, -1):
            strides[a] = strides[a + 1] * shape[a + 1]
        if float(np.prod(shape.astype(np.float64))) > 2.0 ** 62:
            raise ValueError("create_bonds: particle cloud too sparse for the cell grid "
                             f"({shape.tolist()} cells of {reach} m)")
        key = cell @ strides
        order = np.argsort(key, kind="stable")
        skey = key[order]
        arange = np.arange(n)
        for off in itertools.product((-1, 0, 1), repeat=dim):
            nkey = key + np.asarray(off, np.int64) @ strides
            start = np.searchsorted(skey, nkey, side="left")
            count = np.searchsorted(skey, nkey, side="right") - start
            tot = int(count.sum())
            if tot == 0:
                continue
            a = np.repeat(arange, count)
            within = np.arange(tot) - np.repeat(np.cumsum(count) - count, count)
            b = order[np.repeat(start, count) + within]
            keep = a < b
            a, b = a[keep], b[keep]
            gap = np.linalg.norm(p[b] - p[a], axis=1) - r[a] - r[b]
            keep = gap <= tol
            pairs_i.append(a[keep])
            pairs_j.append(b[keep])
    bi = idx[np.concatenate(pairs_i)] if n else np.zeros(0, np.int64)
    bj = idx[np.concatenate(pairs_j)] if n else np.zeros(0, np.int64)
    return bonds_for_pairs(bi, bj, dim, capacity=capacity, dtype=particles.pos.dtype)


def bonds_for_pairs(i, j, dim: int, *, capacity: int | None = None, dtype=None) -> Bonds:
    """Fresh bonds for the pairs ``(i[k], j[k])`` (host integer arrays, i < j): rows
    sorted by (i, j), every evolving field at zero, ``break_step`` at -1.
    ``capacity`` (default: the number of pairs rounded up by
    :func:`jdem.state.aligned_rows`) pads with invalid rows; a capacity below
    it raises ``ValueError``."""
    bi, bj = np.asarray(i, np.int64), np.asarray(j, np.int64)
    if bi.shape != bj.shape or bi.ndim != 1 or np.any(bi >= bj):
        raise ValueError("bonds_for_pairs: i and j must be 1-D of one length with i < j")
    srt = np.lexsort((bj, bi))
    bi, bj = bi[srt], bj[srt]
    found = bi.size
    capacity = aligned_rows(found) if capacity is None else int(capacity)
    if capacity < found:
        raise ValueError(f"create_bonds: capacity {capacity} is smaller than the number of "
                         f"bonds found {found}")
    bonds = empty_bonds(dim, capacity, dtype=dtype)
    ii = np.zeros(capacity, np.int32)
    jj = np.zeros(capacity, np.int32)
    ok = np.zeros(capacity, bool)
    ii[:found], jj[:found], ok[:found] = bi, bj, True
    return bonds._replace(i=jnp.asarray(ii), j=jnp.asarray(jj), valid=jnp.asarray(ok))


def bond_forces(bonds: Bonds, particles: Particles, params: Params, dim: int, step,
                section: str = "circular", always_true=None):
    """One explicit incremental update of every bond (002 eq 3-13).

    Arguments: ``bonds`` (capacity B), ``particles`` (capacity N; ``vel`` and
    ``angvel`` are the velocities over the step), ``params`` (``dt`` and the
    ``bond_*`` fields), ``dim`` (2 or 3, static) and ``step`` (int, the current
    step number, stored in ``break_step`` when a bond breaks); ``section`` the 2D
    bending section (``Config.bond_section``, see :func:`bond_geometry`);
    ``always_true`` the traced true scalar of :func:`jdem.kinematics.computed_once`
    (default ``step >= 0``); under ``vmap`` pass one that is not batched, as
    :func:`jdem.integrate.step_batched` does, or the conditional that keeps the
    law in memory becomes a select.

    Returns ``(new_bonds, force (N, d) [N], torque (N,) or (N, 3) [N m])``.
    Invalid rows contribute nothing and keep zero history.

    A bond whose tensile strength or cohesion reaches zero in this step is flagged
    broken now, but its forces for this step are the softened (~0) bonded values;
    from the next step it is a frictional contact: F_n = K_n max(0, -u_n)
    (compression only, re-engaging at the bonded separation), |F_s| <= F_n tan(phi),
    no tension, cohesion or moments.

    Inequality 11 is checked with this step's corrected forces and trial moments
    (old moments rotated into the plane ⊥ n plus the eq 4 increment); when it is
    met, ``moment_lost`` is set for good and the moments are zero from this very
    step on, so a moment beyond the criterion is never transmitted.
    """
    # The law row by row, into memory (jdem.kinematics.computed_once, at every
    # size): otherwise, under jax.jvp, XLA:CPU fuses the tangent of the whole law
    # into the concatenation that stacks the shear components and evaluates it
    # element by element, so that a Jacobian by forward mode cost 8.1 forward runs
    # per tangent instead of 2.6 (experiments/jvp_profile.py, jacobian_cost.py).  The
    # forward step is unchanged (3D bonded benchmark: 227 -> 239 steps/s, one pair).
    new, f1, t1, t2 = computed_once(
        lambda: _bond_law(bonds, particles, params, dim, step, section),
        jnp.asarray(step) >= 0 if always_true is None else always_true, min_rows=0)
    valid, i, j = bonds.valid, bonds.i, bonds.j
    # one scatter per side and quantity (padding rows left out)
    n_part = particles.pos.shape[0]
    add = lambda rows, index: segment_add(rows, index, n_part, where=valid)
    force = add(f1, i) + add(tuple(-f for f in f1), j)
    torque = add(t1, i) + add(t2, j)
    stack = lambda v: jnp.stack(v, axis=-1) if isinstance(v, tuple) else v
    new_bonds = new._replace(i=i, j=j, valid=valid, shear_force=stack(new.shear_force),
                             bend=stack(new.bend), u_s=stack(new.u_s))
    return new_bonds, force, torque


def _bond_law(bonds: Bonds, particles: Particles, params: Params, dim: int, step,
              section: str):
    """002 eq 3-13 on every row (see :func:`bond_forces`): ``(new bonds, f1, t1,
    t2)``, the new bonds without ``i``, ``j``, ``valid`` (None: not passed through
    the conditional) and with the vector fields as component tuples; ``f1`` the
    force on particle 1, ``t1``, ``t2`` the torques on particles 1 and 2, zero on
    invalid rows."""
    valid = bonds.valid
    i, j = bonds.i, bonds.j
    mat = bond_material(bonds, particles, params)
    geo = bond_geometry(bonds, particles, params, dim, section, mat)
    area, length, kn, ks = geo.area, geo.length, geo.kn, geo.ks
    area_d, length_d = _den(area), _den(length)
    dt = params.dt
    e_mod, g_mod = mat.youngs, mat.shear_modulus
    t0, c0 = mat.tensile, mat.cohesion
    tanphi = mat.tan_phi
    eps_lim, gam_lim = mat.tensile_strain, mat.shear_strain
    z = lambda a: jnp.where(valid, a, jnp.zeros_like(a))

    # Vectors are component tuples of (B,) arrays (see jdem.kinematics); in 2D the
    # rotations, moments and torques are scalars (B,).
    zv = lambda v: tuple(z(c) for c in v) if isinstance(v, tuple) else z(v)

    # Geometry: n from 1 to 2; r1, r2 from the centroids to the contact point on the
    # bar, which divides the centre line in the ratio R1 : R2 (002 Fig. 3).
    dx = tuple(x[j] - x[i] for x in components(particles.pos))
    n, _ = unit(dx)
    r1 = scale(particles.radius[i] / length_d, dx)
    r2 = scale(-(particles.radius[j] / length_d), dx)

    # 002 eq 12: displacement increment of 1 relative to 2 at the contact point.
    v_rel = relative_velocity(particles.vel, particles.angvel, i, j, r1, r2)
    du = tuple(c * dt for c in v_rel)
    du_n = dot(du, n)
    d_open = -du_n                                   # Δu_n, opening positive
    d_us = project_tangent(du, n)                    # Δu_s, tangential

    # Turn the stored tangential history into the current plane ⊥ n, then add up
    # the totals u_n, u_s.
    fs_old = rotate_into_plane(components(bonds.shear_force), n)
    u_s = tuple(a + b for a, b in zip(rotate_into_plane(components(bonds.u_s), n), d_us))
    u_n = bonds.u_n + d_open
    us_mag = safe_norm(u_s)

    # ---- intact bond -------------------------------------------------------
    # 002 eq 3: incremental trial forces (F_n compression positive; F_s on 1).
    fn_tr = bonds.normal_force - kn * d_open
    fs_tr = tuple(f - ks * d for f, d in zip(fs_old, d_us))
    # 002 eq 10: current strengths from the stored damage.
    t_old = t0 * (1.0 - bonds.alpha)
    c_old = c0 * (1.0 - bonds.beta)
    # 002 eq 6-7: tension cut-off with linear softening of T.
    tens = -fn_tr >= t_old * area
    fn_b = jnp.where(tens, -t_old * area, fn_tr)
    eps_p = u_n / length_d - t_old / e_mod
    alpha_c = jnp.where(eps_lim > 0, eps_p / _den(eps_lim), 1.0)   # eps_lim = 0: brittle
    alpha_b = jnp.where(tens, jnp.clip(jnp.maximum(bonds.alpha, alpha_c), 0.0, 1.0), bonds.alpha)
    # 002 eq 8-9: Mohr-Coulomb with the corrected F_n, linear softening of c.
    strength = jnp.maximum(fn_b * tanphi + c_old * area, 0.0)
    fs_mag = floored_norm(fs_tr)
    shear = fs_mag >= strength
    ratio = strength / fs_mag
    fs_b = tuple(jnp.where(shear, f * ratio, f) for f in fs_tr)
    gam_p = us_mag / length_d - (c_old + fn_b * tanphi / area_d) / g_mod
    beta_c = jnp.where(gam_lim > 0, gam_p / _den(gam_lim), 1.0)    # gamma_lim = 0: brittle
    beta_b = jnp.where(shear, jnp.clip(jnp.maximum(bonds.beta, beta_c), 0.0, 1.0), bonds.beta)

    # ---- broken bond: compression-only frictional contact -------------------
    fn_f = kn * jnp.maximum(0.0, -u_n)
    f_lim = fn_f * tanphi
    slip = fs_mag > f_lim                 # the same trial force as the intact bond's
    fs_f = tuple(jnp.where(slip, f * (f_lim / fs_mag), f) for f in fs_tr)

    was_broken = bonds.broken
    fn = z(jnp.where(was_broken, fn_f, fn_b))
    fs = tuple(z(jnp.where(was_broken, f, b)) for f, b in zip(fs_f, fs_b))
    alpha = z(jnp.where(was_broken, bonds.alpha, alpha_b))
    beta = z(jnp.where(was_broken, bonds.beta, beta_b))

    # A bond breaks when T or c reaches zero; recorded once, effective next step.
    new_break = valid & ~was_broken & ((alpha >= 1.0) | (beta >= 1.0))
    broken = valid & (was_broken | new_break)
    break_mode = jnp.where(new_break, jnp.where(alpha >= 1.0, 1, 2).astype(jnp.int32),
                           bonds.break_mode)
    break_step = jnp.where(new_break, jnp.asarray(step, jnp.int32), bonds.break_step)

    # ---- moments -------------------------------------------------------------
    # 002 eq 4: relative rotation increment split into twist (along n) and bending.
    w1, w2 = rows(particles.angvel, i), rows(particles.angvel, j)
    if dim == 3:
        dth = tuple((a - b) * dt for a, b in zip(w1, w2))
        dth_n = dot(dth, n)
        dth_s = project_tangent(dth, n)
        bend_old = rotate_into_plane(components(bonds.bend), n)
        bend_tr = tuple(b - (kn * geo.I / area_d) * d for b, d in zip(bend_old, dth_s))
        bend_mag = safe_norm(bend_tr)
    else:
        dth_n, dth_s = 0.0, (w1 - w2) * dt
        bend_tr = bonds.bend - kn * geo.I * dth_s / area_d
        bend_mag = jnp.abs(bend_tr)
    twist_tr = bonds.twist - ks * geo.J * dth_n / area_d
    # 002 ineq 11 (with this step's corrected forces and trial moments): the bond
    # stops transmitting moments for good.  A bond that yields at its full
    # strength meets a branch with equality (the corrected F_n is -T0 A_c, the
    # corrected |F_s| is F_n tan(phi) + c0 A_c), so those cases are decided by the
    # yield flags, not by the round-off of the corrected forces.
    sig_n = fn_b / area_d
    ineq11 = ((-sig_n + bend_mag / _den(geo.I) * geo.r_min >= t0)
              | (safe_norm(fs_b) / area_d + jnp.abs(twist_tr) / _den(geo.J) * geo.r_min
                 >= sig_n * tanphi + c0)
              | (tens & (t_old >= t0)) | (shear & (c_old >= c0)))
    moment_lost = valid & (bonds.moment_lost | (~was_broken & ineq11))
    carry_m = valid & ~was_broken & ~moment_lost
    twist = jnp.where(carry_m, twist_tr, 0.0)
    bend = tuple(jnp.where(carry_m, b, 0.0) for b in bend_tr) if dim == 3 \
        else jnp.where(carry_m, bend_tr, 0.0)

    # ---- bond dashpots (Params.bond_damping) ----------------------------------
    # Viscous forces on the relative motion of intact bonds, 2 zeta sqrt(m* K)
    # times the rate (000 eq 3-1); applied to the particles but not stored, so the
    # elastic-plastic history above is untouched.
    live = valid & ~was_broken
    m1_, m2_ = particles.mass[i], particles.mass[j]
    m_eff = jnp.where(live, m1_ * m2_ / _den(m1_ + m2_), 0.0)
    visc = lambda k: 2.0 * mat.damping * jnp.sqrt(jnp.where(live, m_eff * k, 1.0)) / dt
    fn_d = jnp.where(live, visc(kn) * du_n, 0.0)            # compression positive
    visc_s = visc(ks)
    fs_d = tuple(jnp.where(live, -visc_s * d, 0.0) for d in d_us)

    # ---- back onto the particles (002 eq 13) ----------------------------------
    f1 = zv(tuple(-(fn + fn_d) * nc + f + d for nc, f, d in zip(n, fs, fs_d)))  # on particle 1
    if dim == 3:
        m1 = tuple(twist * nc + b for nc, b in zip(n, bend))
        t1 = tuple(a + m for a, m in zip(cross_r_f(r1, f1), m1))
        t2 = tuple(a - m for a, m in zip(cross_r_f(r2, tuple(-f for f in f1)), m1))
    else:
        t1 = cross_r_f(r1, f1) + bend
        t2 = cross_r_f(r2, tuple(-f for f in f1)) - bend
    new = bonds._replace(
        i=None, j=None, valid=None, normal_force=fn, shear_force=fs, twist=twist, bend=bend,
        u_n=z(u_n), u_s=zv(u_s), alpha=alpha, beta=beta, moment_lost=moment_lost,
        broken=broken, break_mode=break_mode, break_step=break_step)
    return new, f1, zv(t1), zv(t2)


def damage(bonds: Bonds) -> dict:
    """Damage factors of 002 eq 10: ``alpha`` = 1 - T/T0, ``beta`` = 1 - c/c0 and
    ``chi`` = 1 - (1 - alpha)(1 - beta); zero for invalid rows."""
    alpha = jnp.where(bonds.valid, bonds.alpha, 0.0)
    beta = jnp.where(bonds.valid, bonds.beta, 0.0)
    return {"alpha": alpha, "beta": beta, "chi": 1.0 - (1.0 - alpha) * (1.0 - beta)}


def bond_strain_energy(bonds: Bonds, particles: Particles, params: Params, dim: int):
    """Bond strain energy L_p [J] (2D: per metre of thickness), 002 eq 16:

        L_p = sum over intact valid bonds of (F_n (-u_n) - F_s . u_s) / 2

    with the signs of this module (F_n compression positive, u_n opening positive;
    F_s acts on particle 1 and u_s is the displacement of 1 relative to 2), so that
    both terms are >= 0 for an elastic bond, where the sum equals
    F_n^2 / (2 K_n) + |F_s|^2 / (2 K_s).  Twisting and bending energies are
    omitted, as in the seed.  Broken bonds are not counted.
    (``particles``, ``params`` and ``dim`` are accepted for a uniform signature.)
    """
    del particles, params, dim
    live = bonds.valid & ~bonds.broken
    e = 0.5 * (-bonds.normal_force * bonds.u_n - dot(bonds.shear_force, bonds.u_s))
    return jnp.sum(jnp.where(live, e, 0.0))


def bond_stats(bonds: Bonds, counted=None) -> dict:
    """Counts: ``n_bonds`` (valid rows), ``n_broken``, ``n_tension`` / ``n_shear``
    (broken in mode 1 / 2) and ``fracture_degree`` = n_broken / n_bonds (0 if none).
    ``counted`` (B,) bool: count only these rows (the rock's bonds of a specimen
    with loading plates, :func:`rock_bonds`); default all."""
    valid = bonds.valid if counted is None else bonds.valid & counted
    broken = valid & bonds.broken
    n_bonds = jnp.sum(valid)
    n_broken = jnp.sum(broken)
    return {
        "n_bonds": n_bonds,
        "n_broken": n_broken,
        "n_tension": jnp.sum(broken & (bonds.break_mode == 1)),
        "n_shear": jnp.sum(broken & (bonds.break_mode == 2)),
        "fracture_degree": jnp.where(n_bonds > 0, n_broken / jnp.maximum(n_bonds, 1), 0.0),
    }


def rock_bonds(bonds: Bonds, particles, plate_material) -> jnp.ndarray:
    """(B,) bool: bonds with neither end a particle of ``plate_material`` (the
    discs of loading plates, :func:`jdem.specimen.add_plates`).  The fracture
    degree is a figure of the rock (002 §2.3): a plate's bonds to the rock are
    neither in its count nor in its total."""
    mat = particles.material
    return (mat[bonds.i] != plate_material) & (mat[bonds.j] != plate_material)
