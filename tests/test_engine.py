"""The dynamic-relaxation engine: energy, settling, servo walls, capacities,
restarts, batching, gradients, bad input."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdem
from jdem import measure, neighbors, timestep
from jdem.io import CorruptFileError, load_run, save_run


def _box_walls(lo, hi, n, **kw):
    """Four walls of the box [lo, hi] (2D), normals pointing inwards."""
    pts = [[lo[0], 0], [hi[0], 0], [0, lo[1]], [0, hi[1]]]
    nrm = [[1, 0], [-1, 0], [0, 1], [0, -1]]
    return jdem.make_walls(pts, nrm, n_particles=n, **kw)


def _loose_discs(nx, ny, r=1e-3, seed=0, gap=0.3, jitter=0.1):
    """Discs on a jittered grid with radii in [0.8 r, 1.2 r] (touching when gap < 0)."""
    rng = np.random.default_rng(seed)
    s = 2 * 1.2 * r * (1 + gap)
    xy = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij"), -1).reshape(-1, 2)
    pos = (xy + 0.5) * s + rng.uniform(-jitter, jitter, size=xy.shape) * r
    rad = rng.uniform(0.8 * r, 1.2 * r, size=len(pos))
    return pos, rad, (nx * s, ny * s)


# ----------------------------------------------------------------------------- energy
def _energy(state, params, config):
    return dict(kinetic=measure.synchronized_kinetic_energy(state, params, config),
                elastic=measure.contact_energy(state, params, config))


def test_undamped_elastic_packing_conserves_energy():
    """Relative total-energy drift below 1e-3 over 10,000 steps at 0.2 x critical.

    The scheme's energy error comes from contacts that open and close between
    steps.  In one packing these errors add up as a random walk of either sign, so
    one run's drift is a random number: over 20 packings of this set-up it ranged
    from 5e-6 to 1.7e-3 (3 of 20 above 1e-3, signs mixed), and it changes when
    round-off changes the trajectory (e.g. the order in which a particle's contact
    forces are summed).  A bias of the scheme would show in the mean over
    packings: eight packings run as one batch, and their mean drift must stay
    below 1e-3, with no run straying from its initial energy by 1 %.
    """
    from jdem.batch import stack_states as _stack_members

    members = []
    for seed in range(1, 9):
        pos, rad, (w, h) = _loose_discs(8, 8, gap=-0.2, seed=seed)  # slightly overlapping
        vel = np.random.default_rng(seed + 1).normal(0, 0.01, size=pos.shape)
        p = jdem.make_particles(pos, rad, vel=vel)
        members.append(jdem.make_state(p, walls=_box_walls((0, 0), (w, h), len(pos)))[0])
    state, cfg = _stack_members(members, 2)
    params = jdem.make_params(dim=2, kn=1e5, ks=1e5, friction=0.0)
    crit = min(float(timestep.critical_timestep(m, params, cfg)) for m in members)
    params = jdem.broadcast_batch(params._replace(dt=jnp.asarray(0.2 * crit)), len(members))
    res = jdem.run(state, params, cfg, 10_000, record_every=50, observe=_energy, progress=False,
                   batched=True)
    e = res.history["kinetic"] + res.history["elastic"]  # (8, records)
    assert np.all(res.history["elastic"].max(axis=1) > 0.1 * e[:, 0])  # contacts really work
    assert np.all(np.asarray(res.state.contacts.n_builds) > 2)  # the lists were rebuilt
    k = e.shape[1] // 10
    drift = (e[:, -k:].mean(axis=1) - e[:, :k].mean(axis=1)) / e[:, 0]
    assert abs(drift.mean()) < 1e-3
    assert np.abs(e / e[:, :1] - 1).max() < 1e-2  # no excursion either


# ----------------------------------------------------------------------------- deposition
def _weight_observe(state, params, config):
    return dict(kinetic=measure.kinetic_energy(state), wall_force=state.walls.force)


def test_gravity_deposition_settles_and_floor_carries_the_weight():
    pos, rad, (w, h) = _loose_discs(25, 40, seed=4, jitter=0.35)
    n = len(pos)
    g = 9.81
    p = jdem.make_particles(pos, rad)
    # frictionless walls (material 1): the floor alone carries the weight
    walls = _box_walls((0, 0), (w, 2 * h), n, material=1)
    # local damping for the quasi-static settling, contact dashpots for the impacts and
    # a little mass-proportional damping for rattlers spinning freely in their cages
    params = jdem.make_params(dim=2, n_materials=2, kn=1e5, ks=1e5, friction=[0.5, 0.0],
                              gravity=[0.0, -g], local_damping=0.7, contact_damping=0.3,
                              viscous_damping=2.0)
    state, cfg = jdem.make_state(p, walls=walls)
    crit = float(timestep.nominal_critical_timestep(p, params, cfg))
    params = params._replace(dt=jnp.asarray(timestep.recommended(crit)))
    res = jdem.run(state, params, cfg, 40_000, record_every=1000, observe=_weight_observe,
                   progress=False)
    ke = res.history["kinetic"]
    assert ke[-1] < 1e-6 * ke.max()
    weight = float(np.sum(np.asarray(p.gravity_mass)) * g)
    floor = -res.history["wall_force"][-1, 2, 1]  # particles push the floor down (-y)
    assert abs(floor / weight - 1) < 0.01
    assert not bool(neighbors.overflowed(res.state.contacts, res.config))


# ----------------------------------------------------------------------------- capacity
def _positions(state, params, config):
    return dict(pos=state.particles.pos, vel=state.particles.vel)


def _small_fall(seed=5, nx=6, ny=10):
    pos, rad, (w, h) = _loose_discs(nx, ny, seed=seed)
    p = jdem.make_particles(pos, rad)
    walls = _box_walls((0, 0), (w, 2 * h), len(pos))
    params = jdem.make_params(dim=2, kn=1e5, ks=1e5, friction=0.4, gravity=[0.0, -9.81],
                              local_damping=0.1, dt=2e-5)
    state, cfg = jdem.make_state(p, walls=walls)
    return state, params, cfg


def test_too_small_neighbour_capacity_gives_the_same_trajectory():
    state, params, cfg = _small_fall()
    ample, cfg_ample = neighbors.allocate(state.particles, cfg, min_capacity=2000)
    tight_cfg = cfg.replace(max_per_cell=1)
    tight = neighbors.build(neighbors.empty(state.particles, 3), state.particles, tight_cfg)
    a = jdem.run(state._replace(contacts=ample), params, cfg_ample, 6000, record_every=200,
                 observe=_positions, progress=False, chunk_steps=1000)
    b = jdem.run(state._replace(contacts=tight), params, tight_cfg, 6000, record_every=200,
                 observe=_positions, progress=False, chunk_steps=1000)
    assert b.state.contacts.i.shape[0] > 3 and b.config.max_per_cell > 1  # it re-allocated
    assert int(a.state.contacts.n_pairs) > 10
    np.testing.assert_allclose(b.history["pos"], a.history["pos"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.history["vel"], a.history["vel"], rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- restart
def test_restart_from_hdf5_continues_bit_for_bit(tmp_path):
    state, params, cfg = _small_fall(seed=6)
    whole = jdem.run(state, params, cfg, 4000, record_every=100, observe=_positions,
                     progress=False, chunk_steps=1000)
    half = jdem.run(state, params, cfg, 2000, record_every=100, observe=_positions,
                    progress=False, chunk_steps=1000)
    path = save_run(tmp_path / "half.h5", state=half.state, params=params, config=half.config,
                    history=half.history)
    back = load_run(path)
    rest = jdem.run(back.state, back.params, back.config, 2000, record_every=100,
                    observe=_positions, progress=False, chunk_steps=1000)
    for a, b in zip(jax.tree_util.tree_leaves(whole.state), jax.tree_util.tree_leaves(rest.state)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(whole.history["pos"][20:], rest.history["pos"])


# ----------------------------------------------------------------------------- batching
def test_vmap_over_friction_matches_separate_runs():
    state, params, cfg = _small_fall(seed=7)
    mus = [0.0, 0.2, 0.5, 1.0]
    batch_state = jdem.broadcast_batch(state, 4)
    batch_params = jdem.broadcast_batch(params, 4)._replace(
        friction=jnp.asarray(mus)[:, None] * jnp.ones_like(params.friction))
    batched = jdem.run(batch_state, batch_params, cfg, 3000, record_every=100, observe=_positions,
                       progress=False, batched=True)
    assert batched.history["pos"].shape[:2] == (4, 30)
    finals = []
    for k, mu in enumerate(mus):
        one = jdem.run(state, params._replace(friction=jnp.full_like(params.friction, mu)), cfg,
                       3000, record_every=100, observe=_positions, progress=False)
        # identical up to round-off (the vectorised code may fuse differently), which
        # the collisions amplify to ~1e-11 m by the end
        np.testing.assert_allclose(batched.history["pos"][k], one.history["pos"], rtol=0, atol=1e-10)
        finals.append(one.history["pos"][-1])
    assert np.abs(finals[0] - finals[3]).max() > 1e-6  # friction really matters here


# ----------------------------------------------------------------------------- servo wall
def _stress_observe(state, params, config):
    from jdem.walls import normal_stress

    return dict(stress=normal_stress(state.walls), kinetic=measure.kinetic_energy(state))


def test_servo_wall_holds_target_stress():
    pos, rad, (w, h) = _loose_discs(10, 10, seed=8, gap=0.05)
    n = len(pos)
    target = 2e5  # Pa on a wall of length w and unit thickness
    # frictionless walls (material 1), so the side walls carry no vertical load
    walls = _box_walls((0, 0), (w, h * 1.02), n, servo=[False, False, False, True],
                       target_stress=[0, 0, 0, target], area=[h, h, w, w], servo_vmax=0.5,
                       servo_gain=0.3, material=1)
    p = jdem.make_particles(pos, rad)
    params = jdem.make_params(dim=2, n_materials=2, kn=1e6, ks=1e6, friction=[0.3, 0.0],
                              local_damping=0.7, dt=1e-5)
    state, cfg = jdem.make_state(p, walls=walls)
    res = jdem.run(state, params, cfg, 10_000, record_every=500, observe=_stress_observe,
                   progress=False)
    stress = res.history["stress"][-1]
    assert abs(stress[3] / target - 1) < 1e-3
    # equilibrium: the floor carries what the servo wall pushes
    assert abs(stress[2] / target - 1) < 1e-3
    assert res.history["kinetic"][-1] < 1e-9 * res.history["kinetic"].max()


def test_averaged_stress_of_a_compressed_square_lattice():
    """3 x 3 equal discs squeezed between four walls, every contact overlapped by d:
    each row / column carries F = k d, the walls feel n F / L, and 000 eq 4-44
    gives n F (L + d) / L^2: contact points sit mid-overlap, so the wall contacts
    lie d/2 beyond each wall plane."""
    r, k, d, n = 1e-3, 1e6, 1e-6, 3
    pitch = 2 * r - d
    c = (r - d) + pitch * np.arange(n)
    pos = np.stack(np.meshgrid(c, c, indexing="ij"), -1).reshape(-1, 2)
    side = c[-1] + r - d
    walls = _box_walls((0, 0), (side, side), n * n)
    params = jdem.make_params(dim=2, kn=k, ks=k, friction=0.5, dt=1e-6)
    state, cfg = jdem.make_state(jdem.make_particles(pos, np.full(n * n, r)), walls=walls)
    sigma = np.asarray(measure.averaged_stress(state, params, cfg, side * side))
    expected = n * k * d * (side + d) / side**2
    np.testing.assert_allclose(np.diag(sigma), [expected, expected], rtol=1e-9)
    assert abs(sigma[0, 1]) < 1e-9 * expected
    # and the walls feel n F / L after one step from rest
    s1 = jdem.advance(state, params, cfg, 1)
    from jdem.walls import normal_stress

    np.testing.assert_allclose(np.asarray(normal_stress(s1.walls._replace(area=jnp.full(4, side)))),
                               n * k * d / side, rtol=1e-9)


# ----------------------------------------------------------------------------- gradients
def _oblique_collision():
    r = 0.01
    p = jdem.make_particles([[0.0, 0.0], [2 * r + 1e-5, 0.004]], [r, r],
                            vel=[[0.4, 0.0], [-0.4, 0.0]])
    state, cfg = jdem.make_state(p, skin=2e-3)

    def loss(params):
        final, hist = jdem.rollout(state, params, cfg, 40, 50, _positions)
        return jnp.sum(final.particles.vel[1] ** 2) + 1e3 * final.particles.pos[1, 1]

    return loss


def test_gradient_through_rollout_matches_finite_differences():
    params = jdem.make_params(dim=2, kn=1e5, ks=5e4, friction=0.3, dt=2e-6, local_damping=0.05)
    loss = _oblique_collision()
    # jitted: run eagerly, every rollout would trace and compile its scans again
    g = jax.jit(jax.grad(loss))(params)
    loss = jax.jit(loss)
    for field, h in (("kn", 1.0), ("friction", 1e-5), ("local_damping", 1e-6)):
        base = getattr(params, field)
        up = loss(params._replace(**{field: base + h}))
        down = loss(params._replace(**{field: base - h}))
        fd = (up - down) / (2 * h)
        ad = jnp.sum(getattr(g, field))
        assert np.isfinite(ad)
        assert abs(ad - fd) <= 1e-3 * abs(fd) + 1e-12, (field, ad, fd)


# ----------------------------------------------------------------------------- bad input
def test_bad_particle_input_names_field_and_value():
    with pytest.raises(jdem.InputError, match=r"radius\[1\] must be > 0, got -0.5"):
        jdem.make_particles([[0, 0], [1, 0]], [1.0, -0.5])
    with pytest.raises(jdem.InputError, match=r"radius\[0\] must be finite, got nan"):
        jdem.make_particles([[0, 0], [1, 0]], [np.nan, 1.0])
    with pytest.raises(jdem.InputError, match=r"pos\[1, 1\] must be finite"):
        jdem.make_particles([[0, 0], [1, np.inf]], [1.0, 1.0])
    with pytest.raises(jdem.InputError, match=r"params.friction\[0\] must be finite, got nan"):
        jdem.make_params(dim=2, friction=np.nan)
    with pytest.raises(jdem.InputError, match=r"params.dt must be > 0"):
        jdem.make_params(dim=2, dt=-1.0)
    with pytest.raises(jdem.InputError, match=r"params.local_damping must lie in \[0.0, 1.0\), got 1.5"):
        jdem.make_params(dim=2, local_damping=1.5)


def test_time_step_above_critical_is_refused():
    state, params, cfg = _small_fall()
    crit = float(timestep.nominal_critical_timestep(state.particles, params, cfg))
    with pytest.raises(jdem.InputError, match=r"params.dt = .* exceeds the critical time step"):
        jdem.run(state, params._replace(dt=jnp.asarray(3 * crit)), cfg, 100, record_every=100,
                 progress=False)


@pytest.mark.parametrize("uniform", [False, True])
def test_density_scaling_makes_the_requested_step_stable(uniform):
    """000 §3.3.2: after scaling, dt_target is below safety x the critical step,
    and the weights (gravitational masses) are unchanged."""
    pos, rad, (w, h) = _loose_discs(5, 5, gap=-0.1, seed=10)
    p = jdem.make_particles(pos, rad)
    params = jdem.make_params(dim=2, kn=1e6, ks=1e6, friction=0.3)
    state, cfg = jdem.make_state(p, walls=_box_walls((0, 0), (w, h), len(pos)))
    crit = float(timestep.critical_timestep(state, params, cfg))
    target = 5 * crit
    scaled = timestep.scale_density(state, params, cfg, target, safety=0.8, uniform=uniform)
    assert float(timestep.critical_timestep(scaled, params, cfg)) >= target / 0.8 * (1 - 1e-12)
    np.testing.assert_array_equal(scaled.particles.gravity_mass, state.particles.gravity_mass)
    factor = np.asarray(scaled.particles.mass / state.particles.mass)
    np.testing.assert_allclose(np.asarray(scaled.particles.inertia / state.particles.inertia), factor)
    assert factor.min() >= 1.0 and factor.max() > 20.0
    if uniform:
        np.testing.assert_allclose(factor, factor[0])


def test_missing_and_corrupt_files_are_reported(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.h5"):
        load_run(tmp_path / "nope.h5")
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"definitely not hdf5" * 10)
    with pytest.raises(CorruptFileError, match="bad.h5"):
        load_run(bad)


def test_divergence_stops_with_step_and_last_good_state():
    """A step 3 x the estimated limit grows an oscillation over many steps; the
    guard stops it while everything is still finite (it used to run on to NaN)."""
    pos, rad, (w, h) = _loose_discs(4, 4, gap=-0.1, seed=9)
    p = jdem.make_particles(pos, rad)
    params = jdem.make_params(dim=2, kn=1e6, ks=1e6, friction=0.3)
    state, cfg = jdem.make_state(p, walls=_box_walls((0, 0), (w, h), len(pos)))
    crit = float(timestep.critical_timestep(state, params, cfg))
    params = params._replace(dt=jnp.asarray(3 * crit))
    with pytest.raises(jdem.SimulationDiverged) as info:
        jdem.run(state, params, cfg, 20_000, record_every=100, progress=False, check_dt=False)
    err = info.value
    good = err.last_good_state
    assert int(good.step) == err.step > 0
    assert np.all(np.isfinite(np.asarray(good.particles.pos)))
    nxt = jdem.advance(good, params, cfg, 1)
    assert int(nxt.first_bad_step) == err.step          # the very next step fails the guard
    assert np.all(np.isfinite(np.asarray(nxt.particles.vel)))   # and is caught before NaN
    assert f"step {err.step}" in str(err) and "of its radius" in err.reason
