"""Tangential contact law with particle spin against analytic rigid-body results
(000 §4.2: incremental tangential spring eq 4-3 with the Coulomb limit, relative
contact velocity with spin eq 4-11..4-15, Hertz-Mindlin eq 4-6 / 4-8, mixing of
unlike particles eq 4-9).

A moving disc (2D) or sphere (3D) of radius ``R`` meets one of three surfaces,
all with their top at y = 0 and outward normal +y:

* ``wall``: a rigid plane (:mod:`jdem.walls`);
* ``particle_j``: a fixed particle of radius ``R_BIG`` = 10,000 R in row 0, the
  moving one in row 1 (it is j of the pair i < j);
* ``particle_i``: the same with the rows swapped (the moving one is i).

The fixed particle is so large that its surface is flat over the distances
travelled here (a curvature of 1 / R_BIG tilts the normal by less than 3e-5).
Both pair orders are run because the two sides of a pair have their own lever
arm and spin in the relative velocity; a spinning particle is needed on each
side to see either.

The contact point sits in the middle of the overlap, at ``a = R - overlap / 2``
below the centre: its velocity is ``v + w x arm`` with ``arm = -a e_y``.
"""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdem
from jdem import contact, integrate

R = 0.01          # radius of the moving particle [m]
RHO = 2500.0      # [kg/m^3]
R_BIG = 1.0e4 * R  # radius of the fixed particle [m]
W = 1.0e4         # normal frequency sqrt(k_n / m) of the moving particle on the surface [rad/s]
G = 9.81          # [m/s^2]
BODIES = ("wall", "particle_j", "particle_i")
BLOCK = 10        # steps between records


def _tol(body, wall, particle):
    """Tolerance of a comparison: on the fixed particle it also covers its
    curvature (the normal turns by the distance travelled / R_BIG)."""
    return wall if body == "wall" else particle


def _mass(dim):
    return RHO * (np.pi * R**2 if dim == 2 else 4.0 / 3.0 * np.pi * R**3)


def _kappa(dim):
    """I / (m R^2): 1/2 for a disc, 2/5 for a sphere."""
    return 0.5 if dim == 2 else 0.4


def _kn(dim):
    return _mass(dim) * W**2


def _up(dim):
    return np.eye(dim)[1]


def _tangent(dim):
    """Unit direction of the tangential motion: x in 2D, oblique in the x-z plane in 3D."""
    if dim == 2:
        return np.array([1.0, 0.0])
    phi = np.deg2rad(30.0)
    return np.array([np.cos(phi), 0.0, np.sin(phi)])


def _as3(v):
    v = np.asarray(v, dtype=float)
    return np.array([v[0], v[1], 0.0]) if v.shape == (2,) else v


def _spin3(w):
    """A spin as a 3-vector (2D: about z)."""
    w = np.asarray(w, dtype=float)
    return np.array([0.0, 0.0, float(w)]) if w.ndim == 0 else w


def _spin_like(w3, dim):
    return w3[2] if dim == 2 else w3


def _slip(vel, spin, a):
    """Velocity (3-vector) of the contact point at ``-a e_y`` below the centre."""
    return _as3(vel) + np.cross(_spin3(spin), np.array([0.0, -a, 0.0]))


def _observe(state, params, config):
    p = state.particles
    return dict(t=state.time, pos=p.pos, vel=p.vel, angvel=p.angvel)


@functools.partial(jax.jit, static_argnums=(2, 3))
def _block(state, params, config, every):
    """``every`` steps, then the observation (one compiled program per set-up)."""
    state, _ = jax.lax.scan(lambda s, _: (integrate.step(s, params, config), None), state,
                            None, length=every)
    return state, _observe(state, params, config)


def _run(state, params, config, n_records, every, k=None):
    """Run ``n_records`` blocks of ``every`` steps; the history of row ``k`` (all
    rows if None), NumPy arrays along the records."""
    records = []
    for _ in range(n_records):
        state, obs = _block(state, params, config, every)
        records.append(obs)
    hist = {key: np.stack([np.asarray(r[key]) for r in records]) for key in records[0]}
    if k is not None:
        for key in ("pos", "vel", "angvel"):
            hist[key] = hist[key][:, k]
    return hist


def _particles(dim, body, *, y, vel, spin, material, surface_material, fixed_rot=False):
    """Particles (and walls) of one set-up; returns ``(particles, walls, k)`` with
    ``k`` the row of the moving particle."""
    up = _up(dim)
    centre = y * up
    spin = np.asarray(spin, dtype=float)
    rot_shape = () if dim == 2 else (3,)
    if body == "wall":
        p = jdem.make_particles([centre], [R], density=RHO, vel=[vel], angvel=[spin],
                                material=[material],
                                fixed_rot=[np.full(rot_shape, fixed_rot)])
        walls = jdem.make_walls([np.zeros(dim)], [up], n_particles=1,
                                material=[surface_material])
        return p, walls, 0
    rows = [-R_BIG * up, centre]
    vels = [np.zeros(dim), vel]
    spins = [np.zeros(rot_shape), spin]
    mats = [surface_material, material]
    fixed_v = [np.ones(dim, bool), np.zeros(dim, bool)]
    fixed_w = [np.ones(rot_shape, bool), np.full(rot_shape, fixed_rot)]
    order = [0, 1] if body == "particle_j" else [1, 0]
    pick = lambda seq: [seq[o] for o in order]  # noqa: E731
    p = jdem.make_particles(pick(rows), pick([R_BIG, R]), density=RHO, vel=pick(vels),
                            angvel=pick(spins), material=pick(mats), fixed_vel=pick(fixed_v),
                            fixed_rot=pick(fixed_w))
    return p, None, order.index(1)


@functools.lru_cache(maxsize=None)
def _config(dim, body, model):
    """One Config per set-up (a template position), so that the runs of a set-up
    share one compiled program."""
    p, _, _ = _particles(dim, body, y=R, vel=np.zeros(dim), spin=np.zeros(() if dim == 2 else 3),
                         material=0, surface_material=0)
    return jdem.make_config(p, contact_model=model, skin=0.5 * R)


def _state(dim, body, *, y, vel, spin, material=0, surface_material=0, model="linear",
           fixed_rot=False):
    p, walls, k = _particles(dim, body, y=y, vel=vel, spin=spin, material=material,
                             surface_material=surface_material, fixed_rot=fixed_rot)
    state, cfg = jdem.make_state(p, _config(dim, body, model), walls=walls)
    return state, cfg, k


def _params(dim, *, kt_over_kn=1.0, friction=0.5, dt, gravity=False, **kw):
    kn = _kn(dim)
    grav = -G * _up(dim) if gravity else np.zeros(dim)
    fr = np.broadcast_to(np.asarray(friction, dtype=float), (2,))
    return jdem.make_params(dim=dim, n_materials=2, kn=kn, ks=kt_over_kn * kn, friction=fr,
                            dt=dt, gravity=grav, **kw)


# --------------------------------------------------------------------------- impacts
IMPACT_DT = 0.005 / W      # 628 steps per contact (duration pi / W)
IMPACT_STEPS = 720         # 2 steps of approach, the contact, and some free flight
IMPACT_VT, IMPACT_VN = 0.5, 0.2  # tangential and normal impact speeds [m/s]


def _impact(dim, body, params, material=0, surface_material=0, mixing=None):
    """An oblique impact without initial spin; returns (final velocity, final spin,
    final height of the centre) of the moving particle.  ``mixing``: the
    ``Config.friction_mixing`` (default: the default rule)."""
    vel = IMPACT_VT * _tangent(dim) - IMPACT_VN * _up(dim)
    gap = 2.5 * IMPACT_VN * IMPACT_DT
    spin = np.zeros(() if dim == 2 else 3)
    state, cfg, k = _state(dim, body, y=R + gap, vel=vel, spin=spin, material=material,
                           surface_material=surface_material)
    if mixing is not None:
        cfg = cfg.replace(friction_mixing=mixing)
    h = _run(state, params, cfg, IMPACT_STEPS // BLOCK, BLOCK, k)
    return h["vel"][-1], h["angvel"][-1], h["pos"][-1][1]


def _check_sliding_impact(dim, mu, vel, spin, height):
    """Analytic gross-sliding impact, see test_oblique_impact_gross_sliding."""
    m, kap = _mass(dim), _kappa(dim)
    up, t_hat = _as3(_up(dim)), _as3(_tangent(dim))
    assert height > R  # the contact is over
    v3 = _as3(vel)
    dvn = v3 @ up + IMPACT_VN
    restitution = (v3 @ up) / IMPACT_VN
    assert abs(restitution - 1.0) < 2e-5
    dvt = v3 - (v3 @ up) * up - IMPACT_VT * t_hat
    err_t = np.linalg.norm(dvt + mu * dvn * t_hat) / (mu * dvn)
    a_eff = R - np.pi / 8.0 * IMPACT_VN / W
    j = -mu * m * dvn * t_hat  # tangential impulse on the particle
    w_expected = np.cross(np.array([0.0, -a_eff, 0.0]), j) / (kap * m * R**2)
    err_w = np.linalg.norm(_spin3(spin) - w_expected) / np.linalg.norm(w_expected)
    # the contact point still slips forward at the end: the sliding assumption held
    assert _slip(vel, spin, R) @ t_hat > 0.3 * IMPACT_VT
    return err_t, err_w


@pytest.mark.parametrize("body", BODIES)
@pytest.mark.parametrize("dim", [2, 3])
def test_oblique_impact_gross_sliding(dim, body):
    """Oblique impact with gross sliding over the whole contact.

    While sliding, the tangential force is mu F_n at every step, opposing the
    slip, so the impulses obey J_t = mu J_n:  dv_t = -mu dv_n t_hat, with
    dv_n = (1 + e) v_n and e = 1 (undamped linear spring).  The spin gained is
    dw = (arm x J_t) / I, I = m R^2 / 2 (disc) or 2/5 m R^2 (sphere), with the
    lever arm a = R - overlap / 2 averaged over the half-sine normal force:
    a_eff = R - (pi / 8) overlap_max, overlap_max = v_n / W.

    mu = 0.2 keeps the contact sliding: the slip falls by mu dv_n (1 + m R^2 / I)
    = 0.24 (disc) / 0.28 (sphere) of the initial 0.5 m/s.
    Tolerances, relative: J_t / J_n 1e-12 on the wall (it holds step by step);
    1e-5 on the fixed particle, whose normal turns by up to v_t t_c / R_BIG =
    1.6e-6 rad during the contact, which tilts J_n by 0.8e-6 on average, 4e-6
    of mu; the spin 1e-6 (terms of second order in overlap / R = 2e-3, the time
    step and, on the particle, the curvature); e = 1 within 2e-5.
    """
    mu = 0.2
    params = _params(dim, friction=mu, dt=IMPACT_DT)
    err_t, err_w = _check_sliding_impact(dim, mu, *_impact(dim, body, params))
    assert err_t < _tol(body, 1e-12, 1e-5)
    assert err_w < 1e-6


@pytest.mark.parametrize("body", BODIES)
@pytest.mark.parametrize("dim", [2, 3])
def test_oblique_impact_sticking_reverses_slip(dim, body):
    """Oblique impact that sticks throughout: tangential compliance reverses the slip.

    With no sliding the contact point is a linear tangential oscillator of
    stiffness k_t and reduced mass m_t, 1/m_t = 1/m + R^2/I (translation plus
    rolling), started from zero spring force at the slip speed v_t.  With
    k_t / k_n = m_t / m (= 1/3 disc, 2/7 sphere) its frequency equals the normal
    one W, so over the contact (half a normal period) the slip is reversed:
    s_end = -v_t.  The impulse J_t = -2 m_t v_t t_hat gives
    v_t,end = v_t (1 - kappa) / (1 + kappa) (1/3 disc, 3/7 sphere; kappa = I / m R^2)
    and w_end = (arm x J_t) / I.  The spring force stays below the Coulomb limit:
    both F_t = k_t v_t sin(W t) / W and F_n = k_n v_n sin(W t) / W, so
    F_t / F_n = (k_t v_t) / (k_n v_n) is a constant 0.83 (disc) / 0.71 (sphere),
    and mu = twice that is used.

    Without the spin term the oscillator frequency is sqrt(k_t / m), W / sqrt(3),
    and the slip ends at cos(pi / sqrt 3) v_t = -0.24 v_t.
    Tolerance 2e-3 of v_t: the overlap (2e-3 R) changes the lever arm and m_t.
    """
    kap = _kappa(dim)
    ratio = kap / (1.0 + kap)  # m_t / m
    mu = 2.0 * ratio * IMPACT_VT / IMPACT_VN
    params = _params(dim, kt_over_kn=ratio, friction=mu, dt=IMPACT_DT)
    vel, spin, height = _impact(dim, body, params)
    assert height > R
    m = _mass(dim)
    t_hat, up = _as3(_tangent(dim)), _as3(_up(dim))
    v3 = _as3(vel)
    vt_end = v3 - (v3 @ up) * up
    expected_v = IMPACT_VT * (1.0 - kap) / (1.0 + kap) * t_hat
    j = -2.0 * ratio * m * IMPACT_VT * t_hat
    expected_w = np.cross(np.array([0.0, -R, 0.0]), j) / (kap * m * R**2)
    assert np.linalg.norm(vt_end - expected_v) / IMPACT_VT < 2e-3
    assert np.linalg.norm(_spin3(spin) - expected_w) * R / IMPACT_VT < 2e-3
    slip_end = _slip(vel, spin, R)
    slip_end = slip_end - (slip_end @ up) * up
    assert np.linalg.norm(slip_end + IMPACT_VT * t_hat) / IMPACT_VT < 2e-3


@pytest.mark.parametrize("body", BODIES)
@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_unlike_friction_is_the_smaller_coefficient(order, body):
    """Friction of unlike materials is the smaller coefficient (contact module
    docstring), for particle pairs in both orders and for walls: a sliding
    impact of a material with mu = 0.4 on one with mu = 0.1 gives J_t / J_n = 0.1
    (the rule and tolerances of test_oblique_impact_gross_sliding); the mean
    would give 0.25."""
    mover, surface = order
    params = _params(2, friction=[0.1, 0.4], dt=IMPACT_DT)
    err_t, err_w = _check_sliding_impact(2, 0.1, *_impact(2, body, params, mover, surface))
    assert err_t < _tol(body, 1e-12, 2e-5)
    assert err_w < 1e-6


@pytest.mark.parametrize("body", BODIES)
@pytest.mark.parametrize("mixing, mu", [("mean", 0.25), ("geometric", 0.2),
                                        (((0.1, 0.15), (0.15, 0.4)), 0.15)])
def test_friction_mixing_rule_can_be_chosen(mixing, mu, body):
    """``Config.friction_mixing``: the same sliding impact of mu = 0.4 on
    mu = 0.1 gives J_t / J_n = the mean 0.25, the geometric mean 0.2, or the
    pair's entry 0.15 of a table (walls through their material index)."""
    params = _params(2, friction=[0.1, 0.4], dt=IMPACT_DT)
    err_t, err_w = _check_sliding_impact(2, mu, *_impact(2, body, params, 0, 1, mixing=mixing))
    assert err_t < _tol(body, 1e-12, 2e-5)
    assert err_w < 1e-6


def test_friction_mixing_is_checked(tmp_path):
    import jdem.io

    cfg = jdem.Config()
    with pytest.raises(jdem.InputError, match="friction_mixing"):
        cfg.replace(friction_mixing="largest")
    with pytest.raises(jdem.InputError, match="symmetric"):
        cfg.replace(friction_mixing=((0.1, 0.2), (0.3, 0.4)))
    with pytest.raises(jdem.InputError, match="square"):
        cfg.replace(friction_mixing=((0.1, 0.2),))
    assert cfg.replace(friction_mixing=[[0.5]]).friction_mixing == ((0.5,),)   # hashable
    table = cfg.replace(friction_mixing=((0.1, 0.2), (0.2, 0.3)))
    jdem.io.save_run(tmp_path / "c.h5", config=table)
    assert jdem.io.load_run(tmp_path / "c.h5").config == table                  # round trip
    p = jdem.make_particles([[0.0, 0.0], [1.5, 0.0]], [1.0, 1.0])
    state, config = jdem.make_state(p)
    params = jdem.make_params(dim=2, n_materials=2, dt=1e-3)
    with pytest.raises(jdem.InputError, match="table"):
        jdem.advance(state, params, config.replace(friction_mixing=((0.5,),)), 1)


# --------------------------------------------------------------------------- rolling
ROLL_DT = 0.05 / W
ROLL_MU = 0.5
ROLL_RECORDS = 560  # 5,600 steps = 0.028 s, about 4 times the sliding phase
ROLL_V0 = 0.1       # [m/s]


def _roll_start(dim, start):
    """Initial (velocity, spin) of a rolling test, with the contact at a = R - g / (2 W^2)."""
    a = R - 0.5 * G / W**2
    t_hat = _tangent(dim)
    if start == "slide":
        return ROLL_V0 * t_hat, np.zeros(() if dim == 2 else 3)
    if start == "spin":  # no translation; contact-point slip of 0.1 m/s, plus a twist in 3D
        spin = np.array(10.0) if dim == 2 else np.array([6.0, 4.0, -8.0])
        return np.zeros(dim), spin
    # pure rolling: v + w x arm = 0, plus a twist about the normal in 3D
    w3 = np.cross(np.array([0.0, 1.0, 0.0]), _as3(ROLL_V0 * t_hat)) / a
    if dim == 3:
        w3 = w3 + np.array([0.0, 3.0, 0.0])
    return ROLL_V0 * t_hat, _spin_like(w3, dim)


@functools.lru_cache(maxsize=None)
def _roll(dim, body, start):
    """A particle on the surface under gravity at its static overlap m g / k_n."""
    vel, spin = _roll_start(dim, start)
    state, cfg, k = _state(dim, body, y=R - G / W**2, vel=vel, spin=spin)
    params = _params(dim, friction=ROLL_MU, dt=ROLL_DT, gravity=True)
    return _run(state, params, cfg, ROLL_RECORDS, BLOCK, k)


def _rolling_prediction(dim, start):
    """Sliding phase and final rolling state on a plane (see test_sliding_to_rolling)."""
    m, kap = _mass(dim), _kappa(dim)
    a = R - 0.5 * G / W**2
    kap_a = kap * R**2 / a**2  # I / (m a^2)
    vel, spin = _roll_start(dim, start)
    arm = np.array([0.0, -a, 0.0])
    s0 = _slip(vel, spin, a)
    speed = np.linalg.norm(s0)
    s_hat = s0 / speed if speed > 0 else np.zeros(3)
    t_star = speed / (ROLL_MU * G * (1.0 + 1.0 / kap_a))
    j = -s0 * kap_a / (1.0 + kap_a) * m  # friction impulse that stops the slip
    v_end = _as3(vel) + j / m
    w_end = _spin3(spin) + np.cross(arm, j) / (kap * m * R**2)
    return dict(arm=arm, s_hat=s_hat, t_star=t_star, v_end=v_end, w_end=w_end,
                v0=_as3(vel), w0=_spin3(spin))


@pytest.mark.parametrize("body", BODIES)
@pytest.mark.parametrize("dim", [2, 3])
def test_friction_opposes_slip_from_spin(dim, body):
    """A particle spinning in place on the surface, no translation: the slip of
    the contact point comes from the spin alone, s0 = w0 x arm, and gross
    sliding friction mu m g acts against it.  During the sliding phase
    (t < t* = |s0| / (mu g (1 + m a^2 / I))):

        v(t) = -mu g t s_hat,   w(t) = w0 + (arm x (-mu m g s_hat)) / I t,

    and the 3D spin about the normal (4 rad/s) is left alone (no twisting
    resistance).  Dropping the spin term leaves no slip and no friction.
    The spring reaches the Coulomb limit within the first step and the normal
    force stays m g, so on the wall this holds to rounding (tolerance 1e-9 of
    mu g t).  On the fixed particle the normal turns by the distance slid /
    R_BIG < 1e-6 rad, which tilts m g by 2e-6 of mu m g (tolerance 5e-6).
    """
    h = _roll(dim, body, "spin")
    pr = _rolling_prediction(dim, "spin")
    m, kap = _mass(dim), _kappa(dim)
    sliding = h["t"] < 0.9 * pr["t_star"]
    assert sliding.sum() > 50
    t = h["t"][sliding][:, None]
    friction = -ROLL_MU * m * G * pr["s_hat"]
    v_expected = friction / m * t
    w_expected = pr["w0"] + np.cross(pr["arm"], friction) / (kap * m * R**2) * t
    v = np.array([_as3(x) for x in h["vel"][sliding]])
    w = np.array([_spin3(x) for x in h["angvel"][sliding]])
    scale = ROLL_MU * G * t.max()
    tol = _tol(body, 1e-9, 5e-6)
    assert np.abs(v - v_expected).max() / scale < tol
    assert np.abs(w - w_expected).max() * R / scale < tol
    # the velocity gained points against the initial slip of the contact point
    assert np.all(v @ pr["s_hat"] < 0)


@pytest.mark.parametrize("start", ["slide", "spin", "roll"])
@pytest.mark.parametrize("body", BODIES)
@pytest.mark.parametrize("dim", [2, 3])
def test_sliding_to_rolling(dim, body, start):
    """Sliding friction turns sliding into rolling (the classic billiard-ball result).

    Friction acts at the contact point, so the angular momentum about it,
    I w + m (-arm) x v, is conserved; the slip s = v + w x arm falls along
    its own direction until s = 0.  The friction impulse is
    J = -s0 kappa / (1 + kappa) m (kappa = I / m a^2), hence

        v_end = v0 - s0 kappa / (1 + kappa),   w_end = w0 + (arm x J) / I:

    ``slide`` (v0, no spin): v_end = v0 / (1 + kappa) = 2/3 v0 (disc), 5/7 v0 (sphere);
    ``spin`` (spin only): v_end = -(w0 x arm) kappa / (1 + kappa), i.e. -1/3 (disc)
    and -2/7 (sphere) of the initial slip;
    ``roll`` (v0 = -w0 x arm): no slip, nothing changes.
    The spin about the normal (3D) is kept.  Compared: the velocity and spin
    averaged over [2 t*, 4 t*] (after sticking the elastic tangential spring
    rings at sqrt(1 + m a^2 / I) W, sqrt(3) W for a disc, with a velocity
    amplitude of about mu g / (sqrt(3) W), 3e-3 of the slip; the average over
    some 35 periods leaves < 1e-4 of it, and sticking sets in within a step).
    Tolerance 3e-4 of the initial slip.
    ``roll`` keeps v0 and w0 at every record to 1e-9 on the wall; on the fixed
    particle the velocity follows the curved surface, v_y = -v0^2 t / R_BIG
    (2.8e-5 of v0 at the end), tolerance 1e-4.
    """
    h = _roll(dim, body, start)
    pr = _rolling_prediction(dim, start)
    if start == "roll":
        v = np.array([_as3(x) for x in h["vel"]])
        w = np.array([_spin3(x) for x in h["angvel"]])
        tol = _tol(body, 1e-9, 1e-4)
        assert np.abs(v - pr["v0"]).max() / ROLL_V0 < tol
        assert np.abs(w - pr["w0"]).max() * R / ROLL_V0 < tol
        return
    t_star = pr["t_star"]
    assert h["t"][-1] > 3.9 * t_star
    window = (h["t"] > 2 * t_star) & (h["t"] < 4 * t_star)
    v = np.array([_as3(x) for x in h["vel"][window]]).mean(axis=0)
    w = np.array([_spin3(x) for x in h["angvel"][window]]).mean(axis=0)
    s0 = ROLL_V0
    assert np.linalg.norm(v - pr["v_end"]) / s0 < 3e-4
    assert np.linalg.norm(w - pr["w_end"]) * R / s0 < 3e-4
    assert np.linalg.norm(_slip(v, _spin_like(w, dim), R - 0.5 * G / W**2)) / s0 < 3e-4


# --------------------------------------------------------------------------- Hertz-Mindlin
HERTZ_E = (1.0e9, 3.0e9)   # Young's moduli of material 0 (particle) and 1 (surface)
HERTZ_NU = (0.1, 0.4)      # Poisson ratios
HERTZ_STEPS = 4000


def _hertz_frequency_prediction(body, fixed_rot):
    """Static overlap under m g and the tangential frequency of 000 eq 4-6 with
    the Mindlin stiffness, for unlike materials."""
    m, kap = _mass(3), _kappa(3)
    e = 2 * HERTZ_E[0] * HERTZ_E[1] / (HERTZ_E[0] + HERTZ_E[1])  # harmonic mean
    nu = 0.5 * (HERTZ_NU[0] + HERTZ_NU[1])                        # mean
    r_eff = R if body == "wall" else R * R_BIG / (R + R_BIG)
    h = 2 * e / (3 * (1 - nu**2)) * np.sqrt(r_eff)
    overlap = (m * G / h) ** (2 / 3)
    # Mindlin: k_t / k_n = 2 (1 - nu) / (2 - nu), k_n = dF_n / d overlap = 1.5 h sqrt(overlap)
    kt = 2 * (1 - nu) / (2 - nu) * 1.5 * h * np.sqrt(overlap)
    a = R - 0.5 * overlap
    inv_mass = 1 / m if fixed_rot else 1 / m + a**2 / (kap * m * R**2)
    return overlap, kt, np.sqrt(kt * inv_mass)


@pytest.mark.parametrize("fixed_rot", [False, True], ids=["rolling", "no_rotation"])
@pytest.mark.parametrize("body", BODIES)
def test_hertz_mindlin_tangential_oscillation(body, fixed_rot):
    """A sphere resting under gravity at its Hertz static overlap
    (m g = H overlap^(3/2), H = 2 E / (3 (1 - nu^2)) sqrt(R*), 000 eq 4-6), nudged
    sideways by v0 = 1e-4 m/s, oscillates on the tangential spring without
    sliding.  Mindlin's no-slip stiffness k_t = 2 (1 - nu) / (2 - nu) k_n with
    k_n = dF_n / d overlap gives the angular frequency

        w = sqrt(k_t / m)                      (rotation fixed)
        w = sqrt(k_t (1/m + a^2 / I))          (free to roll; sqrt(3.5) times higher)

    Unlike materials (E = 1, 3 GPa; nu = 0.1, 0.4): E mixed by the harmonic mean
    (000 eq 4-9), nu by the mean (contact module docstring); with the smaller or
    harmonic-mean nu the frequency would differ by 3 % / 2 %.
    The central-difference scheme turns w into w_d = (2 / dt) arcsin(w dt / 2)
    ((w dt)^2 / 24 = 4e-5 lower here); the period 2 pi / w_d is compared with the
    one measured over the zero crossings of the contact-point slip, tolerance 1e-5.
    """
    overlap, kt, omega = _hertz_frequency_prediction(body, fixed_rot)
    dt = 2 * np.pi / _hertz_frequency_prediction(body, False)[2] / 200
    v0 = 1e-4
    spin = np.zeros(3)
    state, cfg, k = _state(3, body, y=R - overlap, vel=[v0, 0.0, 0.0], spin=spin, material=0,
                           surface_material=1, model="hertz", fixed_rot=fixed_rot)
    params = _params(3, friction=0.5, dt=dt, gravity=True, youngs=list(HERTZ_E),
                     poisson=list(HERTZ_NU))
    h = _run(state, params, cfg, HERTZ_STEPS // BLOCK, BLOCK, k)
    # slip of the contact point (velocities and spins are both half-step values)
    slip = np.array([_slip(v, w, R - 0.5 * overlap)[0] for v, w in zip(h["vel"], h["angvel"])])
    t = h["t"] - 0.5 * dt
    assert np.abs(h["vel"][:, 1]).max() < 1e-9  # the normal stays at rest
    # the spring force stays within its Coulomb limit: no sliding
    assert kt * v0 / omega < 0.5 * 0.5 * _mass(3) * G
    cross = np.nonzero(np.sign(slip[1:]) != np.sign(slip[:-1]))[0]
    tc = t[cross] - slip[cross] * (t[cross + 1] - t[cross]) / (slip[cross + 1] - slip[cross])
    assert len(tc) >= 8
    period = 2 * (tc[-1] - tc[0]) / (len(tc) - 1)
    omega_d = 2 / dt * np.arcsin(0.5 * omega * dt)
    assert abs(period * omega_d / (2 * np.pi) - 1) < 1e-5
    assert abs(np.abs(slip).max() / v0 - 1) < 1e-3  # undamped: the amplitude stays v0


def test_hertz_mixing_of_unlike_materials():
    """000 eq 4-6 / 4-8 for unlike materials, both orders of the pair: E by the
    harmonic mean (eq 4-9), nu by the mean, friction by the smaller coefficient;
    like materials keep their own values.  Exact to rounding (rtol 1e-12)."""
    params = jdem.make_params(dim=3, n_materials=3, youngs=[1e9, 3e9, 2e9],
                              poisson=[0.1, 0.4, 0.3], friction=[0.2, 0.6, 0.4])
    mat_a = jnp.asarray([0, 1, 0, 2, 1, 2])
    mat_b = jnp.asarray([1, 0, 0, 1, 2, 2])
    overlap, r_eff = 3e-5, 0.004
    fn, kn, kt = contact.normal_law(jnp.full(6, overlap), jnp.full(6, r_eff), mat_a, mat_b,
                                    params, "hertz")
    mu = contact.pair_property(params.friction, mat_a, mat_b, jnp.minimum)
    ea, eb = np.asarray(params.youngs)[mat_a], np.asarray(params.youngs)[mat_b]
    nua, nub = np.asarray(params.poisson)[mat_a], np.asarray(params.poisson)[mat_b]
    e = 2 * ea * eb / (ea + eb)
    nu = 0.5 * (nua + nub)
    h = 2 * e / (3 * (1 - nu**2)) * np.sqrt(r_eff)
    np.testing.assert_allclose(fn, h * overlap**1.5, rtol=1e-12)
    np.testing.assert_allclose(kn, 1.5 * h * np.sqrt(overlap), rtol=1e-12)
    # Mindlin, written from the shear modulus G = E / (2 (1 + nu)) of two like halves:
    # k_t = 4 G a / (2 - nu), a = sqrt(R* overlap) (= 2 (1 - nu) / (2 - nu) k_n)
    g = e / (2 * (1 + nu))
    np.testing.assert_allclose(kt, 4 * g * np.sqrt(r_eff * overlap) / (2 - nu), rtol=1e-12)
    fr = np.asarray(params.friction)
    np.testing.assert_allclose(mu, np.minimum(fr[mat_a], fr[mat_b]), rtol=0)
    np.testing.assert_allclose(mu, [0.2, 0.2, 0.2, 0.4, 0.4, 0.4], rtol=0)
    assert np.isclose(float(e[0]), 1.5e9) and np.isclose(float(nu[0]), 0.25)


# --------------------------------------------------------------------------- dashpot
def _restitution_no_tension(zeta):
    """Restitution of a linear spring-dashpot whose force may not pull.

    m x'' = -k x - c x', c = 2 zeta sqrt(m k), x(0) = 0, x'(0) = v:
    x = v / w_d exp(-zeta w t) sin(w_d t), w_d = w sqrt(1 - zeta^2).  The force
    k x + c x' reaches zero (and stays clamped there) at tan(w_d t1) =
    -2 zeta sqrt(1 - zeta^2) / (1 - 2 zeta^2), i.e. w_d t1 in (pi/2, pi) for
    zeta < 1/sqrt 2; the particles then leave at the speed they have:
    e = -x'(t1) / v = -exp(-zeta w t1) (cos(w_d t1) - zeta / sqrt(1 - zeta^2) sin(w_d t1)).
    (Without the clamp e = exp(-zeta pi / sqrt(1 - zeta^2)), a little lower.)
    """
    s = np.sqrt(1 - zeta**2)
    phase = np.pi - np.arctan2(2 * zeta * s, 1 - 2 * zeta**2)  # w_d t1
    return -np.exp(-zeta * phase / s) * (np.cos(phase) - zeta / s * np.sin(phase))


@pytest.mark.parametrize("zeta", [0.05, 0.3])
@pytest.mark.parametrize("body", ["wall", "free_pair"])
def test_normal_dashpot_restitution(body, zeta):
    """Head-on impact with the normal dashpot 2 zeta sqrt(m* k_n) (000 eq 3-1),
    m* = m_i m_j / (m_i + m_j) for a pair (here discs of radius R and 1.5 R, both
    free) and the particle mass on a wall: the relative normal motion is the
    damped oscillator of :func:`_restitution_no_tension` (the total normal force
    is kept >= 0), e = 0.8588 (zeta = 0.05), 0.4510 (zeta = 0.3)
    (exp(-zeta pi / sqrt(1 - zeta^2)) = 0.8545, 0.3723).
    Tolerance 1e-3 (time step 1/2000 of the contact; measured 9e-6 and 2.5e-4)."""
    v = 0.2
    m = _mass(2)
    dt = 0.0025 / W
    steps = 1400
    if body == "wall":
        state, cfg, k = _state(2, body, y=R + 2.5 * v * dt, vel=[0.0, -v], spin=np.array(0.0))
        params = _params(2, dt=dt, contact_damping=zeta)
        h = _run(state, params, cfg, steps // BLOCK, BLOCK, k)
        assert h["pos"][-1][1] > R
        e = h["vel"][-1][1] / v
    else:
        m2 = 2.25 * m
        m_eff = m * m2 / (m + m2)
        kn = m_eff * W**2
        gap = 2.5 * 2 * v * dt
        p = jdem.make_particles([[0.0, 0.0], [2.5 * R + gap, 0.0]], [R, 1.5 * R], density=RHO,
                                vel=[[v, 0.0], [-v, 0.0]])
        # the 2D pair set-up's grid and list sizes: the same compiled program
        state, cfg = jdem.make_state(p, _config(2, "particle_j", "linear"))
        params = jdem.make_params(dim=2, n_materials=2, kn=kn, dt=dt, contact_damping=zeta)
        hist = _run(state, params, cfg, steps // BLOCK, BLOCK)
        vel = np.asarray(hist["vel"])[-1]
        assert np.asarray(hist["pos"])[-1][1, 0] - np.asarray(hist["pos"])[-1][0, 0] > 2.5 * R
        e = (vel[1, 0] - vel[0, 0]) / (2 * v)
        # momentum is conserved
        assert abs(m * vel[0, 0] + m2 * vel[1, 0] - (m - m2) * v) < 1e-12 * m2 * v
    expected = _restitution_no_tension(zeta)
    assert abs(e / expected - 1) < 1e-3


def test_kinematics_array_forms_match_the_component_forms():
    """scale, project_tangent and unit on (R, d) arrays equal their component-
    tuple forms and NumPy; a zero vector has a zero unit vector, not NaN."""
    from jdem import kinematics as km

    rng = np.random.default_rng(3)
    for d in (2, 3):
        v = rng.normal(size=(7, d))
        n = rng.normal(size=(7, d))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        s = rng.normal(size=7)
        np.testing.assert_allclose(np.asarray(km.scale(jnp.asarray(s), jnp.asarray(v))),
                                   s[:, None] * v, rtol=1e-15)
        tang = v - np.sum(v * n, axis=1, keepdims=True) * n
        np.testing.assert_allclose(np.asarray(km.project_tangent(jnp.asarray(v), jnp.asarray(n))),
                                   tang, rtol=1e-12, atol=1e-15)
        comp = km.project_tangent(tuple(jnp.asarray(c) for c in v.T),
                                  tuple(jnp.asarray(c) for c in n.T))
        np.testing.assert_allclose(np.stack([np.asarray(c) for c in comp], axis=1), tang,
                                   rtol=1e-12, atol=1e-15)
        zero = jnp.zeros((2, d)).at[1].set(jnp.asarray(v[0]))
        u, length = km.unit(zero)
        assert np.all(np.asarray(u[0]) == 0) and np.all(np.isfinite(np.asarray(u)))
        np.testing.assert_allclose(np.asarray(u[1]), v[0] / np.linalg.norm(v[0]), rtol=1e-15)


def test_a_floor_moving_under_a_resting_disc_drags_it_at_mu_g_and_carries_its_weight():
    """A disc at rest on a floor that moves at 0.2 m/s in x under gravity: the
    floor's friction accelerates it at mu g in the floor's direction while it
    slides (checked 4 ms after the start, well before rolling sets in), and the
    force the disc exerts on the floor is its weight, pointing into the floor."""
    r, mu, g = 0.01, 0.4, 9.81
    p = jdem.make_particles(np.array([[0.0, r]]), np.array([r]), density=2500.0)
    walls = jdem.make_walls([[0.0, 0.0]], [[0.0, 1.0]], n_particles=1, vel=[[0.2, 0.0]])
    params = jdem.make_params(dim=2, kn=1e7, ks=1e7, friction=mu, dt=2e-6,
                              gravity=[0.0, -g], contact_damping=0.7)
    state, cfg = jdem.make_state(p, walls=walls)
    m = float(p.mass[0])
    # settle the normal contact first with the floor at rest, then start it
    still = state._replace(walls=state.walls._replace(vel=jnp.zeros_like(state.walls.vel)))
    settled = jdem.advance(still, params, cfg, 20_000)
    np.testing.assert_allclose(np.asarray(settled.walls.force[0]), [0.0, -m * g], rtol=1e-6,
                               atol=1e-9 * m * g)
    moving = settled._replace(walls=settled.walls._replace(vel=state.walls.vel))
    n = 2_000                                     # 4 ms, well inside the sliding phase
    out = jdem.advance(moving, params, cfg, n)
    vx = float(out.particles.vel[0, 0])
    np.testing.assert_allclose(vx, mu * g * n * 2e-6, rtol=2e-2)


def test_norms_and_the_history_rotation_have_finite_gradients_at_zero():
    """A fresh contact stores a zero shear vector, and a stored one can lie along
    the new normal: the rollout's gradient passes through safe_norm and
    rotate_into_plane there, and must stay finite.  safe_norm's gradient at the
    zero vector is 0; rotate_into_plane keeps the length of a tangential vector
    (jacobian the identity on the tangent plane) and has finite jacobians where
    the vector is zero or along the normal."""
    from jdem import kinematics as km

    for d in (2, 3):
        n = jnp.zeros((1, d)).at[0, 1].set(1.0)           # normal +y
        zero = jnp.zeros((1, d))
        g = jax.grad(lambda v: jnp.sum(km.safe_norm(v)))(zero)
        np.testing.assert_array_equal(np.asarray(g), 0.0)
        assert np.all(np.isfinite(np.asarray(jax.grad(lambda v: jnp.sum(km.unit(v)[0]))(zero))))
        rot = lambda v: km.rotate_into_plane(v, n)[0]      # noqa: E731
        along = n * 2.0                                    # all along the normal: no tangential part
        tangential = jnp.zeros((1, d)).at[0, 0].set(3.0)
        np.testing.assert_array_equal(np.asarray(rot(zero)), 0.0)
        np.testing.assert_array_equal(np.asarray(rot(along)), 0.0)
        np.testing.assert_allclose(np.asarray(rot(tangential)), np.asarray(tangential[0]),
                                   rtol=1e-15)
        for v in (zero, along):
            for jac in (jax.jacfwd(rot)(v), jax.jacrev(rot)(v)):
                assert np.all(np.isfinite(np.asarray(jac))), (d, v, jac)
        jt = np.asarray(jax.jacfwd(rot)(tangential))[:, 0, :]       # (d, d)
        tangent_plane = np.eye(d) - np.outer(np.asarray(n[0]), np.asarray(n[0]))
        np.testing.assert_allclose(jt, tangent_plane, rtol=0, atol=1e-15)
