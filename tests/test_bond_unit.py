"""Single linked-bar bond driven kinematically (002 §1.3): tension, direct shear,
bending, twist, objectivity, vmap, grad, padding; plus create_bonds and the
small helpers.  Two spheres / discs R = 0.5 m, E = 10 GPa, nu = 0.22,
c0 = T0 = 3 MPa, phi = 30 deg, eps_lim = 0.1 %, gamma_lim = 0.3 %; particle 0 is
the lower (fixed) one, particle 1 the upper one, so the bond runs along +y (2D)
or +z (3D)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jdem.bond import (bond_forces, bond_geometry, bond_stats, bond_strain_energy,
                       create_bonds, damage)
from jdem.state import ROW_ALIGN, Params, aligned_rows, empty_bonds, make_params, make_particles
from seed_bond import C0, E, EPS_LIM, G, GAM_LIM, NU, PHI, T0, TANPHI

R = 0.5
L = 2 * R
DT = 1e-3
DSTRAIN = 5e-7          # strain increment per step in the tension / shear tests


@pytest.fixture(autouse=True, scope="module")
def _x64():
    """Run this module under float64 (set here rather than at import so that the
    flag does not leak into modules collected later), then restore it."""
    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", old)


def area(dim):
    return 2 * R if dim == 2 else np.pi * R ** 2


def axis(dim):
    """Index of the bond axis (the 'vertical')."""
    return dim - 1


def setup(dim, capacity=None, bond_capacity=1, **kw):
    """Two particles on the bond axis joined by one bond (one row unless
    ``bond_capacity`` says more)."""
    pos = np.zeros((2, dim))
    pos[1, axis(dim)] = L
    parts = make_particles(pos, [R, R], density=2500.0, capacity=capacity)
    bonds = create_bonds(parts, dim, gap_tolerance=1e-9, capacity=bond_capacity)
    pk = dict(dim=dim, dt=DT, bond_youngs=E, bond_poisson=NU, bond_tensile=T0,
              bond_cohesion=C0, bond_friction_angle=PHI, bond_tensile_strain=EPS_LIM,
              bond_shear_strain=GAM_LIM)
    pk.update(kw)
    return bonds, parts, make_params(**pk)


def drive(bonds, parts, params, dim, kin, nsteps, record=True):
    """Kinematic loop: at step k, ``kin(k, pos)`` gives the velocities and angular
    velocities of all particles; bond_forces, then x += v dt.  Returns the final
    (bonds, particles) and (if ``record``) the per-step history
    (bonds, force, torque, pos)."""
    def body(carry, k):
        b, p = carry
        vel, w = kin(k, p.pos)
        p = p._replace(vel=vel, angvel=w)
        b, f, t = bond_forces(b, p, params, dim, k)
        hist = (b, f, t, p.pos) if record else None
        p = p._replace(pos=p.pos + vel * params.dt)
        return (b, p), hist

    return jax.lax.scan(body, (bonds, parts), jnp.arange(nsteps))


def zeros_rot(dim, n=2):
    return jnp.zeros((n,) if dim == 2 else (n, 3))


def upper_vel(dim, v_vec, n=2):
    return jnp.zeros((n, dim)).at[1].set(v_vec)


def tension_kin(dim, n=2):
    v = DSTRAIN * L / DT
    e = jnp.zeros(dim).at[axis(dim)].set(v)
    return lambda k, pos: (upper_vel(dim, e, n), zeros_rot(dim, n))


def tangent(dim, nvec):
    """Unit vector ⊥ n in the x-(bond axis) plane: (1, 0) / (1, 0, 0) for n = axis."""
    if dim == 2:
        return jnp.array([nvec[1], -nvec[0]])
    return jnp.array([nvec[2], 0.0, -nvec[0]])


# --------------------------------------------------------------------------- geometry

@pytest.mark.parametrize("dim", [2, 3])
def test_geometry(dim):
    bonds, parts, params = setup(dim)
    g = bond_geometry(bonds, parts, params, dim)
    a = area(dim)
    j = np.pi * (2 * R) ** 4 / 32
    np.testing.assert_allclose(g.area, [a], rtol=1e-14)
    np.testing.assert_allclose(g.length, [L], rtol=1e-14)
    np.testing.assert_allclose(g.kn, [E * a / L], rtol=1e-14)
    np.testing.assert_allclose(g.ks, [G * a / L], rtol=1e-14)
    np.testing.assert_allclose(g.J, [j], rtol=1e-14)
    np.testing.assert_allclose(g.I, [j / 2], rtol=1e-14)


# --------------------------------------------------------------------------- tension

@pytest.mark.parametrize("dim", [2, 3])
def test_uniaxial_tension(dim):
    bonds, parts, params = setup(dim)
    nsteps = int(1.15e-3 / DSTRAIN)
    run = jax.jit(lambda prm: drive(bonds, parts, prm, dim, tension_kin(dim), nsteps))
    _, (hb, force, torque, _) = run(params)
    a = area(dim)
    stress = -np.asarray(hb.normal_force)[:, 0] / a
    strain = np.asarray(hb.u_n)[:, 0] / L
    alpha = np.asarray(hb.alpha)[:, 0]
    broken = np.asarray(hb.broken)[:, 0]
    np.testing.assert_allclose(strain, DSTRAIN * np.arange(1, nsteps + 1), rtol=1e-9)

    # elastic part: slope E
    el = (alpha == 0) & (stress < T0)
    assert el.sum() > 500
    np.testing.assert_allclose(stress[el] / strain[el], E, rtol=1e-6)

    # peak
    kp = int(np.argmax(stress))
    assert abs(stress[kp] / T0 - 1) < 5e-3
    assert abs(strain[kp] / (T0 / E) - 1) < 5e-3

    # break: once, in tension, where the stress line reaches zero (strain = eps_lim)
    kb = int(np.argmax(broken))
    assert broken[kb] and not broken[kb - 1] and broken[kb:].all()
    assert int(hb.break_step[-1, 0]) == kb
    assert int(hb.break_mode[-1, 0]) == 1
    assert (np.asarray(hb.break_mode)[:kb, 0] == 0).all()
    assert abs(strain[kb] / EPS_LIM - 1) < 5e-3
    assert alpha[kb] == 1.0

    # softening: linear from (T0/E, T0) to (eps_lim, 0)
    soft = np.arange(kp, kb + 1)
    line = T0 * (EPS_LIM - strain[soft]) / (EPS_LIM - T0 / E)
    assert np.max(np.abs(stress[soft] - line)) < 5e-3 * T0
    assert np.all(np.diff(stress[soft]) <= 0)
    # alpha = 1 - T/T0: the force transmitted at step k+1 is the strength after step k
    np.testing.assert_allclose(stress[soft[:-1] + 1], T0 * (1 - alpha[soft[:-1]]),
                               rtol=1e-12, atol=1e-9 * T0)
    assert (alpha[:kp] == 0).all() and np.all(np.diff(alpha) >= 0)

    # after the break: no force, no torque, no moment, no shear
    assert kb < nsteps - 50
    assert np.all(np.asarray(hb.normal_force)[kb + 1:] == 0)
    assert np.all(np.asarray(force)[kb + 1:] == 0)
    assert np.all(np.asarray(torque)[kb + 1:] == 0)
    # forces on the particles: upper pulled down, lower pulled up, equal and opposite
    f = np.asarray(force)
    np.testing.assert_allclose(f[:kb, 1, axis(dim)], -stress[:kb] * a, rtol=1e-12, atol=1e-6)
    np.testing.assert_allclose(f[:, 0], -f[:, 1], atol=1e-9)
    # moments were lost at the peak (ineq 11: -F_n/A_c >= T0), never carried
    assert np.asarray(hb.moment_lost)[kp:, 0].all()


# --------------------------------------------------------------------------- direct shear

def shear_kin(dim, n_comp):
    """Pre-compress by 3e6 L / E in n_comp steps, then slide the upper particle along
    the current tangent of the bond (a circle about the lower particle), which
    keeps the normal gap - hence F_n - fixed while shearing."""
    v_c = 3e6 * L / E / (n_comp * DT)
    v_s = DSTRAIN * L / DT

    def kin(k, pos):
        nvec = (pos[1] - pos[0]) / jnp.linalg.norm(pos[1] - pos[0])
        v = jnp.where(k < n_comp, -v_c * nvec, v_s * tangent(dim, nvec))
        return upper_vel(dim, v), zeros_rot(dim)

    return kin


@pytest.mark.parametrize("dim", [2, 3])
def test_direct_shear(dim):
    bonds, parts, params = setup(dim)
    n_comp = 600
    n_shear = int(4.2e-3 / DSTRAIN)
    run = jax.jit(lambda prm: drive(bonds, parts, prm, dim, shear_kin(dim, n_comp),
                                    n_comp + n_shear))
    _, (hb, force, torque, pos) = run(params)
    a = area(dim)
    sig = 3e6
    fn = np.asarray(hb.normal_force)[:, 0]
    np.testing.assert_allclose(fn[n_comp - 1:], sig * a, rtol=1e-9)
    tau = np.linalg.norm(np.asarray(hb.shear_force)[:, 0], axis=-1)[n_comp:] / a
    gam = np.linalg.norm(np.asarray(hb.u_s)[:, 0], axis=-1)[n_comp:] / L
    beta = np.asarray(hb.beta)[n_comp:, 0]
    broken = np.asarray(hb.broken)[n_comp:, 0]
    np.testing.assert_allclose(gam, DSTRAIN * np.arange(1, n_shear + 1), rtol=1e-9)
    assert np.all(np.asarray(hb.alpha) == 0)

    peak = C0 + sig * TANPHI            # 002 eq 14: 4.732 MPa
    resid = sig * TANPHI                # 1.732 MPa
    el = (beta == 0) & (tau < peak)
    assert el.sum() > 1000
    np.testing.assert_allclose(tau[el] / gam[el], G, rtol=1e-6)

    kp = int(np.argmax(tau))
    assert abs(tau[kp] / peak - 1) < 5e-3
    assert abs(peak / 1e6 - 4.732) < 1e-3

    kb = int(np.argmax(broken))
    assert broken[kb] and not broken[kb - 1]
    assert int(hb.break_mode[-1, 0]) == 2
    assert int(hb.break_step[-1, 0]) == n_comp + kb
    # residual reached when the plastic shear strain gamma_p = gamma - tau_res / G
    # equals gamma_lim
    assert abs((gam[kb] - resid / G) / GAM_LIM - 1) < 5e-3

    # linear softening between the peak and (gamma_lim + tau_res / G, tau_res)
    soft = np.arange(kp, kb + 1)
    g_end = GAM_LIM + resid / G
    g_pk = peak / G
    line = resid + C0 * (g_end - gam[soft]) / (g_end - g_pk)
    assert np.max(np.abs(tau[soft] - line)) < 5e-3 * peak
    assert np.all(np.diff(tau[soft]) <= 0)
    # beta = 1 - c/c0: shear stress at k+1 is c(after step k) + sigma tan(phi)
    np.testing.assert_allclose(tau[soft[:-1] + 1], resid + C0 * (1 - beta[soft[:-1]]),
                               rtol=1e-10)

    # afterwards: frictional sliding at the residual, normal force unchanged
    assert kb < n_shear - 1000
    np.testing.assert_allclose(tau[kb + 1:], resid, rtol=5e-3)
    np.testing.assert_allclose(tau[kb + 1:], resid, rtol=1e-9)
    np.testing.assert_allclose(fn[n_comp + kb + 1:], sig * a, rtol=1e-9)
    # the force on the upper particle is the contact force: normal push + friction
    f_up = np.asarray(force)[-1, 1]
    nv = np.asarray(pos)[-1, 1] - np.asarray(pos)[-1, 0]
    nv /= np.linalg.norm(nv)
    np.testing.assert_allclose(f_up @ nv, sig * a, rtol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(f_up - (f_up @ nv) * nv), resid * a, rtol=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
def test_brittle_bond_breaks_in_shear_at_its_peak(dim):
    """gamma_lim = 0 (perfectly brittle in shear, 002 eq 10): the bond breaks in
    shear (mode 2) on the step its shear stress reaches c0 + sigma tan(phi), and
    slides at the residual sigma tan(phi) from the next step on."""
    bonds, parts, params = setup(dim, bond_shear_strain=0.0)
    n_comp = 600
    n_shear = int(1.5e-3 / DSTRAIN)
    _, (hb, _, _, _) = jax.jit(lambda prm: drive(bonds, parts, prm, dim,
                                                 shear_kin(dim, n_comp),
                                                 n_comp + n_shear))(params)
    a = area(dim)
    sig = 3e6
    tau = np.linalg.norm(np.asarray(hb.shear_force)[:, 0], axis=-1)[n_comp:] / a
    broken = np.asarray(hb.broken)[n_comp:, 0]
    gam = DSTRAIN * np.arange(1, n_shear + 1)
    peak = C0 + sig * TANPHI
    kb = int(np.argmax(broken))
    assert broken[kb] and not broken[kb - 1] and broken[-1]
    assert int(hb.break_mode[-1, 0]) == 2 and float(hb.beta[-1, 0]) == 1.0
    # the break step is the first whose elastic trial stress G gamma reaches the peak
    assert kb == int(np.argmax(G * gam >= peak))
    assert abs(tau[kb - 1] / peak - 1) < 2 * DSTRAIN * G / peak
    np.testing.assert_allclose(tau[kb + 1:], sig * TANPHI, rtol=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
def test_bond_dashpots_oppose_the_relative_velocity(dim):
    """Params.bond_damping zeta: the bond adds -2 zeta sqrt(m* K_n) v_n n - 2 zeta
    sqrt(m* K_s) v_s on the upper particle (000 eq 3-1 with the reduced mass m*
    = m1 m2 / (m1 + m2)), the opposite on the lower one, and stores nothing: the
    difference to the undamped bond under the same motion is exactly that force."""
    zeta = 0.3
    bonds, parts, params = setup(dim)
    damped = params._replace(bond_damping=jnp.asarray(zeta))
    t = tangent(dim, jnp.zeros(dim).at[axis(dim)].set(1.0))
    v_n, v_s = 2e-7 * L / DT, -1.3e-7 * L / DT
    v = jnp.zeros(dim).at[axis(dim)].set(v_n) + v_s * t
    kin = lambda k, pos: (upper_vel(dim, v), zeros_rot(dim))
    run = jax.jit(lambda prm: drive(bonds, parts, prm, dim, kin, 5))
    (b0, _), (_, f0, t0, pos) = run(params)
    (b1, _), (_, f1, t1, _) = run(damped)
    m = np.asarray(parts.mass)
    m_red = m[0] * m[1] / (m[0] + m[1])
    g = bond_geometry(bonds, parts, params, dim)
    c_n = 2 * zeta * np.sqrt(m_red * float(g.kn[0]))
    c_s = 2 * zeta * np.sqrt(m_red * float(g.ks[0]))
    d = np.asarray(pos)[:, 1] - np.asarray(pos)[:, 0]
    nv = d / np.linalg.norm(d, axis=1, keepdims=True)
    vn = nv @ np.asarray(v)
    expect = -(c_n * vn[:, None] * nv + c_s * (np.asarray(v)[None] - vn[:, None] * nv))
    diff = np.asarray(f1) - np.asarray(f0)
    np.testing.assert_allclose(diff[:, 1], expect, rtol=1e-6, atol=1e-12 * c_n * abs(v_n))
    np.testing.assert_allclose(diff[:, 0], -expect, rtol=1e-6, atol=1e-12 * c_n * abs(v_n))
    for name in ("normal_force", "shear_force", "u_n", "u_s"):
        np.testing.assert_array_equal(getattr(b1, name), getattr(b0, name))


# --------------------------------------------------------------------------- bending / twist

def ineq11(fn, fs_mag, mn_mag, ms_mag, dim):
    a = area(dim)
    j = np.pi * (2 * R) ** 4 / 32
    i = j / 2
    return ((-fn / a + ms_mag / i * R >= T0)
            | (fs_mag / a + mn_mag / j * R >= fn / a * TANPHI + C0))


@pytest.mark.parametrize("pre", [0.0, 0.5, -0.5])
@pytest.mark.parametrize("dim", [2, 3])
def test_bending_and_moment_cutoff(dim, pre):
    """Bending by a rotation of the upper particle, after an axial pre-load of
    ``pre`` T0 (tension positive): ineq 11's tension branch -F_n / A_c + |M| R / I
    >= T0 cuts the moment at |M| R / I = (1 - pre) T0, i.e. at theta = (1 - pre)
    x 6e-4."""
    bonds, parts, params = setup(dim)
    dth = 7.3e-7 * np.pi / 3        # rotation per step, not commensurate with the limit
    omega = dth / DT
    w_up = omega if dim == 2 else jnp.array([omega, 0.0, 0.0])
    n_pre = int(round(abs(pre) * T0 / E / DSTRAIN))
    nsteps = n_pre + 1800
    v_pre = jnp.zeros(dim).at[axis(dim)].set(np.sign(pre) * DSTRAIN * L / DT)

    def kin(k, pos):
        loading = k < n_pre
        vel = jnp.where(loading, upper_vel(dim, v_pre), jnp.zeros((2, dim)))
        return vel, jnp.where(loading, zeros_rot(dim), zeros_rot(dim).at[1].set(w_up))

    run = jax.jit(lambda prm: drive(bonds, parts, prm, dim, kin, nsteps))
    _, (hb, force, torque, pos) = run(params)
    a = area(dim)
    kn = E * a / L
    i_m = np.pi * (2 * R) ** 4 / 64
    slope = kn * i_m / a            # bending moment per radian (002 eq 4)
    theta = dth * np.clip(np.arange(1, nsteps + 1) - n_pre, 0, None)
    bend = np.asarray(hb.bend)[:, 0]
    bend_x = bend if dim == 2 else bend[:, 0]
    lost = np.asarray(hb.moment_lost)[:, 0]
    fn = np.asarray(hb.normal_force)[:, 0]
    fs_mag = np.linalg.norm(np.asarray(hb.shear_force)[:, 0], axis=-1)
    mn = np.asarray(hb.twist)[:, 0]

    # ineq 11 on the recorded history, with the trial moment of each step
    # (the moment of the previous step plus this step's increment)
    dm = slope * dth
    prev = np.concatenate([[0.0], bend_x[:-1]])
    trial = prev + dm
    met = ineq11(fn, fs_mag, np.abs(mn), np.abs(trial), dim)
    assert met.any()
    k_star = int(np.argmax(met))
    # |M| R / I = T0 at theta = 6e-4 with F_n = 0; the pre-load's stress adds to it
    np.testing.assert_allclose(-fn[n_pre - 1], pre * T0 * area(dim), rtol=1e-6) if n_pre \
        else None
    assert abs(theta[k_star] / ((1 - pre) * 6e-4) - 1) < 0.03
    np.testing.assert_array_equal(lost, np.arange(nsteps) >= k_star)
    assert np.all(bend[k_star:] == 0) and np.all(mn == 0)

    # before the cut-off: M_s = K_n I / A_c * theta, acting on particle 1 against
    # its relative rotation (-omega), so along +x
    np.testing.assert_allclose(bend_x[:k_star], slope * theta[:k_star], rtol=1e-9)
    if dim == 3:
        assert np.all(bend[:, 1:] == 0)
    # torques: r x F plus M on the lower particle, r x (-F) - M on the upper one
    f = np.asarray(force)
    t = np.asarray(torque)
    m_vec = bend
    # the contact point halves the current centre line (equal radii)
    r1 = 0.5 * (np.asarray(pos)[:, 1] - np.asarray(pos)[:, 0])
    cr = (lambda r, v: r[..., 0] * v[..., 1] - r[..., 1] * v[..., 0]) if dim == 2 else \
        (lambda r, v: np.cross(r, v))
    np.testing.assert_allclose(t[:, 0], cr(r1, f[:, 0]) + m_vec, rtol=1e-10, atol=1e-3)
    np.testing.assert_allclose(t[:, 1], cr(-r1, f[:, 1]) - m_vec, rtol=1e-10, atol=1e-3)
    assert not np.asarray(hb.broken).any()


def test_twist_3d():
    dim = 3
    bonds, parts, params = setup(dim)
    dth = 1e-6
    nsteps = 1000
    w_up = jnp.array([0.0, 0.0, dth / DT])

    def kin(k, pos):
        return jnp.zeros((2, dim)), zeros_rot(dim).at[1].set(w_up)

    _, (hb, force, torque, _) = jax.jit(
        lambda prm: drive(bonds, parts, prm, dim, kin, nsteps))(params)
    a = area(dim)
    j = np.pi * (2 * R) ** 4 / 32
    slope = G * a / L * j / a       # K_s J / A_c per radian (002 eq 4)
    theta = dth * np.arange(1, nsteps + 1)
    np.testing.assert_allclose(np.asarray(hb.twist)[:, 0], slope * theta, rtol=1e-9)
    assert np.all(np.asarray(hb.bend) == 0)
    assert np.all(np.asarray(force) == 0)
    assert not np.asarray(hb.moment_lost).any()
    t = np.asarray(torque)
    np.testing.assert_allclose(t[:, 0, 2], slope * theta, rtol=1e-9)
    np.testing.assert_allclose(t[:, 1], -t[:, 0], rtol=1e-12)
    assert np.all(t[:, :, :2] == 0)


# --------------------------------------------------------------------------- objectivity

def rigid_kin(dim, omega, k_start=0, pre=None):
    """Both particles rotate rigidly about the midpoint of the bond from step
    k_start; before it, ``pre`` gives the velocities."""
    w = omega if dim == 2 else jnp.array([omega, 0.0, 0.0])

    def kin(k, pos):
        mid = 0.5 * (pos[0] + pos[1])
        ws = zeros_rot(dim) + w
        rel = pos - mid
        if dim == 2:
            vel = jnp.stack([-omega * rel[:, 1], omega * rel[:, 0]], axis=-1)
        else:
            vel = jnp.cross(ws, rel)
        if pre is None:
            return vel, ws
        pv, pw = pre(k, pos)
        return jnp.where(k < k_start, pv, vel), jnp.where(k < k_start, pw, ws)

    return kin


@pytest.mark.parametrize("dim", [2, 3])
def test_rigid_rotation_unloaded(dim):
    bonds, parts, params = setup(dim)
    dth = 1e-4
    nsteps = 1000                   # 0.1 rad in all
    _, (hb, force, torque, pos) = jax.jit(
        lambda prm: drive(bonds, parts, prm, dim, rigid_kin(dim, dth / DT), nsteps))(params)
    a = area(dim)
    kn = E * a / L
    ref_f = kn * L * dth            # force one step of a non-rigid motion of that size gives
    ref_m = kn * (np.pi * (2 * R) ** 4 / 64) / a * dth
    assert np.max(np.abs(np.asarray(force))) <= 1e-9 * ref_f
    assert np.max(np.abs(np.asarray(hb.normal_force))) <= 1e-9 * ref_f
    assert np.max(np.abs(np.asarray(hb.shear_force))) <= 1e-9 * ref_f
    assert np.max(np.abs(np.asarray(hb.bend))) <= 1e-9 * ref_m
    assert np.max(np.abs(np.asarray(hb.twist))) <= 1e-9 * ref_m
    assert np.max(np.abs(np.asarray(torque))) <= 1e-9 * (ref_m + ref_f * L)
    # it really turned (by 0.1 rad, in the plane ⊥ the rotation axis)
    p = np.asarray(pos)[-1]
    b = (p[1] - p[0])[-2:]          # (x, y) in 2D, (y, z) in 3D; started as (0, 1)
    assert abs(abs(np.arctan2(b[0], b[1])) - 0.1) < 1e-3


@pytest.mark.parametrize("dim", [2, 3])
def test_rigid_rotation_preloaded(dim):
    """Load the bond elastically in tension, shear (in the plane of the later
    rotation) and bending, then turn both particles rigidly by 0.1 rad: the
    magnitudes stay and the force on the upper particle turns with the bond."""
    bonds, parts, params = setup(dim)
    n_pre = 100
    ax = axis(dim)
    side = 0 if dim == 2 else 1     # shear direction in the plane of the rotation
    v_pre = jnp.zeros(dim).at[ax].set(5e-7 * L / DT).at[side].set(1.2e-6 * L / DT)
    w_bend = 1e-6 / DT
    wb = w_bend if dim == 2 else jnp.array([w_bend, 0.0, 0.0])

    def pre(k, pos):
        return upper_vel(dim, v_pre), zeros_rot(dim).at[1].set(wb)

    kin = rigid_kin(dim, 1e-4 / DT, k_start=n_pre, pre=pre)
    nsteps = n_pre + 1000
    _, (hb, force, torque, pos) = jax.jit(
        lambda prm: drive(bonds, parts, prm, dim, kin, nsteps))(params)
    fn = np.asarray(hb.normal_force)[:, 0]
    fs = np.linalg.norm(np.asarray(hb.shear_force)[:, 0], axis=-1)
    bend = np.asarray(hb.bend)[:, 0]
    bm = np.abs(bend) if dim == 2 else np.linalg.norm(bend, axis=-1)
    k0 = n_pre - 1
    assert fn[k0] < 0 and fs[k0] > 0 and bm[k0] > 0
    assert not np.asarray(hb.moment_lost).any() and np.all(np.asarray(hb.alpha) == 0)
    np.testing.assert_allclose(fn[k0:], fn[k0], rtol=1e-9)
    np.testing.assert_allclose(fs[k0:], fs[k0], rtol=1e-9)
    np.testing.assert_allclose(bm[k0:], bm[k0], rtol=1e-9)
    # the force on particle 1 turned with the bond
    p = np.asarray(pos)
    b0, b1 = p[k0, 1] - p[k0, 0], p[-1, 1] - p[-1, 0]
    if dim == 3:
        b0, b1 = b0[1:], b1[1:]
    ang = np.arctan2(b0[0] * b1[1] - b0[1] * b1[0], b0 @ b1)
    assert abs(abs(ang) - 0.1) < 1e-3
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    f = np.asarray(force)
    f0, f1 = f[k0, 1], f[-1, 1]
    if dim == 3:
        assert abs(f1[0]) <= 1e-9 * np.linalg.norm(f0)
        f0, f1 = f0[1:], f1[1:]
    np.testing.assert_allclose(f1, rot @ f0, atol=1e-9 * np.linalg.norm(f0))


# --------------------------------------------------------------------------- vmap / grad

def test_vmap_over_tensile_strain():
    dim = 3
    bonds, parts, params = setup(dim)
    eps = jnp.array([0.0, 2e-4, 5e-4, 8e-4, 1e-3, 1.5e-3, 2e-3, 5e-3])
    nsteps = int(1.3e-3 / DSTRAIN)

    def run(prm):
        _, (hb, f, t, _) = drive(bonds, parts, prm, dim, tension_kin(dim), nsteps)
        return hb, f, t

    axes = Params(*[None] * len(Params._fields))._replace(bond_tensile_strain=0)
    batched = jax.jit(jax.vmap(run, in_axes=(axes,)))(params._replace(bond_tensile_strain=eps))
    single = jax.jit(run)
    for b in range(eps.size):
        ref = single(params._replace(bond_tensile_strain=eps[b]))
        for got, want in zip(jax.tree_util.tree_leaves(batched), jax.tree_util.tree_leaves(ref)):
            np.testing.assert_allclose(np.asarray(got)[b], np.asarray(want), rtol=1e-10,
                                       atol=1e-6)
    # the brittle bond (eps_lim = 0) broke at the peak, the others in order of eps_lim,
    # in tension; those with eps_lim > 1.3e-3 (the final strain) are still intact
    hb = batched[0]
    bs = np.asarray(hb.break_step)[:, -1, 0]
    k_peak = int(np.argmax(-np.asarray(hb.normal_force)[0, :, 0]))
    assert bs[0] == k_peak and abs((k_peak + 1) * DSTRAIN / (T0 / E) - 1) < 5e-3
    assert np.all(np.diff(bs[:5]) > 0)
    assert np.all(np.asarray(hb.break_mode)[:5, -1, 0] == 1)
    assert not np.asarray(hb.broken)[5:, -1, 0].any()


def test_vmap_over_state():
    """A batch of particle states (different upper velocities) in one call."""
    dim = 3
    bonds, parts, params = setup(dim)
    vels = jnp.array([[0.0, 0.0, 1e-3], [1e-3, 0.0, 0.0], [0.0, -1e-3, 5e-4]])
    w = jnp.array([[0.0, 0.0, 0.0], [1e-3, 2e-3, 0.0], [0.0, 0.0, 3e-3]])
    batch = jax.vmap(lambda v, wv: parts._replace(vel=upper_vel(dim, v),
                                                  angvel=zeros_rot(dim).at[1].set(wv)))(vels, w)
    bb = jax.tree_util.tree_map(lambda x: jnp.stack([x] * 3), bonds)
    out = jax.jit(jax.vmap(lambda b, p: bond_forces(b, p, params, dim, 0)))(bb, batch)
    for k in range(3):
        p = jax.tree_util.tree_map(lambda x: x[k], batch)
        ref = bond_forces(bonds, p, params, dim, 0)
        for got, want in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(ref)):
            np.testing.assert_allclose(np.asarray(got)[k], np.asarray(want), rtol=1e-12,
                                       atol=1e-9)


def test_grad_post_peak_stress():
    dim = 3
    bonds, parts, params = setup(dim)
    nsteps = int(round(6e-4 / DSTRAIN))     # strain 0.06 % at the last step
    a = area(dim)

    def stress(t0, eps_lim):
        prm = params._replace(bond_tensile=t0, bond_tensile_strain=eps_lim)
        (b, _), _ = drive(bonds, parts, prm, dim, tension_kin(dim), nsteps, record=False)
        return -b.normal_force[0] / a

    f = jax.jit(stress)
    g = jax.jit(jax.grad(stress, argnums=(0, 1)))
    t0, el = jnp.asarray(T0), jnp.asarray(EPS_LIM)
    s = float(f(t0, el))
    # on the softening branch: ~ T0 (1 - eps / eps_lim) / (1 - T0 / (E eps_lim))
    assert abs(s / (T0 * (1 - 6e-4 / EPS_LIM) / (1 - T0 / (E * EPS_LIM))) - 1) < 5e-3
    gt, ge = (float(x) for x in g(t0, el))
    ht, he = T0 * 1e-5, EPS_LIM * 1e-5
    fd_t = (float(f(t0 + ht, el)) - float(f(t0 - ht, el))) / (2 * ht)
    fd_e = (float(f(t0, el + he)) - float(f(t0, el - he))) / (2 * he)
    assert abs(gt / fd_t - 1) < 1e-2
    assert abs(ge / fd_e - 1) < 1e-2
    assert gt > 0 and ge > 0


# --------------------------------------------------------------------------- padding

def combined_kin(dim, n_part, rate=4.0):
    """Tension + shear + rotation of particle 1; breaks the bond (in tension) at
    about step 3330 / rate, after the moments were lost."""
    v = jnp.zeros(dim).at[axis(dim)].set(3e-7 * rate * L / DT).at[0].set(4e-7 * rate * L / DT)
    w = 2e-7 * rate / DT if dim == 2 else jnp.array([2e-7, 1e-7, 3e-7]) * rate / DT
    return lambda k, pos: (upper_vel(dim, v, n_part), zeros_rot(dim, n_part).at[1].set(w))


@pytest.mark.parametrize("dim", [2, 3])
def test_padding_changes_nothing(dim):
    nsteps = 1200
    bonds, parts, params = setup(dim)
    _, (hb, f, t, _) = jax.jit(
        lambda prm: drive(bonds, parts, prm, dim, combined_kin(dim, 2), nsteps))(params)
    assert np.asarray(hb.broken)[-1, 0] and int(hb.break_step[-1, 0]) < nsteps - 200
    assert np.asarray(hb.moment_lost)[-1, 0]

    bp, pp, _ = setup(dim, capacity=5, bond_capacity=4)
    # padded rows that even point at the real pair must stay inert
    bp = bp._replace(i=bp.i.at[2].set(0), j=bp.j.at[2].set(1))
    bp = bp._replace(i=bp.i.at[3].set(1), j=bp.j.at[3].set(4))
    assert bp.valid.tolist() == [True, False, False, False]
    _, (hp, fp, tp, _) = jax.jit(
        lambda prm: drive(bp, pp, prm, dim, combined_kin(dim, 5), nsteps))(params)
    # same numbers up to round-off (the padded program is compiled differently)
    np.testing.assert_allclose(np.asarray(fp)[:, :2], np.asarray(f), rtol=1e-12, atol=1e-6)
    np.testing.assert_allclose(np.asarray(tp)[:, :2], np.asarray(t), rtol=1e-12, atol=1e-6)
    assert np.all(np.asarray(fp)[:, 2:] == 0) and np.all(np.asarray(tp)[:, 2:] == 0)
    empty = empty_bonds(dim, 4)
    for name in hp._fields:
        got, want = np.asarray(getattr(hp, name)), np.asarray(getattr(hb, name))
        # round-off relative to the field's scale (softening cancels digits: T0 (1 - alpha))
        np.testing.assert_allclose(got[:, :1], want, rtol=1e-12,
                                   atol=1e-12 * float(np.max(np.abs(want))), err_msg=name)
        if name not in ("i", "j", "valid"):
            np.testing.assert_array_equal(
                got[:, 1:], np.broadcast_to(np.asarray(getattr(empty, name))[1:], got[:, 1:].shape),
                err_msg=name)


@pytest.mark.parametrize("dim", [2, 3])
def test_gradients_finite(dim):
    """No NaN gradients with padded rows, perfectly brittle bonds (eps_lim =
    gamma_lim = 0) and through breakage."""
    bp, pp, params = setup(dim, capacity=4, bond_capacity=3)
    kin = combined_kin(dim, 4)

    def loss(prm):
        (b, p), _ = drive(bp, pp, prm, dim, kin, 1000, record=False)
        return (jnp.sum(b.normal_force ** 2) + jnp.sum(b.shear_force ** 2)) * 1e-12 \
            + jnp.sum(b.u_n) + jnp.sum(b.alpha + b.beta)

    grad = jax.jit(jax.grad(loss))
    zero = jnp.zeros_like(params.bond_tensile_strain)
    for prm in (params, params._replace(bond_tensile_strain=zero, bond_shear_strain=zero)):
        grads = grad(prm)
        for name, gv in grads._asdict().items():
            assert np.all(np.isfinite(np.asarray(gv))), name
        # the final state is broken in tension; the shear damage still depends on c0
        assert any(float(np.abs(gv).sum()) > 0 for gv in grads)


# --------------------------------------------------------------------------- helpers

def test_create_bonds_lattice_and_capacity():
    nx, ny = 4, 3
    pos = np.array([[x, y] for y in range(ny) for x in range(nx)], float)
    parts = make_particles(pos, np.full(len(pos), 0.5), capacity=len(pos) + 3)
    bonds = create_bonds(parts, 2, gap_tolerance=1e-6)
    n_exp = (nx - 1) * ny + nx * (ny - 1)
    # the default capacity: the bonds found, padded to a multiple of ROW_ALIGN
    assert bonds.i.shape == (aligned_rows(n_exp),) and bonds.i.shape[0] % ROW_ALIGN == 0
    valid = np.asarray(bonds.valid)
    assert valid[:n_exp].all() and not valid[n_exp:].any()
    bonds = jax.tree_util.tree_map(lambda a: a[:n_exp], bonds)
    i, j = np.asarray(bonds.i), np.asarray(bonds.j)
    assert np.all(i < j)
    assert list(zip(i, j)) == sorted(zip(i, j))
    assert np.all(j < len(pos))
    d = np.linalg.norm(pos[j] - pos[i], axis=1)
    np.testing.assert_allclose(d, 1.0)
    assert np.all(np.asarray(bonds.break_step) == -1)
    assert np.all(np.asarray(bonds.u_n) == 0) and not np.asarray(bonds.broken).any()
    big = create_bonds(parts, 2, gap_tolerance=1e-6, capacity=30)
    assert big.i.shape == (30,) and int(big.valid.sum()) == n_exp
    np.testing.assert_array_equal(big.i[:n_exp], bonds.i)
    # a tolerance that reaches the diagonals (gap sqrt 2 - 1)
    diag = create_bonds(parts, 2, gap_tolerance=0.42)
    assert int(diag.valid.sum()) == n_exp + 2 * (nx - 1) * (ny - 1)
    with pytest.raises(ValueError, match=rf"(?s)(?=.*\b10\b)(?=.*\b{n_exp}\b)"):
        create_bonds(parts, 2, gap_tolerance=1e-6, capacity=10)


def test_create_bonds_random_3d_matches_brute_force():
    rng = np.random.default_rng(1)
    n = 300
    pos = rng.uniform(0, 3.0, (n, 3))
    rad = rng.uniform(0.05, 0.2, n)
    parts = make_particles(pos, rad, capacity=n + 7)
    tol = 0.03
    bonds = create_bonds(parts, 3, gap_tolerance=tol)
    gap = np.linalg.norm(pos[:, None] - pos[None], axis=-1) - rad[:, None] - rad[None]
    ii, jj = np.nonzero(np.triu(gap <= tol, k=1))
    valid = np.asarray(bonds.valid)
    np.testing.assert_array_equal(np.asarray(bonds.i)[valid], ii)
    np.testing.assert_array_equal(np.asarray(bonds.j)[valid], jj)
    none = create_bonds(make_particles(pos[:1], rad[:1]), 3, gap_tolerance=tol, capacity=2)
    assert none.i.shape == (2,) and not np.asarray(none.valid).any()


@pytest.mark.parametrize("dim, lengths, offset", [
    (2, (40.0, 15.0), -120.0),          # the cloud entirely at negative coordinates
    (3, (30.0, 12.0, 21.0), 0.0),       # a box of three different lengths: strides differ
    (3, (20.0, 20.0, 9.0), -55.0),
    (3, (9.0, 12.0, 30.0), -10.0),      # straddling the origin, the last axis the longest
])
def test_create_bonds_across_many_cells_matches_brute_force(dim, lengths, offset):
    """Radii of order one metre (so the cell edge 2 max(R) + tol is neither tiny nor
    the whole cloud), a cloud spanning many cells along axes of unequal length,
    and coordinates away from the origin: the cell-grid search finds exactly the
    pairs a brute-force search finds."""
    rng = np.random.default_rng(dim)
    n = 700
    pos = offset + rng.uniform(0, 1, (n, dim)) * np.asarray(lengths)
    rad = rng.uniform(0.5, 1.6, n)
    parts = make_particles(pos, rad)
    tol = 0.2
    bonds = create_bonds(parts, dim, gap_tolerance=tol)
    gap = np.linalg.norm(pos[:, None] - pos[None], axis=-1) - rad[:, None] - rad[None]
    ii, jj = np.nonzero(np.triu(gap <= tol, k=1))
    assert ii.size > 200                     # the case is not empty
    valid = np.asarray(bonds.valid)
    np.testing.assert_array_equal(np.asarray(bonds.i)[valid], ii)
    np.testing.assert_array_equal(np.asarray(bonds.j)[valid], jj)


def test_create_bonds_takes_a_gap_equal_to_the_tolerance():
    """"At most gap_tolerance": discs that touch exactly (gap 0.0 in binary) bond
    with a tolerance of 0, as in a lattice of touching discs."""
    parts = make_particles(np.array([[0.0, 0.0], [2.0, 0.0], [5.0, 0.0]]), [1.0, 1.0, 1.0])
    bonds = create_bonds(parts, 2, gap_tolerance=0.0)
    valid = np.asarray(bonds.valid)
    assert valid.sum() == 1
    assert (int(bonds.i[0]), int(bonds.j[0])) == (0, 1)
    # the gap 1.0 to the third disc is bonded by a tolerance of exactly 1.0 only
    assert int(np.sum(create_bonds(parts, 2, gap_tolerance=1.0).valid)) == 2
    assert int(np.sum(create_bonds(parts, 2, gap_tolerance=0.999).valid)) == 1


def test_bonds_for_pairs_refuses_a_particle_bonded_to_itself():
    from jdem.bond import bonds_for_pairs
    with pytest.raises(ValueError, match="i < j"):
        bonds_for_pairs(np.array([0, 2]), np.array([1, 2]), 2)
    with pytest.raises(ValueError, match="i < j"):
        bonds_for_pairs(np.array([3]), np.array([1]), 2)
    ok = bonds_for_pairs(np.array([2, 0]), np.array([3, 1]), 2)
    assert [(int(a), int(b)) for a, b in zip(ok.i[:2], ok.j[:2])] == [(0, 1), (2, 3)]


def test_bond_stats_counts_breaks_by_mode_over_valid_rows():
    """bond_stats on 4 bonds (capacity 8): one broken in tension, one in shear,
    a padding row marked broken that must not count: fracture degree 2 / 4."""
    pos = np.array([[x, 0.0] for x in range(5)], float)
    parts = make_particles(pos, np.full(5, 0.5))
    b = create_bonds(parts, 2, gap_tolerance=1e-6, capacity=8)
    assert int(b.valid.sum()) == 4
    broken = np.zeros(8, bool)
    broken[[0, 2, 6]] = True                   # row 6 is padding
    mode = np.zeros(8, np.int32)
    mode[[0, 2, 6]] = [1, 2, 1]
    st = bond_stats(b._replace(broken=jnp.asarray(broken), break_mode=jnp.asarray(mode)))
    assert int(st["n_bonds"]) == 4 and int(st["n_broken"]) == 2
    assert int(st["n_tension"]) == 1 and int(st["n_shear"]) == 1
    assert float(st["fracture_degree"]) == 0.5
    assert float(bond_stats(jax.tree_util.tree_map(lambda a: a[4:], b))["fracture_degree"]) == 0


def test_energy_damage_stats():
    dim = 3
    bonds, parts, params = setup(dim, bond_capacity=2)
    v = jnp.array([2e-7, -1e-7, 3e-7]) * L / DT
    kin = lambda k, pos: (upper_vel(dim, v), zeros_rot(dim))
    (b, p), _ = jax.jit(lambda prm: drive(bonds, parts, prm, dim, kin, 500))(params)
    g = bond_geometry(b, p, params, dim)
    e = float(bond_strain_energy(b, p, params, dim))
    fs = np.linalg.norm(np.asarray(b.shear_force[0]))
    expect = float(b.normal_force[0]) ** 2 / (2 * float(g.kn[0])) + fs ** 2 / (2 * float(g.ks[0]))
    assert e > 0
    np.testing.assert_allclose(e, expect, rtol=1e-9)
    st = bond_stats(b)
    assert int(st["n_bonds"]) == 1 and int(st["n_broken"]) == 0
    assert float(st["fracture_degree"]) == 0.0

    bonds2 = bonds._replace(alpha=jnp.array([0.5, 0.7]), beta=jnp.array([0.2, 0.9]))
    dmg = damage(bonds2)
    np.testing.assert_allclose(dmg["alpha"], [0.5, 0.0])
    np.testing.assert_allclose(dmg["beta"], [0.2, 0.0])
    np.testing.assert_allclose(dmg["chi"], [1 - 0.5 * 0.8, 0.0])

    # break it in tension: stats count it, the energy drops it
    (b, p), _ = jax.jit(lambda prm: drive(bonds, parts, prm, dim, tension_kin(dim), 2200))(params)
    st = bond_stats(b)
    assert int(st["n_broken"]) == 1 and int(st["n_tension"]) == 1 and int(st["n_shear"]) == 0
    assert float(st["fracture_degree"]) == 1.0
    assert float(bond_strain_energy(b, p, params, dim)) == 0.0
    st0 = bond_stats(empty_bonds(dim, 3))
    assert int(st0["n_bonds"]) == 0 and float(st0["fracture_degree"]) == 0.0
