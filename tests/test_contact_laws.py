"""Contact laws against analytic values (000 §4.2, eq 4-1..4-9)."""
import jax.numpy as jnp
import numpy as np
import pytest

import jdem
from jdem import contact


def _collide(pos, radius, vel, params, model, n_steps, density=2500.0):
    p = jdem.make_particles(pos, radius, density=density, vel=vel)
    state, cfg = jdem.make_state(p, contact_model=model, skin=0.2 * min(radius))

    def obs(s, prm, c):
        gap = jnp.linalg.norm(s.particles.pos[1] - s.particles.pos[0]) - s.particles.radius.sum()
        return dict(t=s.time, gap=gap, vel=s.particles.vel)

    return jdem.run(state, params, cfg, n_steps, record_every=1, observe=obs, progress=False)


def test_two_disc_linear_collision_duration_and_restitution():
    r, rho, kn, v = 0.01, 2500.0, 1e6, 0.5
    m = rho * np.pi * r**2
    tc = np.pi * np.sqrt((m / 2) / kn)  # half period of the relative oscillator
    dt = tc / 1000
    params = jdem.make_params(dim=2, kn=kn, ks=kn, friction=0.3, dt=dt)
    res = _collide([[0, 0], [2 * r + 2e-5, 0]], [r, r], [[v, 0], [-v, 0]], params, "linear", 3000)
    h = res.history
    t_touch = h["t"][h["gap"] < 0]
    duration = t_touch[-1] - t_touch[0] + dt
    assert abs(duration / tc - 1) < 0.01
    v_after = h["vel"][-1]
    restitution = (v_after[1, 0] - v_after[0, 0]) / (2 * v)
    assert abs(restitution - 1) < 1e-6
    assert abs(v_after[:, 1]).max() < 1e-12  # head-on: no sideways motion


def test_two_sphere_hertz_collision_duration():
    r, rho, e, nu, v = 0.01, 2500.0, 1e9, 0.25, 0.5
    m = rho * 4 / 3 * np.pi * r**3
    m_eff, r_eff = m / 2, r / 2
    h = 2 * e / (3 * (1 - nu**2)) * np.sqrt(r_eff)  # 000 eq 4-6
    # Hertz impact: max overlap from energy balance, duration 2.9432 * d_max / v_rel
    v_rel = 2 * v
    d_max = (5 * m_eff * v_rel**2 / (4 * h)) ** 0.4
    tc = 2.9432 * d_max / v_rel
    params = jdem.make_params(dim=3, youngs=e, poisson=nu, friction=0.3, dt=tc / 1000)
    res = _collide([[0, 0, 0], [2 * r + 1e-5, 0, 0]], [r, r], [[v, 0, 0], [-v, 0, 0]],
                   params, "hertz", 3000)
    hist = res.history
    t_touch = hist["t"][hist["gap"] < 0]
    duration = t_touch[-1] - t_touch[0] + tc / 1000
    assert abs(duration / tc - 1) < 0.02
    assert abs(-hist["gap"].min() / d_max - 1) < 0.01


def test_mixed_stiffness_is_harmonic_mean():
    params = jdem.make_params(dim=2, n_materials=2, kn=[1e6, 3e6], ks=[1e5, 2e5], friction=0.1)
    fn, kn, kt = contact.normal_law(jnp.asarray(1e-4), jnp.asarray(0.005), jnp.asarray(0),
                                    jnp.asarray(1), params, "linear")
    assert np.isclose(kn, 2 * 1e6 * 3e6 / 4e6)  # 000 eq 4-9
    assert np.isclose(kt, 2 * 1e5 * 2e5 / 3e5)
    assert np.isclose(fn, kn * 1e-4)


def test_hertz_tangential_stiffness_matches_eq_4_8():
    params = jdem.make_params(dim=3, youngs=5e9, poisson=0.3)
    overlap, r_eff = 2e-5, 0.004
    fn, kn, kt = contact.normal_law(jnp.asarray(overlap), jnp.asarray(r_eff), jnp.asarray(0),
                                    jnp.asarray(0), params, "hertz")
    e, nu = 5e9, 0.3
    h = 2 * e / (3 * (1 - nu**2)) * np.sqrt(r_eff)
    assert np.isclose(fn, h * overlap**1.5, rtol=1e-12)
    assert np.isclose(kn, 1.5 * h * overlap**0.5, rtol=1e-12)
    kt_seed = (e / (1 + nu)) ** (2 / 3) * (12 * (1 - nu) * r_eff * fn) ** (1 / 3) / (2 - nu)
    assert np.isclose(kt, kt_seed, rtol=1e-12)


def _first_position(state, params, config):
    return dict(pos=state.particles.pos[0])


def _slide_on_incline(dim, slope_deg, friction_deg, steps=8000):
    """A non-rotating particle resting on an inclined wall under gravity.

    Returns its displacement down the slope at the end, the analytic sliding
    displacement, and the creep between the means of
    the second and last quarter of the run (the elastic tangential spring
    oscillates undamped, so single samples wobble; a stuck particle's mean
    position does not move).
    """
    r, rho, kn, g = 0.01, 2500.0, 1e6, 9.81
    th = np.deg2rad(slope_deg)
    normal = np.zeros(dim)
    normal[0], normal[1] = -np.sin(th), np.cos(th)  # wall through the origin, tilted by th
    m = rho * (np.pi * r**2 if dim == 2 else 4 / 3 * np.pi * r**3)
    sink = m * g * np.cos(th) / kn  # static overlap under the normal load
    centre = normal * (r - sink)
    fixed_rot = [True] if dim == 2 else [[True, True, True]]
    p = jdem.make_particles([centre], [r], density=rho, fixed_rot=fixed_rot)
    walls = jdem.make_walls([np.zeros(dim)], [normal], n_particles=1)
    grav = np.zeros(dim)
    grav[1] = -g
    dt = 0.05 * np.sqrt(m / kn)
    mu = np.tan(np.deg2rad(friction_deg))
    params = jdem.make_params(dim=dim, kn=kn, ks=kn, friction=mu, dt=dt, gravity=grav)
    # the search grid of a particle at the origin for every slope (one particle: no
    # pairs to find), so that the runs share one compiled chunk
    cfg = jdem.make_config(jdem.make_particles([np.zeros(dim)], [r]))
    state, cfg = jdem.make_state(p, cfg, walls=walls)
    down = np.zeros(dim)
    down[0], down[1] = -np.cos(th), -np.sin(th)

    res = jdem.run(state, params, cfg, steps, record_every=10, observe=_first_position,
                   progress=False)
    x = (res.history["pos"] - centre) @ down
    q = len(x) // 4
    creep = x[3 * q:].mean() - x[q:2 * q].mean()
    # analytic spring-slider: the tangential spring (k_t) loads from zero while the
    # particle accelerates at g sin; it slips once k_t x = mu m g cos, with speed v0,
    # then slides as a Coulomb block at a = g (sin - mu cos)
    t = steps * dt
    w = np.sqrt(kn / m)
    x_slip = mu * m * g * np.cos(th) / kn
    amp = m * g * np.sin(th) / kn
    t_slip = np.arccos(1 - x_slip / amp) / w
    v0 = amp * w * np.sin(w * t_slip)
    a = g * (np.sin(th) - mu * np.cos(th))
    ts = t - t_slip
    return x[-1], x_slip + v0 * ts + 0.5 * a * ts**2, creep


@pytest.mark.parametrize("dim", [2, 3])
def test_particle_on_incline_slides_iff_slope_exceeds_friction_angle(dim):
    phi = 25.0
    for slope in (phi - 5, phi - 1):
        x, _, creep = _slide_on_incline(dim, slope, phi)
        assert abs(x) < 1e-4  # a hundredth of the radius: elastic spring, no sliding
        assert abs(creep) < 1e-8
    for slope in (phi + 1, phi + 5):
        x, expected, creep = _slide_on_incline(dim, slope, phi)
        assert abs(x / expected - 1) < 0.01  # spring-slider solution
        assert creep > 1e-4


def test_segment_add_leaves_out_masked_rows():
    """``segment_add(..., where=)`` drops the masked rows (sent past the last bin),
    so they may hold anything; the kept rows sum as without a mask."""
    from jdem.kinematics import segment_add

    values = jnp.asarray([[1.0, 2.0], [10.0, 20.0], [100.0, 200.0], [5.0, 7.0]])
    index = jnp.asarray([0, 2, 0, 1])
    keep = jnp.asarray([True, False, True, True])
    got = np.asarray(segment_add(values, index, 3, where=keep))
    np.testing.assert_array_equal(got, [[101.0, 202.0], [5.0, 7.0], [0.0, 0.0]])
    zeroed = jnp.where(keep[:, None], values, 0.0)
    np.testing.assert_array_equal(got, np.asarray(segment_add(zeroed, index, 3)))


def test_contact_sums_are_those_of_every_listed_row():
    """contact_forces sums only touching rows; the totals equal a plain scatter of
    every listed row (padding and separated pairs contribute exact zeros)."""
    from jdem import neighbors
    from jdem.kinematics import cross_r_f

    rng = np.random.default_rng(3)
    pos = rng.uniform(0, 0.02, (60, 3))
    p = jdem.make_particles(pos, rng.uniform(1e-3, 2e-3, 60), density=2500.0,
                            vel=rng.normal(0, 0.1, (60, 3)), angvel=rng.normal(0, 5.0, (60, 3)))
    state, cfg = jdem.make_state(p, skin=1e-3)
    c, _ = neighbors.allocate(state.particles, cfg, min_capacity=4 * int(state.contacts.n_pairs))
    params = jdem.make_params(dim=3, kn=1e5, friction=0.5, dt=1e-6)
    assert int(c.n_pairs) < c.i.shape[0]  # there are padding rows
    new, force, torque, count = contact.contact_forces(c, state.particles, params, cfg)
    g = contact.pair_geometry(c, state.particles)
    assert 0 < int(g.touching.sum()) < int(c.n_pairs)  # touching and separated pairs
    # every row's force from the returned shear and the same normal law, summed unmasked
    _, fn, _, _ = contact.pair_law(c, state.particles, params, cfg)
    i, j = c.i, c.j
    assert float(params.contact_damping) == 0.0  # no normal dashpot term to add
    f_i = -jnp.where(g.touching, fn, 0.0)[:, None] * g.normal + new.shear
    n = pos.shape[0]
    full = jnp.zeros((n, 3)).at[i].add(f_i).at[j].add(-f_i)
    np.testing.assert_allclose(np.asarray(force), np.asarray(full), rtol=1e-12, atol=1e-15)
    arm_i = (state.particles.radius[i] - 0.5 * g.overlap)[:, None] * g.normal
    arm_j = -(state.particles.radius[j] - 0.5 * g.overlap)[:, None] * g.normal
    t_full = jnp.zeros((n, 3)).at[i].add(cross_r_f(arm_i, f_i)).at[j].add(cross_r_f(arm_j, -f_i))
    np.testing.assert_allclose(np.asarray(torque), np.asarray(t_full), rtol=1e-12, atol=1e-15)
    touching = np.asarray(g.touching)
    want = np.bincount(np.asarray(i)[touching], minlength=n) + np.bincount(np.asarray(j)[touching], minlength=n)
    np.testing.assert_array_equal(np.asarray(count), want)


def test_reported_depth_is_the_deepest_overlap_over_the_smaller_radius():
    """The tunnelling measure the step's guard reads: a large and a small disc
    overlapping by 0.4 of the small radius, and a second, shallower pair;
    depth = max overlap / min(R_i, R_j) = 0.4 (over the larger radius it would
    be 0.1: the small disc could pass through unnoticed)."""
    from jdem import neighbors

    r_big, r_small = 4e-3, 1e-3
    pos = np.array([[0.0, 0.0], [r_big + 0.6 * r_small, 0.0],
                    [0.0, 0.05], [0.0, 0.05 + 2 * r_small - 0.1 * r_small]])
    p = jdem.make_particles(pos, [r_big, r_small, r_small, r_small])
    state, cfg = jdem.make_state(p)
    c, _ = neighbors.allocate(state.particles, cfg)
    params = jdem.make_params(dim=2, kn=1e5, dt=1e-6)
    *_, depth = contact.contact_forces(c, state.particles, params, cfg, report_depth=True)
    assert float(depth) == pytest.approx(0.4, rel=1e-12)


def test_wall_forces_of_a_large_system_equal_those_of_its_parts():
    """Above kinematics.COMPUTED_ONCE_MIN_ROWS (wall, particle) rows the wall law
    runs as a computation of its own behind a conditional; below it, inline.
    Wall forces of one particle do not depend on the others, so 4,200 discs
    against four walls (16,800 rows, the conditional) must get the forces of
    the same discs taken 1,050 at a time (inline), at the first step, when no
    wall has been touched yet."""
    from jdem.kinematics import COMPUTED_ONCE_MIN_ROWS
    from jdem.walls import wall_forces

    n, r = 4200, 1e-3
    assert 4 * n >= COMPUTED_ONCE_MIN_ROWS > 4 * (n // 4)
    rng = np.random.default_rng(11)
    pos = np.stack([np.arange(n) * 3 * r, rng.uniform(0.5 * r, 2 * r, n)], axis=1)
    vel = rng.normal(0, 0.1, (n, 2))
    params = jdem.make_params(dim=2, kn=1e5, friction=0.5, dt=1e-6)
    walls_at = ([[0.0, 0.0], [0.0, 1.0], [-r, 0.0], [n * 3 * r, 0.0]],
                [[0.0, 1.0], [0.0, -1.0], [1.0, 0.0], [-1.0, 0.0]])

    def forces(sl):
        p = jdem.make_particles(pos[sl], np.full(len(pos[sl]), r), vel=vel[sl],
                                angvel=np.zeros(len(pos[sl])))
        walls = jdem.make_walls(*walls_at, n_particles=len(pos[sl]))
        state, cfg = jdem.make_state(p, walls=walls)
        w, f, t, count = wall_forces(state.walls, state.particles, params, cfg)
        return np.asarray(f), np.asarray(t), np.asarray(count), np.asarray(w.n_contacts)

    f, t, count, per_wall = forces(slice(None))
    assert 0 < per_wall[0] < n and np.all(per_wall[1:] == 0)   # only the floor touches
    parts = [forces(slice(k, k + n // 4)) for k in range(0, n, n // 4)]
    np.testing.assert_allclose(f, np.concatenate([x[0] for x in parts]), rtol=1e-12, atol=0)
    np.testing.assert_allclose(t, np.concatenate([x[1] for x in parts]), rtol=1e-12, atol=0)
    np.testing.assert_array_equal(count, np.concatenate([x[2] for x in parts]))
