"""Local damping and the critical time step against analytic values (000 §3.2, §3.3).

Every system is built from linked-bar bonds (002 §1) of discs / spheres R = 0.5 m,
rho = 2500 kg/m^3, bar E = 1 GPa, nu = 0.22 and strengths far beyond reach, so
each bond is a linear spring in tension and compression alike:

* a *pair*: particle 0 fixed, particle 1 free in translation (both rotations
  held), bonded along an axis (2D) or along the diagonal (1, 2, 2) / 3 (3D).  Its
  motion along the bar is one mass m on one spring K_n = E A_c / L (002 eq 2),
  with the bar's normal dashpot c = 2 zeta sqrt(m* K_n), m* = m / 2;
* a free *chain* of N = 8 bonded discs in a straight line.

The step is the explicit central-difference cycle of :mod:`jdem.integrate`:
forces from x_n and the half-step velocity v_{n-1/2} (the dashpots and the local
damping read v_{n-1/2}), then v_{n+1/2} = v_{n-1/2} + dt F / m, x_{n+1} = x_n +
dt v_{n+1/2}.

Runtime: one compiled 200-step chunk per system (three in all); the time step
and the damping coefficients are ``Params`` arrays, so changing them does not
recompile.
"""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdem
from jdem import contact, integrate, timestep
from jdem.bond import bond_geometry, bond_strain_energy, create_bonds

R = 0.5
RHO = 2500.0
E = 1e9
NU = 0.22
CHUNK = 200            # steps per compiled call
TINY = 1e-80           # m/s: initial speed of the stability runs (see _stability_run)


def _params(dim, dt, **kw):
    return jdem.make_params(dim=dim, dt=dt, bond_youngs=E, bond_poisson=NU,
                            bond_tensile=1e30, bond_cohesion=1e30, **kw)


@functools.partial(jax.jit, static_argnames=("config",))
def _chunk(state, params, config):
    """CHUNK steps; per step: the bar opening u_n of bond 0, the velocities and
    the energy (kinetic, translational and rotational, plus bond strain energy)."""
    dim = config.dim

    def body(s, _):
        s = integrate.step(s, params, config)
        p = s.particles
        spin = p.angvel ** 2 if p.angvel.ndim == 1 else jnp.sum(p.angvel ** 2, axis=-1)
        kinetic = 0.5 * jnp.sum(p.mass * jnp.sum(p.vel ** 2, axis=-1) + p.inertia * spin)
        energy = kinetic + bond_strain_energy(s.bonds, p, params, dim)
        return s, (s.bonds.u_n[0], p.vel, energy)

    return jax.lax.scan(body, state, None, length=CHUNK)


def _simulate(state, params, config, n_chunks=1):
    out = []
    for _ in range(n_chunks):
        state, rec = _chunk(state, params, config)
        out.append(jax.device_get(rec))
    return [np.concatenate(parts) for parts in zip(*out)]


def _with_velocity(state, vel, angvel=None):
    p = state.particles
    angvel = p.angvel if angvel is None else jnp.asarray(angvel, p.angvel.dtype)
    return state._replace(particles=p._replace(vel=jnp.asarray(vel, p.vel.dtype), angvel=angvel))


@functools.lru_cache(maxsize=None)
def _pair(dim):
    """(state, config, unit bar direction u, m, K_n, K_s) of the fixed-free pair."""
    u = np.array([1.0, 0.0]) if dim == 2 else np.array([1.0, 2.0, 2.0]) / 3.0
    pos = np.stack([np.zeros(dim), 2 * R * u])
    fixed_vel = np.array([[True] * dim, [False] * dim])
    fixed_rot = np.ones((2,) if dim == 2 else (2, 3), bool)
    parts = jdem.make_particles(pos, [R, R], density=RHO, fixed_vel=fixed_vel,
                                fixed_rot=fixed_rot)
    bonds = create_bonds(parts, dim, gap_tolerance=1e-9)
    assert int(np.sum(bonds.valid)) == 1
    state, config = jdem.make_state(parts, bonds=bonds)
    g = bond_geometry(state.bonds, state.particles, _params(dim, 1e-6), dim)
    m, kn, ks = float(parts.mass[1]), float(g.kn[0]), float(g.ks[0])
    area = 2 * R if dim == 2 else np.pi * R ** 2
    assert kn == pytest.approx(E * area / (2 * R), rel=1e-14)      # 002 eq 2
    return state, config, u, m, kn, ks


# ----------------------------------------------------------------------------- local damping
def _extrema(x):
    """Indices of the interior turning points of the sampled sequence x."""
    d = np.diff(x)
    return np.nonzero(np.sign(d[1:]) != np.sign(d[:-1]))[0] + 1


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("alpha", [0.1, 0.3, 0.8])
def test_local_damping_peak_ratio(dim, alpha):
    """000 eq 3-19 on one mass and one spring: successive peaks decay by
    sqrt((1 - alpha) / (1 + alpha)) per half cycle.

    Derivation.  With F = -K x the damped force is F - alpha |F| sign(v)
    (:func:`jdem.damping.local_damping`).  Moving away from equilibrium
    (x v > 0), alpha |F| sign(v) = alpha K x, so the force is -K (1 + alpha) x;
    moving back (x v < 0) it is -K (1 - alpha) x.  Each quarter cycle is thus an
    undamped oscillator of stiffness K (1 -/+ alpha).  From a turning point at
    |x| = A_i the mass returns to x = 0 with (1/2) m v^2 = (1/2) K (1 - alpha) A_i^2
    and runs out to the next turning point, of the other sign, where
    (1/2) K (1 + alpha) A_{i+1}^2 = (1/2) m v^2.  Hence

        A_{i+1} / A_i = sqrt((1 - alpha) / (1 + alpha))        (half cycle)
        A_{i+2} / A_i = (1 - alpha) / (1 + alpha)              (full cycle)

    independent of amplitude (for small alpha, alpha ~ pi zeta of an equivalent
    viscous damping ratio zeta).

    The explicit step takes the sign from v_{n-1/2}; within a quarter cycle it
    is the central-difference scheme for K (1 -/+ alpha), which keeps its
    modified energy, so the only errors are the step at each turning point in
    which the sign flips and the sampling of the peak at whole steps, both
    O((omega dt)^2) with omega = sqrt(K (1 + alpha) / m).  With omega dt = 0.005
    the tolerance 10 (omega dt)^2 = 2.5e-4 on each ratio covers them (measured
    at alpha = 0.8: 5e-5 per half cycle, 9e-5 per cycle).

    In 3D the motion runs along the diagonal u = (1, 2, 2) / 3.  The damping acts
    per component, but with force F u and velocity v u parallel to the bar,
    -alpha |F u_c| sign(v u_c) = -alpha |F| sign(v) u_c in every component c, so
    the 1D result holds.
    """
    state, config, u, m, kn, _ = _pair(dim)
    wdt = 0.005
    dt = wdt / np.sqrt(kn * (1 + alpha) / m)
    vel = np.zeros((2, dim))
    vel[1] = 1e-3 * u                      # from equilibrium: first peak ~ 1e-6 m
    un, _, _ = _simulate(_with_velocity(state, vel), _params(dim, dt, local_damping=alpha),
                         config, n_chunks=40)
    peaks = np.abs(un[_extrema(un)])
    assert peaks.size >= 6
    half = np.sqrt((1 - alpha) / (1 + alpha))
    tol = 10 * wdt ** 2
    np.testing.assert_allclose(peaks[1:] / peaks[:-1], half, rtol=tol)
    np.testing.assert_allclose(peaks[2:] / peaks[:-2], (1 - alpha) / (1 + alpha), rtol=tol)
    # the peaks alternate in sign (an oscillation, not a creep: alpha < 1)
    signs = np.sign(un[_extrema(un)])
    assert np.all(signs[1:] == -signs[:-1])


# ----------------------------------------------------------------------------- critical step
def _damped_limit(w2, g):
    """Stable step of v+ = v- + dt (-w2 x - g v-), x+ = x + dt v+ (see below)."""
    return 2.0 / (np.sqrt(w2 + g * g / 4) + g / 2)


def _stability_run(state, params, config, vel, angvel=None):
    """Energy and velocities of CHUNK steps from a tiny initial velocity.

    The bond forces are built from velocity increments (002 eq 3, 12), so at
    TINY speed the positions do not change in float64 (the displacements stay
    below 1e-25 m after a growth by 1e55, the most 200 steps give here) and the
    system stays exactly linear: the runs measure the linear stability of the
    step itself."""
    _, v, energy = _simulate(_with_velocity(state, vel, angvel), params, config)
    return v, energy


def _growth(energy):
    """Largest energy of the last 50 steps over the energy of the first step."""
    return np.max(energy[-50:]) / energy[0]


DAMPING = {"undamped": {}, "bond_zeta_0.5": {"bond_damping": 0.5},
           "bond_zeta_3": {"bond_damping": 3.0}, "viscous_omega": {"viscous_damping": None}}


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("case", list(DAMPING))
def test_single_mass_critical_step(dim, case):
    """000 eq 3-24 and its damped form for one mass, spring and dashpot.

    The pair's motion along the bar obeys, with w2 = K_n / m and
    g = c / m = 2 zeta sqrt(m* K_n) / m + viscous_damping (m* = m / 2, so the
    bar dashpot's damping ratio on this oscillator is zeta / sqrt(2)),

        v_{n+1/2} = (1 - dt g) v_{n-1/2} - dt w2 x_n,   x_{n+1} = x_n + dt v_{n+1/2}.

    The map of (x, v) has trace T = 2 - dt^2 w2 - dt g and determinant
    D = 1 - dt g; an eigenvalue leaves the unit circle at -1 when
    1 + T + D = 4 - dt^2 w2 - 2 dt g = 0, i.e.

        dt* = 2 / (sqrt(w2 + g^2 / 4) + g / 2) = (2 / omega)(sqrt(1 + zeta'^2) - zeta'),

    (zeta' = g / (2 omega)); for g = 0 this is 000 eq 3-24, dt* = 2 sqrt(m / K).
    The other Jury conditions (|D| < 1, 1 - T + D = dt^2 w2 > 0) hold below dt*.
    Checked here: (a) the recorded velocities obey the map's recurrence
    v_{n+1} = T v_n - D v_{n-1} to rounding (the dashpot and viscous forces do
    read v_{n-1/2}); (b) at 0.95 dt* the energy does not grow, at 1.05 dt* it
    grows by more than 1e12 in 200 steps, at the rate of the dominant eigenvalue;
    (c) ``critical_timestep`` <= dt* and within its Gershgorin factor.  It
    doubles the stiffness and dashpot sums and adds the shear spring and dashpot,
    so the translational row alone gives at least dt* / max(sqrt(2 (1 + K_s / K_n)),
    2 (1 + sqrt(K_s / K_n))) = 0.305 dt* (undamped: sqrt(K_n / (2 (K_n + K_s)))
    = 0.60 dt*); a held rotation is not counted.  Asserted: [0.3 dt*, dt*],
    undamped [0.45 dt*, dt*].
    """
    state, config, u, m, kn, ks = _pair(dim)
    w2 = kn / m
    kw = dict(DAMPING[case])
    if "viscous_damping" in kw:
        kw["viscous_damping"] = np.sqrt(w2)        # g = omega: damping ratio 1/2
    zeta = kw.get("bond_damping", 0.0)
    g = 2 * zeta * np.sqrt(0.5 * m * kn) / m + kw.get("viscous_damping", 0.0)
    limit = _damped_limit(w2, g)
    vel = np.zeros((2, dim))
    vel[1] = TINY * u
    for factor in (0.95, 1.05):
        dt = factor * limit
        v, energy = _stability_run(state, _params(dim, dt, **kw), config, vel)
        s = v[:, 1] @ u                            # speed along the bar
        trace, det = 2 - dt * dt * w2 - dt * g, 1 - dt * g
        resid = s[2:] - trace * s[1:-1] + det * s[:-2]
        scale = np.abs(s[2:]) + np.abs(trace * s[1:-1]) + np.abs(det * s[:-2])
        # 2D: 4e-15.  3D: up to 1e-9, from the rounding-level motion across the
        # diagonal bar, which outlives the faster-decaying axial motion at 0.95 dt*
        assert np.max(np.abs(resid) / scale) < 1e-7
        lam = np.max(np.abs(np.roots([1.0, -trace, det])))
        if factor < 1:
            assert lam <= 1 + 1e-12
            assert _growth(energy) < 10
        else:
            assert lam > 1.1
            assert _growth(energy) > 1e12
            assert abs(s[-1] / s[-2]) == pytest.approx(lam, rel=1e-8)
    crit = float(timestep.critical_timestep(state, _params(dim, 1e-6, **kw), config))
    assert crit <= limit
    assert crit >= (0.45 if g == 0 else 0.3) * limit


@pytest.mark.parametrize("section", ["circular", "slab"])
@pytest.mark.parametrize("visc", [0.0, 1.0])
def test_spinning_disc_on_a_bond_critical_step(visc, section):
    """A disc held in place but free to spin, bonded to a held disc (2D, equal
    radii): I theta'' = -(K_s R^2 + K_n I_b / A_c) theta - c I theta' (the shear
    spring at the contact point R from the centre, the bending spring E I_b / L,
    002 eq 4; c the viscous damping, here 0 or omega).  At 0.95 of the damped
    limit dt* (as for the single mass above) the spin does not grow, at 1.05 it
    does; ``critical_timestep`` counts the spin although the disc cannot move
    (it used to skip a particle whose translation is held) and equals the damped
    limit of 2 w2 (its Gershgorin factor 2 on w2; 1/sqrt(2) dt* undamped).  Both
    2D sections (``Config.bond_section``): a 2D bar has no twist, so the twist
    spring K_s J / A_c does not enter (it used to, making the step 11-14 % short).
    """
    fixed_vel = np.ones((2, 2), bool)
    parts = jdem.make_particles(np.array([[0.0, 0.0], [2 * R, 0.0]]), [R, R], density=RHO,
                                fixed_vel=fixed_vel, fixed_rot=np.array([True, False]))
    bonds = create_bonds(parts, 2, gap_tolerance=1e-9)
    state, config = jdem.make_state(parts, bonds=bonds)
    config = config.replace(bond_section=section)
    g = bond_geometry(state.bonds, state.particles, _params(2, 1e-6), 2, section)
    k = float(g.ks[0]) * R ** 2 + float(g.kn[0] * g.I[0] / g.area[0])
    inertia = float(parts.inertia[1])
    w2 = k / inertia
    kw = {"viscous_damping": visc * np.sqrt(w2)} if visc else {}
    limit = _damped_limit(w2, kw.get("viscous_damping", 0.0))
    for factor in (0.95, 1.05):
        _, energy = _stability_run(state, _params(2, factor * limit, **kw), config,
                                   np.zeros((2, 2)), np.array([0.0, TINY]))
        assert (_growth(energy) < 10) if factor < 1 else (_growth(energy) > 1e6)
    crit = float(timestep.critical_timestep(state, _params(2, 1e-6, **kw), config))
    assert crit <= limit
    # exactly the damped limit of the doubled w2 (Gershgorin): 1/sqrt(2) dt* undamped
    assert crit == pytest.approx(_damped_limit(2 * w2, kw.get("viscous_damping", 0.0)),
                                 rel=1e-12)


def _chain(n):
    pos = np.zeros((n, 2))
    pos[:, 0] = 2 * R * np.arange(n)
    parts = jdem.make_particles(pos, np.full(n, R), density=RHO)
    bonds = create_bonds(parts, 2, gap_tolerance=1e-9)
    assert int(np.sum(bonds.valid)) == n - 1
    return jdem.make_state(parts, bonds=bonds)


def test_chain_critical_step():
    """Free chain of N = 8 bonded discs (2D), every degree of freedom excited.

    Axial modes: N equal masses, N - 1 springs K_n, free ends:
    omega_j = 2 sqrt(K_n / m) sin(j pi / (2N)), j = 0..N-1, so the highest is
    omega_max = 2 sqrt(K_n / m) cos(pi / (2N)) and dt* = sqrt(m / K_n) / cos(pi / 16)
    = 1.0196 sqrt(m / K_n).  Transverse and rotational modes: each bar stores
    (1/2) K_s u_s^2 + (1/2) (K_n I / A_c) (theta_i - theta_j)^2 with
    u_s = y_i - y_j + (theta_i + theta_j) L / 2 (shear spring at the bar's mid
    point, 002 eq 3, 4, 12); the generalised eigenvalues of that stiffness with
    mass diag(m, m R^2 / 2) stay below omega_max (0.92 omega_max), so dt* is the
    limit of the whole chain.  Random (zero-mean) velocities and spins at 0.95 and
    1.05 dt* must stay bounded and grow; ``critical_timestep`` (Gershgorin row
    sums, here set by the rotation of the inner discs) must lie in
    [0.7 dt*, 0.95 dt*] (measured 0.79).
    """
    n = 8
    state, config = _chain(n)
    m = float(state.particles.mass[0])
    inertia = float(state.particles.inertia[0])
    g = bond_geometry(state.bonds, state.particles, _params(2, 1e-6), 2)
    kn, ks, kb = float(g.kn[0]), float(g.ks[0]), float(g.kn[0] * g.I[0] / g.area[0])
    length = float(g.length[0])
    w_axial = 2 * np.sqrt(kn / m) * np.cos(np.pi / (2 * n))
    limit = 2 / w_axial
    # transverse-rotational stiffness of the free chain, dofs (y_0, theta_0, y_1, ...)
    k = np.zeros((2 * n, 2 * n))
    for i in range(n - 1):
        shear = np.zeros(2 * n)
        shear[[2 * i, 2 * i + 2]] = 1.0, -1.0
        shear[[2 * i + 1, 2 * i + 3]] = length / 2
        bend = np.zeros(2 * n)
        bend[[2 * i + 1, 2 * i + 3]] = 1.0, -1.0
        k += ks * np.outer(shear, shear) + kb * np.outer(bend, bend)
    inv_sqrt_m = 1 / np.sqrt(np.tile([m, inertia], n))
    w_trans = np.sqrt(np.max(np.linalg.eigvalsh(inv_sqrt_m[:, None] * k * inv_sqrt_m[None])))
    assert w_trans < 0.95 * w_axial
    rng = np.random.default_rng(0)
    vel = rng.standard_normal((n, 2))
    spin = rng.standard_normal(n) / R
    vel, spin = TINY * (vel - vel.mean(axis=0)), TINY * spin
    growth = {}
    for factor in (0.95, 1.05):
        _, energy = _stability_run(state, _params(2, factor * limit), config, vel, spin)
        growth[factor] = _growth(energy)
    assert growth[0.95] < 10
    assert growth[1.05] > 1e12
    crit = float(timestep.critical_timestep(state, _params(2, 1e-6), config))
    assert 0.7 * limit <= crit <= 0.95 * limit


# ------------------------------------------------------------------ contacts and the bound's form
# The systems above have R = 0.5 and bars of length 2R = 1, where a misplaced
# factor of R or L (x R vs / R) leaves the numbers unchanged; these use unequal
# radii away from 0.5 m and compare with the module docstring's bound term by term.
RA, RB = 0.02, 0.03                      # m
KN, KS = 2e7, 8e6                        # N/m, linear contact law


def _contact_pair(fixed_vel, fixed_rot, overlap=1e-4):
    """Two discs RA, RB touching with ``overlap`` along x (linear law)."""
    parts = jdem.make_particles(np.array([[0.0, 0.0], [RA + RB - overlap, 0.0]]), [RA, RB],
                                density=RHO, fixed_vel=fixed_vel, fixed_rot=fixed_rot)
    return jdem.make_state(parts)


def _contact_params(dt, **kw):
    return jdem.make_params(dim=2, dt=dt, kn=KN, ks=KS, friction=0.5, **kw)


@functools.partial(jax.jit, static_argnames=("config",))
def _spin_chunk(state, params, config):
    def body(s, _):
        s = integrate.step(s, params, config)
        p = s.particles
        return s, 0.5 * jnp.sum(p.inertia * p.angvel ** 2)

    return jax.lax.scan(body, state, None, length=CHUNK)[1]


def test_contact_pair_critical_step_unequal_discs():
    """Two discs of radii a = 0.02, b = 0.03 m on a linear contact (k_n, k_s).

    Rotation (both centres held, both free to spin): the shear spring stretches by
    u_s = a' th_a + b' th_b (a', b' the arms to the mid-overlap contact point,
    000 fig 4-4), so I th'' = -k_s (a', b')^T (a', b') th, one mode with
    omega^2 = k_s (a'^2 / I_a + b'^2 / I_b).  The centred step is stable below
    2 / omega: at 0.95 of it the spin energy stays bounded, at 1.05 it grows.
    ``critical_timestep`` is the docstring's bound, the smaller over the two discs
    of 2 / sqrt(2 k_s r (a + b) / I) (radius r, arm a + b), and lies below 2 / omega.

    Translation (disc a held in place, b free, spins held): the bound is
    2 / sqrt(2 (k_n + k_s) / m_b), with the contact dashpot c = 2 zeta sqrt(m* k_n)
    (m* the reduced mass) and viscous damping g in the damped form; the held disc
    a, lighter than b, is not counted.
    """
    held = np.ones((2, 2), bool)
    state, config = _contact_pair(held, np.array([False, False]))
    p = state.particles
    inertia = np.asarray(p.inertia)
    arm = np.array([RA, RB]) - 0.5e-4
    omega = np.sqrt(KS * np.sum(arm ** 2 / inertia))
    for factor, grows in ((0.95, False), (1.05, True)):
        spun = state._replace(particles=p._replace(angvel=jnp.array([1e-3, 0.0])))
        energy = np.asarray(_spin_chunk(spun, _contact_params(factor * 2 / omega), config))
        assert (np.max(energy[-50:]) / energy[0] > 1e6) == grows
    crit = float(timestep.critical_timestep(state, _contact_params(1e-9), config))
    bound = min(2 / np.sqrt(2 * KS * r * (RA + RB) / i_) for r, i_ in zip((RA, RB), inertia))
    assert crit == pytest.approx(bound, rel=1e-12)
    assert crit < 2 / omega

    state, config = _contact_pair(np.array([[True, True], [False, False]]), np.ones(2, bool))
    m = np.asarray(state.particles.mass)
    m_eff = m[0] * m[1] / (m[0] + m[1])
    for zeta, visc in ((0.0, 0.0), (0.4, 0.0), (0.4, 50.0)):
        prm = _contact_params(1e-9, contact_damping=zeta, viscous_damping=visc)
        crit = float(timestep.critical_timestep(state, prm, config))
        g = 2 * (2 * zeta * np.sqrt(m_eff * KN)) / m[1] + visc
        assert crit == pytest.approx(_damped_limit(2 * (KN + KS) / m[1], g), rel=1e-12)


@pytest.mark.parametrize("radius", [0.5, 0.3])
def test_bond_bound_counts_every_spring_and_dashpot(radius):
    """The bonded pair's bound term by term (module docstring): translation
    2 / sqrt(2 (K_n + K_s) / m) damped by 2 (c_n + c_s) / m + g, where both bar
    dashpots are c = 2 zeta sqrt(m* K); rotation (a disc held in place, free to
    spin) 2 / sqrt(2 (K_s L^2 / 4 + K_n I_b / A_c) / I), the shear spring at the
    bar's mid point and the bending spring (002 eq 4), damped by the shear
    dashpot at arm L / 2.  Radius 0.3 m makes L = 0.6 m, where L^2 and 1 / L^2
    differ."""
    pos = np.array([[0.0, 0.0], [2 * radius, 0.0]])
    # free: the bond's first particle or its second (each end's sums count)
    for free, spins in ((0, False), (1, False), (0, True), (1, True)):
        held = np.arange(2) != free
        fixed_vel = np.ones((2, 2), bool) if spins else np.repeat(held[:, None], 2, axis=1)
        fixed_rot = held if spins else np.ones(2, bool)
        parts = jdem.make_particles(pos, [radius] * 2, density=RHO, fixed_vel=fixed_vel,
                                    fixed_rot=fixed_rot)
        state, config = jdem.make_state(parts, bonds=create_bonds(parts, 2, gap_tolerance=1e-9))
        g = bond_geometry(state.bonds, state.particles, _params(2, 1e-6), 2)
        kn, ks, L = float(g.kn[0]), float(g.ks[0]), float(g.length[0])
        assert L == pytest.approx(2 * radius, rel=1e-12)
        m, inertia = float(parts.mass[free]), float(parts.inertia[free])
        zeta, visc = 0.3, 20.0
        cn, cs = (2 * zeta * np.sqrt(0.5 * m * k) for k in (kn, ks))
        crit = float(timestep.critical_timestep(
            state, _params(2, 1e-9, bond_damping=zeta, viscous_damping=visc), config))
        if not spins:
            expect = _damped_limit(2 * (kn + ks) / m, 2 * (cn + cs) / m + visc)
        else:
            k_rot = ks * L ** 2 / 4 + kn * float(g.I[0]) / float(g.area[0])
            expect = _damped_limit(2 * k_rot / inertia, 2 * cs * L ** 2 / 4 / inertia + visc)
        assert crit == pytest.approx(expect, rel=1e-12), (free, spins)


def test_a_sphere_spinning_on_a_bond_counts_the_twist_spring():
    """3D: a sphere held in place but free to spin, bonded to a held sphere
    (equal radii R, circular section of diameter 2R, 002 eq 5: A_c = pi R^2,
    I_b = pi R^4 / 4, J = 2 I_b).  Its rotational bound adds the twist spring to
    the 2D terms: 2 / sqrt(2 (K_s L^2 / 4 + (K_n I_b + K_s J) / A_c) / I)."""
    pos = np.array([[0.0, 0.0, 0.0], [2 * R, 0.0, 0.0]])
    parts = jdem.make_particles(pos, [R, R], density=RHO, fixed_vel=np.ones((2, 3), bool),
                                fixed_rot=np.array([[True] * 3, [False] * 3]))
    state, config = jdem.make_state(parts, bonds=create_bonds(parts, 3, gap_tolerance=1e-9))
    g = bond_geometry(state.bonds, state.particles, _params(3, 1e-6), 3)
    kn, ks, L = float(g.kn[0]), float(g.ks[0]), float(g.length[0])
    area, i_b = np.pi * R ** 2, np.pi * R ** 4 / 4
    np.testing.assert_allclose([float(g.area[0]), float(g.I[0]), float(g.J[0])],
                               [area, i_b, 2 * i_b], rtol=1e-12)
    k_rot = ks * L ** 2 / 4 + (kn * i_b + ks * 2 * i_b) / area
    crit = float(timestep.critical_timestep(state, _params(3, 1e-9), config))
    assert crit == pytest.approx(2 / np.sqrt(2 * k_rot / float(parts.inertia[1])), rel=1e-12)


def test_a_disc_spinning_against_a_wall_counts_the_wall_shear_spring():
    """A disc held in place, free to spin, pressed on a wall (linear law, overlap
    1e-4 m): the wall's shear spring at arm a' = r - overlap / 2 gives
    I theta'' = -k_s a'^2 theta, so the centred step is stable below
    2 / omega, omega^2 = k_s a'^2 / I: at 0.95 of it the spin energy stays bounded,
    at 1.05 it grows.  ``critical_timestep`` is the docstring's bound
    2 / sqrt(2 k_s r^2 / I) (arm r), below 2 / omega."""
    overlap = 1e-4
    parts = jdem.make_particles(np.array([[0.0, RA - overlap]]), [RA], density=RHO,
                                fixed_vel=np.ones((1, 2), bool), fixed_rot=np.array([False]))
    walls = jdem.make_walls([np.zeros(2)], [np.array([0.0, 1.0])], n_particles=1)
    state, config = jdem.make_state(parts, walls=walls)
    inertia = float(parts.inertia[0])
    omega = np.sqrt(KS * (RA - 0.5 * overlap) ** 2 / inertia)
    for factor, grows in ((0.95, False), (1.05, True)):
        p = state.particles
        spun = state._replace(particles=p._replace(angvel=jnp.array([1e-3])))
        energy = np.asarray(_spin_chunk(spun, _contact_params(factor * 2 / omega), config))
        assert (np.max(energy[-50:]) / energy[0] > 1e6) == grows
    crit = float(timestep.critical_timestep(state, _contact_params(1e-9), config))
    assert crit == pytest.approx(2 / np.sqrt(2 * KS * RA ** 2 / inertia), rel=1e-12)
    assert crit < 2 / omega


def _hex_lattice(radius, overlap_ratio, rows=5, cols=5):
    d = 2 * radius * (1 - 0.5 * overlap_ratio)           # centre spacing
    pos = np.array([[d * (c + 0.5 * (r % 2)), d * np.sqrt(3) / 2 * r]
                    for r in range(rows) for c in range(cols)])
    parts = jdem.make_particles(pos, np.full(len(pos), radius), density=RHO)
    return jdem.make_state(parts, contact_model="hertz")


def test_nominal_step_equals_the_step_of_a_lattice_with_that_coordination():
    """``nominal_critical_timestep`` assumes z like neighbours at an overlap of
    ``overlap_ratio`` R (Hertz).  A hexagonal lattice of discs R = 0.01 m at that
    overlap has z = 6 around its inner discs, which set its critical step: the
    two agree, with contact dashpots and viscous damping on."""
    radius, ratio = 0.01, 0.004
    state, config = _hex_lattice(radius, ratio)
    prm = jdem.make_params(dim=2, dt=1e-9, youngs=5e9, poisson=0.2)
    count = contact.contact_forces(state.contacts, state.particles, prm, config)[3]
    assert int(np.max(np.asarray(count))) == 6
    for zeta, visc in ((0.0, 0.0), (0.3, 100.0)):
        prm = jdem.make_params(dim=2, dt=1e-9, youngs=5e9, poisson=0.2,
                               contact_damping=zeta, viscous_damping=visc)
        crit = float(timestep.critical_timestep(state, prm, config))
        nominal = float(timestep.nominal_critical_timestep(
            state.particles, prm, config, coordination=6, overlap_ratio=ratio))
        assert nominal == pytest.approx(crit, rel=1e-9)


def test_the_step_limit_is_computed_without_the_search_grid():
    """``critical_timestep`` is compiled for ``Config.without_search_grid()`` (one
    program for every grid): the laws it evaluates read no search field, so the
    limit equals the one computed with the full configuration, and a list built
    on another grid gives the same limit."""
    state, config = _hex_lattice(0.01, 0.004)
    prm = jdem.make_params(dim=2, dt=1e-9, youngs=5e9, poisson=0.2, contact_damping=0.3)
    crit = float(timestep.critical_timestep(state, prm, config))
    assert crit == float(timestep._critical_and_touching(state, prm, config)[0])
    other = config.replace(skin=3 * config.skin, cell_size=config.cell_size + 2 * config.skin,
                           grid_origin=tuple(o - 0.01 for o in config.grid_origin))
    rebuilt = state._replace(contacts=jdem.neighbors.build(state.contacts, state.particles, other))
    assert float(timestep.critical_timestep(rebuilt, prm, other)) == crit


def test_check_timestep_without_contacts_uses_the_nominal_step():
    """Before anything touches, the critical step is infinite; ``check_timestep``
    then refuses a step above the nominal one, and accepts one below it."""
    parts = jdem.make_particles(np.array([[0.0, 0.0], [1.0, 0.0]]), [0.01, 0.01], density=RHO)
    state, config = jdem.make_state(parts)
    prm = _contact_params(1e-9)
    nominal = float(timestep.nominal_critical_timestep(state.particles, prm, config))
    assert np.isfinite(nominal)
    timestep.check_timestep(state, prm._replace(dt=jnp.asarray(0.9 * nominal)), config)
    timestep.check_timestep(state, prm._replace(dt=jnp.asarray(nominal)), config)  # "at most"
    with pytest.raises(jdem.InputError, match="params.dt"):
        timestep.check_timestep(state, prm._replace(dt=jnp.asarray(1.1 * nominal)), config)


def test_nominal_step_assumes_four_neighbours_in_2d_and_six_in_3d():
    """The default coordination of ``nominal_critical_timestep``: 4 discs, 6 spheres."""
    for dim, z, other in ((2, 4, 6), (3, 6, 4)):
        parts = jdem.make_particles(np.zeros((1, dim)), [0.01], density=RHO)
        _, config = jdem.make_state(parts)
        prm = jdem.make_params(dim=dim, dt=1e-9, kn=KN, ks=KS)
        step = lambda **kw: float(timestep.nominal_critical_timestep(parts, prm, config, **kw))
        assert step() == step(coordination=z)
        assert step() != pytest.approx(step(coordination=other), rel=1e-3)


def test_a_free_disc_under_viscous_damping_is_stable_below_two_over_c():
    """A disc touching nothing, spinning, with viscous damping c [1/s]: the step
    gives w+ = (1 - dt c) w-, stable for dt < 2 / c (the dashpot alone).  At 0.95
    of it the spin energy decays, at 1.05 it grows; ``critical_timestep`` is
    2 / c.  ``check_timestep`` still guards the contacts to come with the nominal
    step (which counts c as well)."""
    parts = jdem.make_particles(np.zeros((1, 2)), [RA], density=RHO)
    state, config = jdem.make_state(parts)
    spun = state._replace(particles=state.particles._replace(angvel=jnp.array([1e-3])))
    c = 1e4
    for factor, grows in ((0.95, False), (1.05, True)):
        energy = np.asarray(_spin_chunk(spun, _contact_params(factor * 2 / c, viscous_damping=c),
                                        config))
        assert (np.max(energy[-50:]) / energy[0] > 1e6) == grows
        assert (energy[-1] < energy[0]) != grows
    crit = float(timestep.critical_timestep(state, _contact_params(1e-9, viscous_damping=c),
                                            config))
    assert crit == pytest.approx(2 / c, rel=1e-12)
    assert np.isinf(float(timestep.critical_timestep(state, _contact_params(1e-9), config)))
    # weak damping: 2 / c lies far above the nominal step, which still rules
    prm = _contact_params(1e-9, viscous_damping=1e-2 / float(
        timestep.nominal_critical_timestep(state.particles, _contact_params(1e-9), config)))
    nominal = float(timestep.nominal_critical_timestep(state.particles, prm, config))
    assert 2 / float(prm.viscous_damping) > 100 * nominal
    timestep.check_timestep(state, prm._replace(dt=jnp.asarray(0.99 * nominal)), config)
    with pytest.raises(jdem.InputError, match="params.dt"):
        timestep.check_timestep(state, prm._replace(dt=jnp.asarray(1.01 * nominal)), config)


@pytest.mark.parametrize("uniform", [False, True])
def test_scale_density_makes_the_target_step_stable_with_its_margin(uniform):
    """000 §3.3.2: after scaling, the critical step of every disc that needed more
    mass is exactly target / safety (the bound goes as sqrt(m)), for translation
    and rotation alike; the weight keeps the true mass.  Unequal discs of a
    lattice whose rotation limits are tighter than their translation ones for
    some discs and looser for others."""
    state, config = _hex_lattice(0.01, 0.004)
    p = state.particles
    rng = np.random.default_rng(3)
    spread = jnp.asarray(rng.uniform(0.3, 3.0, p.mass.shape))
    state = state._replace(particles=p._replace(inertia=p.inertia * spread))
    prm = jdem.make_params(dim=2, dt=1e-9, youngs=5e9, poisson=0.2)
    crit = float(timestep.critical_timestep(state, prm, config))
    target, safety = 3 * crit, 0.8
    scaled = timestep.scale_density(state, prm, config, target, safety=safety, uniform=uniform)
    after = float(timestep.critical_timestep(scaled, prm, config))
    assert after == pytest.approx(target / safety, rel=1e-9)
    ratio = np.asarray(scaled.particles.mass / state.particles.mass)
    np.testing.assert_allclose(np.asarray(scaled.particles.inertia / state.particles.inertia),
                               ratio, rtol=1e-12)
    assert np.all(ratio >= 1)
    if uniform:
        np.testing.assert_allclose(ratio, ratio[0], rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(scaled.particles.gravity_mass),
                                  np.asarray(state.particles.gravity_mass))
