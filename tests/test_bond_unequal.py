"""Linked-bar bond between particles of unequal radii R1 != R2 (002 §1, eq 1-13).

Every expected number is worked out here from the seed's formulas, with the
smaller particle setting the section:

* eq 1: A_c = min(2R1, 2R2) (2D, unit thickness), pi min(R1, R2)^2 (3D);
* eq 2: K_n = E A_c / (R1 + R2), K_s = G A_c / (R1 + R2);
* eq 5: J = pi min(2R1, 2R2)^4 / 32, I = J / 2;
* eq 4: bending slope K_n I / A_c, twisting slope K_s J / A_c per radian;
* eq 8: shear strength F_n tan(phi) + c A_c, i.e. c - sigma_t tan(phi) under a
  tensile stress sigma_t (F_n < 0 is tension);
* ineq 11: moments are lost once |F_s| / A_c + |M_n| min(R1, R2) / J >=
  F_n / A_c tan(phi) + c0 (the shear/twist branch);
* eq 12, 13: the contact point divides the centre line in the ratio R1 : R2
  (002 Fig. 3), so the arms are r1 = R1 / (R1 + R2) (x2 - x1) and
  r2 = -R2 / (R1 + R2) (x2 - x1) whatever the gap.

Particle 0 (i, radius R_i) is fixed at the origin, particle 1 (j, radius R_j)
sits above it on the last axis; both orders of the radii are run.  Seed
material: E = 10 GPa, nu = 0.22, T0 = c0 = 3 MPa, phi = 30 deg,
eps_lim = 0.1 %, gamma_lim = 0.3 %.
"""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jdem.bond import bond_forces, bond_geometry, create_bonds
from jdem.state import make_params, make_particles
from seed_bond import C0, E, EPS_LIM, G, GAM_LIM, NU, PHI, T0, TANPHI

DT = 1e-3
DSTRAIN = 5e-7                    # shear strain per step
SIG_T = 1e6                       # tensile pre-stress of the shear tests [Pa]
N_PRE = 100                       # steps of the tensile pre-load
RADII = [(0.5, 0.3), (0.3, 0.5)]  # (R_i, R_j): the smaller one below, then above


def section(dim, r1, r2):
    """(A_c, L, K_n, K_s, J, I, r_min) by hand from 002 eq 1, 2, 5."""
    r = min(r1, r2)
    a = 2 * r if dim == 2 else np.pi * r ** 2
    length = r1 + r2
    j = np.pi * (2 * r) ** 4 / 32
    return a, length, E * a / length, G * a / length, j, j / 2, r


def setup(dim, r1, r2, gap=0.0):
    pos = np.zeros((2, dim))
    pos[1, -1] = r1 + r2 + gap
    parts = make_particles(pos, [r1, r2], density=2500.0)
    bonds = create_bonds(parts, dim, gap_tolerance=gap + 1e-9, capacity=1)
    assert bool(bonds.valid[0]) and bonds.i.shape == (1,)
    params = make_params(dim=dim, dt=DT, bond_youngs=E, bond_poisson=NU, bond_tensile=T0,
                         bond_cohesion=C0, bond_friction_angle=PHI,
                         bond_tensile_strain=EPS_LIM, bond_shear_strain=GAM_LIM)
    return bonds, parts, params


def rot(dim, n=2):
    return jnp.zeros((n,) if dim == 2 else (n, 3))


def tangent(dim, nvec):
    """Unit vector ⊥ n in the plane of the first and the last axis."""
    if dim == 2:
        return jnp.array([nvec[1], -nvec[0]])
    return jnp.array([nvec[2], 0.0, -nvec[0]])


@functools.partial(jax.jit, static_argnums=(3, 5))
def drive(bonds, parts, params, dim, load, nsteps):
    """Kinematic loop.  ``load = (n_pre, v_open, v_slide, w)`` (see :func:`prog`): for k < n_pre the
    upper particle moves along the bond axis at v_open (opening positive), then
    at v_slide along the current tangent (a circle about the lower particle, so
    the centre distance stays fixed); ``w`` (2,) or (2, 3) are the angular
    velocities throughout.  Returns the final (bonds, particles) and the per-step
    (bonds, force, torque, pos), pos being the positions at which that step's
    forces were computed."""
    n_pre, v_open, v_slide, w = load

    def body(carry, k):
        b, p = carry
        nvec = (p.pos[1] - p.pos[0]) / jnp.linalg.norm(p.pos[1] - p.pos[0])
        v1 = jnp.where(k < n_pre, v_open * nvec, v_slide * tangent(dim, nvec))
        vel = jnp.zeros((2, dim)).at[1].set(v1)
        p = p._replace(vel=vel, angvel=w)
        b, f, t = bond_forces(b, p, params, dim, k)
        out = (b, f, t, p.pos)
        return (b, p._replace(pos=p.pos + vel * params.dt)), out

    return jax.lax.scan(body, (bonds, parts), jnp.arange(nsteps))


def prog(n_pre, v_open, v_slide, w):
    """A loading programme for :func:`drive`, as arrays (one compilation per
    dim and step count)."""
    f = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731
    return jnp.asarray(n_pre, jnp.int32), f(v_open), f(v_slide), f(w)


def tensioned_shear_prog(dim, length):
    """Open to sigma_t = SIG_T in N_PRE steps, then shear at DSTRAIN per step."""
    v_open = SIG_T * length / E / (N_PRE * DT)
    return prog(N_PRE, v_open, DSTRAIN * length / DT, rot(dim))


@functools.lru_cache(maxsize=None)
def tensioned_shear(dim, r1, r2):
    """History of the tension pre-load + direct shear run, as NumPy arrays."""
    bonds, parts, params = setup(dim, r1, r2)
    length = r1 + r2
    _, (hb, f, t, pos) = drive(bonds, parts, params, dim, tensioned_shear_prog(dim, length),
                               6200)
    return jax.tree_util.tree_map(np.asarray, (hb, f, t, pos))


# --------------------------------------------------------------------------- section

@pytest.mark.parametrize("r1, r2", RADII)
@pytest.mark.parametrize("dim", [2, 3])
def test_section_from_the_smaller_particle(dim, r1, r2):
    """002 eq 1, 2, 5 for R1 != R2: A_c, K_n, K_s, J, I and the fibre distance."""
    bonds, parts, params = setup(dim, r1, r2)
    g = bond_geometry(bonds, parts, params, dim)
    if dim == 2:                  # 2 * 0.3 m x 1 m, E A / L = 10e9 * 0.6 / 0.8
        a_hand, kn_hand = 0.6, 7.5e9
    else:                         # pi 0.3^2, 10e9 * 0.09 pi / 0.8
        a_hand, kn_hand = 0.09 * np.pi, 1.125e9 * np.pi
    j_hand = np.pi * 0.6 ** 4 / 32
    np.testing.assert_allclose(g.area, [a_hand], rtol=1e-14)
    np.testing.assert_allclose(g.length, [0.8], rtol=1e-14)
    np.testing.assert_allclose(g.kn, [kn_hand], rtol=1e-14)
    np.testing.assert_allclose(g.ks, [kn_hand / (2 * (1 + NU))], rtol=1e-14)
    np.testing.assert_allclose(g.J, [j_hand], rtol=1e-14)
    np.testing.assert_allclose(g.I, [j_hand / 2], rtol=1e-14)
    np.testing.assert_allclose(g.r_min, [0.3], rtol=1e-14)


@pytest.mark.parametrize("r1, r2", RADII)
@pytest.mark.parametrize("dim", [2, 3])
def test_normal_and_shear_stiffness_from_the_response(dim, r1, r2):
    """The elastic pre-load gives F_n = -K_n u_n and the elastic shear
    |F_s| = K_s |u_s|, K = (E or G) A_c / (R1 + R2) with A_c from min(R)."""
    hb, f, _, _ = tensioned_shear(dim, r1, r2)
    a, length, kn, ks, *_ = section(dim, r1, r2)
    fn, u_n = hb.normal_force[:, 0], hb.u_n[:, 0]
    pre = slice(0, N_PRE)
    np.testing.assert_allclose(u_n[pre], SIG_T * length / E * np.arange(1, N_PRE + 1) / N_PRE,
                               rtol=1e-9)
    np.testing.assert_allclose(fn[pre], -kn * u_n[pre], rtol=1e-9)
    np.testing.assert_allclose(-fn[N_PRE - 1] / a, SIG_T, rtol=1e-9)
    # the force on the upper particle pulls it back down with K_n u_n
    np.testing.assert_allclose(f[pre, 1, -1], -kn * u_n[pre], rtol=1e-9)
    fs = np.linalg.norm(hb.shear_force[:, 0], axis=-1)
    us = np.linalg.norm(hb.u_s[:, 0], axis=-1)
    el = np.arange(N_PRE, N_PRE + 1000)
    assert np.all(hb.beta[el, 0] == 0)
    np.testing.assert_allclose(us[el], DSTRAIN * length * np.arange(1, 1001), rtol=1e-9)
    np.testing.assert_allclose(fs[el], ks * us[el], rtol=1e-9)
    # sliding along the circle keeps the opening, hence F_n, fixed until the break
    kb = int(np.argmax(hb.broken[:, 0]))
    assert kb > N_PRE + 1000
    np.testing.assert_allclose(fn[N_PRE:kb + 1], fn[N_PRE - 1], rtol=1e-9)


@pytest.mark.parametrize("r1, r2", RADII)
@pytest.mark.parametrize("dim", [2, 3])
def test_bending_and_twisting_slopes(dim, r1, r2):
    """002 eq 4 with eq 5: M_s = K_n I / A_c theta and (3D) M_n = K_s J / A_c theta."""
    bonds, parts, params = setup(dim, r1, r2)
    a, _, kn, ks, j_pol, i_m, _ = section(dim, r1, r2)
    dth = 1e-7
    w = dth / DT
    # particle 1 turns about the first axis (bending) and, in 3D, particle 0 about
    # the bond axis (twist)
    angvel = jnp.zeros(2).at[1].set(w) if dim == 2 else \
        jnp.zeros((2, 3)).at[1, 0].set(w).at[0, 2].set(w)
    _, (hb, _, _, _) = drive(bonds, parts, params, dim, prog(0, 0.0, 0.0, angvel), 50)
    theta = dth * np.arange(1, 51)
    bend = np.asarray(hb.bend)[:, 0]
    bend_x = bend if dim == 2 else bend[:, 0]
    # acting on particle 0 against its relative rotation w0 - w1 = -w
    np.testing.assert_allclose(bend_x, kn * i_m / a * theta, rtol=1e-9)
    assert not np.asarray(hb.moment_lost).any()
    if dim == 3:
        np.testing.assert_allclose(np.asarray(hb.twist)[:, 0], -ks * j_pol / a * theta,
                                   rtol=1e-9)
        # K_s J / A_c = G J / L: the area cancels, J alone sets the twisting slope
        np.testing.assert_allclose(ks * j_pol / a, G * np.pi * 0.6 ** 4 / 32 / 0.8, rtol=1e-14)


# --------------------------------------------------------------------------- contact point, arms

@pytest.mark.parametrize("r1, r2", RADII)
@pytest.mark.parametrize("dim", [2, 3])
def test_contact_point_divides_the_centre_line_r1_to_r2(dim, r1, r2):
    """One step of (a) a tangential translation of particle 1, (b) a spin of
    particle 0 alone, (c) a spin of particle 1 alone, on a bond with a gap
    (centre distance d = 0.82 m != R1 + R2): the arms of eq 12 and 13 are
    R1 d / L and R2 d / L (0.5125 m and 0.3075 m), in the ratio R1 : R2."""
    gap = 0.02
    bonds, parts, params = setup(dim, r1, r2, gap=gap)
    a, length, kn, ks, _, i_m, _ = section(dim, r1, r2)
    d = length + gap
    arm1, arm2 = r1 * d / length, r2 * d / length

    def one_step(vel, angvel):
        p = parts._replace(vel=jnp.asarray(vel), angvel=jnp.asarray(angvel))
        b, f, t = bond_forces(bonds, p, params, dim, 0)
        bend = np.asarray(b.bend[0]) if dim == 2 else np.asarray(b.bend[0])[1]
        return np.asarray(b.shear_force[0]), np.asarray(f), np.asarray(t), bend

    # moments about the out-of-plane axis (2D) or about -y (3D: slide along x,
    # bond along z), so that both dimensions read the same
    tz = (lambda t: t) if dim == 2 else (lambda t: -t[..., 1])  # noqa: E731

    # (a) particle 1 slides by v dt along x: F_s on particle 0 is K_s v dt along +x
    v = 1e-4
    vel = np.zeros((2, dim))
    vel[1, 0] = v
    fs, f, t, bend = one_step(vel, rot(dim))
    fs_hand = ks * v * DT
    np.testing.assert_allclose(fs[0], fs_hand, rtol=1e-12)
    np.testing.assert_allclose(f[0, 0], fs_hand, rtol=1e-12)
    np.testing.assert_allclose(f[1], -f[0], rtol=1e-14)
    assert bend == 0
    # torque = arm x F with r1 = +arm1 and r2 = -arm2 along the bond
    np.testing.assert_allclose(tz(t[0]), -arm1 * fs_hand, rtol=1e-12)
    np.testing.assert_allclose(tz(t[1]), -arm2 * fs_hand, rtol=1e-12)
    np.testing.assert_allclose(tz(t[0]) / tz(t[1]), r1 / r2, rtol=1e-12)

    # (b), (c): a spin w of one particle alone moves its end of the bar by
    # w x arm dt (eq 12): 2D spin about +z, 3D spin about +y
    w = 1e-4
    spin = lambda k: np.eye(2)[k] * w if dim == 2 else np.outer(np.eye(2)[k], [0.0, w, 0.0])  # noqa: E731
    sgn = 1.0 if dim == 2 else -1.0
    fs0, _, _, bend0 = one_step(np.zeros((2, dim)), spin(0))
    fs1, _, _, bend1 = one_step(np.zeros((2, dim)), spin(1))
    np.testing.assert_allclose(fs0[0], sgn * ks * w * arm1 * DT, rtol=1e-12)
    # particle 1's end lies below its centre, and eq 12 subtracts its motion:
    # the same sign
    np.testing.assert_allclose(fs1[0], sgn * ks * w * arm2 * DT, rtol=1e-12)
    np.testing.assert_allclose(fs0[0] / fs1[0], r1 / r2, rtol=1e-12)
    # the bending moment of the relative rotation, K_n I / A_c w dt (eq 4, 5)
    m = kn * i_m / a * w * DT
    np.testing.assert_allclose(bend0, -m, rtol=1e-12)
    np.testing.assert_allclose(bend1, m, rtol=1e-12)


@pytest.mark.parametrize("r1, r2", RADII)
@pytest.mark.parametrize("dim", [2, 3])
def test_isolated_pair_is_in_moment_balance(dim, r1, r2):
    """Opening, sliding and spinning both particles of a bond with a gap: at every
    step the forces sum to zero and so does the moment about any point,
    sum_k (x_k - p) x F_k + T_k, because both forces act at the one contact point
    and the bond moments are equal and opposite (eq 13)."""
    gap = 0.02
    bonds, parts, params = setup(dim, r1, r2, gap=gap)
    length = r1 + r2
    if dim == 2:
        w = jnp.array([3e-7, -2e-7]) / DT
    else:
        w = jnp.array([[3e-7, -1e-7, 2e-7], [-2e-7, 4e-7, -3e-7]]) / DT
    load = prog(150, 2e-7 * length / DT, 4e-7 * length / DT, w)
    _, (hb, f, t, pos) = drive(bonds, parts, params, dim, load, 600)
    f, t, pos = np.asarray(f), np.asarray(t), np.asarray(pos)
    assert not np.asarray(hb.moment_lost).any() and not np.asarray(hb.broken).any()
    scale_f = np.max(np.abs(f))
    assert scale_f > 0 and np.max(np.abs(np.asarray(hb.bend))) > 0
    if dim == 3:
        assert np.max(np.abs(np.asarray(hb.twist))) > 0
    np.testing.assert_allclose(f.sum(axis=1), 0.0, atol=1e-12 * scale_f)

    def cross(r, v):
        if dim == 2:
            return r[..., 0] * v[..., 1] - r[..., 1] * v[..., 0]
        return np.cross(r, v)

    scale_m = scale_f * length + np.max(np.abs(t))
    for p in (np.zeros(dim), np.full(dim, 3.7), -np.arange(1.0, dim + 1)):
        moment = sum(cross(pos[:, k] - p, f[:, k]) + t[:, k] for k in range(2))
        np.testing.assert_allclose(moment, 0.0, atol=1e-12 * scale_m)
    # and each torque is its own arm times the force plus / minus the bond moment
    dx = pos[:, 1] - pos[:, 0]
    m_vec = np.asarray(hb.bend)[:, 0]
    if dim == 3:
        nvec = dx / np.linalg.norm(dx, axis=-1, keepdims=True)
        m_vec = m_vec + np.asarray(hb.twist)[:, 0, None] * nvec
    np.testing.assert_allclose(t[:, 0], cross(r1 / length * dx, f[:, 0]) + m_vec,
                               atol=1e-12 * scale_m)
    np.testing.assert_allclose(t[:, 1], cross(-r2 / length * dx, f[:, 1]) - m_vec,
                               atol=1e-12 * scale_m)


# --------------------------------------------------------------------------- strength

@pytest.mark.parametrize("r1, r2", RADII)
@pytest.mark.parametrize("dim", [2, 3])
def test_tension_softens_and_breaks_at_the_limit_strain(dim, r1, r2):
    """Uniaxial opening at DSTRAIN per step of a bar of length R1 + R2 = 0.8 m
    (strains are u_n / L): the stress peaks at T0 at the strain T0 / E, falls on
    the line T0 (1 - (eps - T0 / E) / (eps_lim - T0 / E)) (002 eq 6, 7 with
    eq 10) and the bond breaks in tension (mode 1) at eps = eps_lim."""
    bonds, parts, params = setup(dim, r1, r2)
    a, length, *_ = section(dim, r1, r2)
    n = int(1.1e-3 / DSTRAIN)
    _, (hb, _, _, _) = drive(bonds, parts, params, dim,
                             prog(n, DSTRAIN * length / DT, 0.0, rot(dim)), n)
    stress = -np.asarray(hb.normal_force)[:, 0] / a
    eps = DSTRAIN * np.arange(1, n + 1)
    np.testing.assert_allclose(np.asarray(hb.u_n)[:, 0] / length, eps, rtol=1e-9)
    kp = int(np.argmax(stress))
    np.testing.assert_allclose(stress[kp], T0, rtol=1e-9)
    assert abs(eps[kp] / (T0 / E) - 1) < 2e-3
    broken = np.asarray(hb.broken)[:, 0]
    kb = int(np.argmax(broken))
    assert broken[kb] and not broken[kb - 1] and int(hb.break_mode[-1, 0]) == 1
    assert abs(eps[kb] / EPS_LIM - 1) < 2e-3
    soft = np.arange(kp + 1, kb)
    line = T0 * (1 - (eps[soft] - T0 / E) / (EPS_LIM - T0 / E))
    assert np.max(np.abs(stress[soft] - line)) < 2e-3 * T0


@pytest.mark.parametrize("r1, r2", RADII)
@pytest.mark.parametrize("dim", [2, 3])
def test_shear_strength_under_tension_and_shear_break(dim, r1, r2):
    """Direct shear under sigma_t = 1 MPa of tension: the peak shear stress is the
    Mohr-Coulomb value c0 - sigma_t tan(phi) = 2.4226 MPa (eq 8, F_n < 0), the
    bond then softens (eq 9) and breaks in shear (mode 2), never in tension."""
    hb, f, _, _ = tensioned_shear(dim, r1, r2)
    a, length, *_ = section(dim, r1, r2)
    tau = np.linalg.norm(hb.shear_force[:, 0], axis=-1)[N_PRE:] / a
    gam = np.linalg.norm(hb.u_s[:, 0], axis=-1)[N_PRE:] / length
    beta = hb.beta[N_PRE:, 0]
    broken = hb.broken[N_PRE:, 0]
    peak = C0 - SIG_T * TANPHI
    assert abs(peak / 1e6 - 2.42265) < 1e-5
    kp = int(np.argmax(tau))
    np.testing.assert_allclose(tau[kp], peak, rtol=1e-12)
    assert abs(gam[kp] / (peak / G) - 1) < 2e-3            # reached at gamma = tau / G
    assert beta[kp - 1] == 0 < beta[kp]                  # first yield at the peak
    assert np.all(hb.alpha == 0)                           # -F_n / A_c = 1 MPa < T0
    # eq 8-9 on the softening line: tau = c - sigma_t tan(phi) with
    # c = c0 (1 - (gamma - tau / G) / gamma_lim), until the strength reaches zero
    # at gamma_lim (1 - sigma_t tan(phi) / c0)
    line = (C0 * (1 - gam / GAM_LIM) - SIG_T * TANPHI) / (1 - C0 / (G * GAM_LIM))
    soft = np.arange(kp, kp + 1500)
    assert np.max(np.abs(tau[soft] - line[soft])) < 2e-3 * peak
    g_zero = GAM_LIM * (1 - SIG_T * TANPHI / C0)
    k_zero = int(np.argmax(tau[kp:] == 0)) + kp
    assert tau[k_zero] == 0 and abs(gam[k_zero] / g_zero - 1) < 2e-3
    # break in shear once c = 0: gamma_p = gamma - (0 + F_n tan(phi) / A_c) / G
    # = gamma_lim, i.e. at gamma = gamma_lim - sigma_t tan(phi) / G
    kb = int(np.argmax(broken))
    assert broken[kb] and not broken[kb - 1] and broken[kb:].all()
    assert int(hb.break_mode[-1, 0]) == 2
    assert abs(gam[kb] / (GAM_LIM - SIG_T * TANPHI / G) - 1) < 2e-3
    # afterwards a frictional contact held open: no force at all
    assert kb < len(tau) - 100
    assert np.all(f[N_PRE + kb + 1:] == 0)


@pytest.mark.parametrize("r1, r2", RADII)
def test_twist_meets_the_shear_branch_of_ineq11(r1, r2):
    """3D, tension pre-load (sigma_t) and an elastic shear pre-load (tau_s), then
    a twist: moments are lost at the first step whose trial twist satisfies
    tau_s + |M_n| min(R) / J >= c0 - sigma_t tan(phi).  With M_n = K_s J theta / A_c
    this is G theta min(R) / L >= c0 - sigma_t tan(phi) - tau_s: the area and J
    cancel, the fibre distance min(R) decides (theta* = 1.18e-3 rad here)."""
    dim = 3
    bonds, parts, params = setup(dim, r1, r2)
    a, length, _, ks, j_pol, _, r_min = section(dim, r1, r2)
    n_shear = 300
    (b0, p0), _ = drive(bonds, parts, params, dim, tensioned_shear_prog(dim, length),
                        N_PRE + n_shear)
    tau_s = float(np.linalg.norm(np.asarray(b0.shear_force[0]))) / a
    np.testing.assert_allclose(tau_s, G * DSTRAIN * n_shear, rtol=1e-9)
    np.testing.assert_allclose(-float(b0.normal_force[0]) / a, SIG_T, rtol=1e-9)
    assert not bool(b0.moment_lost[0]) and float(b0.beta[0]) == 0
    # from the loaded state: particle 1 turns about the bond axis, nothing moves
    n_twist = 1500
    dth = 2.7e-6 * np.pi / 3               # per step, incommensurate with theta*
    nvec = np.array(p0.pos[1] - p0.pos[0])
    nvec = nvec / np.linalg.norm(nvec)
    w = np.zeros((2, 3))
    w[1] = dth / DT * nvec
    _, (hb, _, _, _) = drive(b0, p0, params, dim, prog(0, 0.0, 0.0, w), n_twist)
    twist = np.asarray(hb.twist)[:, 0]
    lost = np.asarray(hb.moment_lost)[:, 0]
    fs = np.linalg.norm(np.asarray(hb.shear_force)[:, 0], axis=-1) / a
    np.testing.assert_allclose(fs, tau_s, rtol=1e-9)        # the twist adds no shear
    np.testing.assert_allclose(-np.asarray(hb.normal_force)[:, 0] / a, SIG_T, rtol=1e-9)
    rhs = C0 - SIG_T * TANPHI
    theta_star = (rhs - tau_s) * length / (G * r_min)
    assert abs(theta_star / 1.1757e-3 - 1) < 1e-3
    # hand count of the step that first reaches theta* (k is 0-based)
    k_star = int(np.ceil(theta_star / dth * (1 - 1e-13))) - 1
    assert 300 < k_star < n_twist - 300
    np.testing.assert_array_equal(lost, np.arange(n_twist) >= k_star)
    # before: M_n = K_s J / A_c theta (eq 4) on particle 0, against its relative
    # rotation (-theta about n)
    theta = dth * np.arange(1, n_twist + 1)
    np.testing.assert_allclose(twist[:k_star], ks * j_pol / a * theta[:k_star], rtol=1e-9)
    assert np.all(twist[k_star:] == 0)
    # a moment loss only: the forces neither yield nor break
    assert not np.asarray(hb.broken).any() and np.all(np.asarray(hb.beta) == 0)
    assert np.all(np.asarray(hb.alpha) == 0)


@pytest.mark.parametrize("dim, r1, r2", [
    (2, 0.5, 0.3), (2, 0.3, 0.5), (3, 0.5, 0.3), (3, 0.3, 0.5)])
def test_shear_yield_meets_the_shear_branch_of_ineq11(dim, r1, r2):
    """With M_n = 0 the shear branch of ineq 11 is the eq 8 yield condition at
    c = c0: moments are lost at the step the bond first yields in shear."""
    hb, _, _, _ = tensioned_shear(dim, r1, r2)
    beta = hb.beta[:, 0]
    ky = int(np.argmax(beta > 0))
    assert ky > N_PRE
    np.testing.assert_array_equal(hb.moment_lost[:, 0], np.arange(len(beta)) >= ky)
