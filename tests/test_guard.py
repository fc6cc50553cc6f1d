"""The divergence guard (jdem.integrate.healthy, jdem.simulate.run) and the
isolation of failing members in batched runs (issue: reliability)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdem
from jdem import contact, timestep
from jdem.batch import broadcast_batch
from jdem.validate import InputError

from test_engine import _box_walls, _loose_discs


def _box(gap=-0.1):
    pos, rad, (w, h) = _loose_discs(4, 4, gap=gap, seed=9)
    p = jdem.make_particles(pos, rad)
    params = jdem.make_params(dim=2, kn=1e6, ks=1e6, friction=0.3)
    state, cfg = jdem.make_state(p, walls=_box_walls((0, 0), (w, h), len(pos)))
    return state, params, cfg, float(timestep.critical_timestep(state, params, cfg))


def test_two_discs_passing_through_each_other_are_stopped():
    """Head-on at 30 m/s relative with k_n = 1e6 N/m the overlap would reach
    v sqrt(m*/k) = 1.9 r: the guard stops the run when the overlap passes r."""
    r = 1e-3
    p = jdem.make_particles(np.array([[0.0, 0.0], [2.5 * r, 0.0]]), np.array([r, r]),
                            vel=np.array([[15.0, 0.0], [-15.0, 0.0]]))
    params = jdem.make_params(dim=2, kn=1e6, ks=1e6, friction=0.3, dt=2e-6)
    state, cfg = jdem.make_state(p)
    with pytest.raises(jdem.SimulationDiverged) as info:
        jdem.run(state, params, cfg, 2000, record_every=10, progress=False)
    err = info.value
    assert "particles 0 and 1 overlap" in err.reason and "passing through" in err.reason
    good = err.last_good_state
    gap = float(np.diff(np.asarray(good.particles.pos)[:, 0])[0])
    assert 0.9 * r < gap < r        # overlap just past r: the centres have not crossed


def test_hertz_pair_whose_critical_step_falls_below_dt_is_stopped_between_chunks():
    """A Hertz contact stiffens as it is pressed: a step 0.9 x the critical step
    at first contact is 1.1 x it at 2.5 x the overlap.  The run stops when the
    re-estimated critical step falls below dt, before anything blows up."""
    r, d0 = 1e-3, 1e-5
    p = jdem.make_particles(np.array([[0.0, 0.0], [2 * r - d0, 0.0]]), np.array([r, r]),
                            fixed_vel=np.array([[True, True], [False, True]]))
    params = jdem.make_params(dim=2, youngs=1e9, poisson=0.25, friction=0.3)
    state, cfg = jdem.make_state(p, contact_model="hertz")
    fn, _, _ = contact.normal_law(jnp.asarray(d0), jnp.asarray(r / 2), jnp.asarray(0),
                                  jnp.asarray(0), params, "hertz")
    state = state._replace(particles=state.particles._replace(
        ext_force=jnp.asarray([[0.0, 0.0], [-4 * float(fn), 0.0]])))
    crit = float(timestep.critical_timestep(state, params, cfg))
    params = params._replace(dt=jnp.asarray(0.9 * crit), viscous_damping=jnp.asarray(0.02 / crit))
    with pytest.raises(jdem.SimulationDiverged) as info:
        jdem.run(state, params, cfg, 20_000, record_every=10, chunk_steps=10, progress=False)
    err = info.value
    assert "critical time step of the current contacts fell" in err.reason
    good = err.last_good_state
    assert np.all(np.isfinite(np.asarray(good.particles.vel)))
    assert float(timestep.critical_timestep(good, params, cfg)) < float(params.dt)


def test_a_diverging_member_is_set_aside_and_the_other_finishes_unchanged():
    state, params, cfg, crit = _box()
    good = params._replace(dt=jnp.asarray(0.1 * crit))
    bad = params._replace(dt=jnp.asarray(3 * crit))
    both = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), good, bad)
    with pytest.warns(RuntimeWarning, match="member 1 set aside"):
        res = jdem.run(broadcast_batch(state, 2), both, cfg, 3000, record_every=100,
                       progress=False, batched=True, check_dt=False)
    alone = jdem.run(state, good, cfg, 3000, record_every=100, progress=False)
    (failure,) = res.failures
    assert failure.member == 1 and "of its radius" in failure.reason
    for key, v in res.history.items():
        np.testing.assert_array_equal(v[0], alone.history[key])   # bit for bit
        if v.dtype.kind == "f":
            assert np.all(np.isnan(v[1][failure.step // 100:]))
    np.testing.assert_array_equal(np.asarray(res.state.particles.pos[0]),
                                  np.asarray(alone.state.particles.pos))
    # the set-aside member ends in its last good state, valid and finite
    assert np.all(np.asarray(res.state.particles.valid[1]) == np.asarray(state.particles.valid))
    assert np.all(np.isfinite(np.asarray(res.state.particles.pos[1])))


def test_a_batch_whose_every_member_fails_raises():
    state, params, cfg, crit = _box()
    bad = broadcast_batch(params._replace(dt=jnp.asarray(3 * crit)), 2)
    with pytest.raises(jdem.SimulationDiverged, match="every member failed"):
        jdem.run(broadcast_batch(state, 2), bad, cfg, 1000, record_every=100, progress=False,
                 batched=True, check_dt=False)


def test_batched_flag_that_does_not_match_the_state_is_refused():
    state, params, cfg, crit = _box()
    params = params._replace(dt=jnp.asarray(0.1 * crit))
    with pytest.raises(InputError, match="batched = True"):
        jdem.run(state, params, cfg, 100, record_every=100, progress=False, batched=True)
    with pytest.raises(InputError, match="batched = False"):
        jdem.run(broadcast_batch(state, 2), broadcast_batch(params, 2), cfg, 100,
                 record_every=100, progress=False)


# slow (~95 s): the set-aside member is checked on jdem.run above and in
# tests/test_calibrate.py::test_ensemble_member_that_diverges_is_isolated
@pytest.mark.slow
def test_a_lab_batch_with_a_diverging_member_finishes_the_others():
    """A UCS batch of two identical members, the second with 20 x the time step:
    it is set aside at its first bad step; the first member's curve is bit for
    bit the one it has beside a healthy twin, and its summary is unchanged."""
    from jdem import lab
    from jdem.materials import rock_params
    from jdem.specimen import generate

    spec = generate("rectangle", (0.004, 0.008), 0.2e-3, 0.35e-3, seed=2)
    params = rock_params(2, kappa=[3e-3, 3e-3])
    setup = lab.UCS.setup(spec, params, platen_step=3e-9, max_strain=4e-4,
                          damping=lab.local(0.8), record_every=50)
    twin = lab.run(setup, progress=False, warn_dynamic=False)
    dt = setup.params.dt
    setup = setup.replace(params=setup.params._replace(dt=dt.at[1].set(20 * dt[1])))
    with pytest.warns(RuntimeWarning, match="member 1 set aside"):
        res = lab.run(setup, progress=False, warn_dynamic=False, check_dt=False)
    (failure,) = res.failures
    assert failure.member == 1 and failure.reason
    assert list(res.history["member_failed_step"]) == [-1, failure.step]
    for key in ("axial_stress", "axial_strain", "fracture_degree"):
        np.testing.assert_array_equal(res.history[key][0], twin.history[key][0])
        assert np.all(np.isnan(res.history[key][1][failure.step // 50 + 1:]))
    s_twin, s_res = lab.peak_summary(twin.history), lab.peak_summary(res.history)
    assert s_res["peak_stress"][0] == s_twin["peak_stress"][0]
    assert np.all(np.isfinite(np.asarray(res.state.particles.pos[1])))


def test_a_pure_rollout_that_overflows_its_list_says_so_and_its_records_are_nan():
    from jdem import neighbors

    state, params, cfg, crit = _box()
    params = params._replace(dt=jnp.asarray(0.1 * crit))
    # jitted, so that the roomy rollout below reuses the first one's compilation
    rollout = jax.jit(jdem.rollout, static_argnums=(2, 3, 4))
    _, hist = rollout(state, params, cfg, 3, 10)
    assert not np.any(np.asarray(hist["overflowed"]))
    jdem.simulate.raise_if_overflowed(hist)                   # no error
    small = state._replace(contacts=neighbors.empty(state.particles, 4))
    _, hist = rollout(small, params, cfg, 3, 10)
    assert np.all(np.asarray(hist["overflowed"]))
    assert np.all(np.isnan(np.asarray(hist["kinetic_energy"])))
    assert np.asarray(hist["step"]).tolist() == [10, 20, 30]   # integers kept
    with pytest.raises(jdem.simulate.NeighbourListOverflow, match="record 0"):
        jdem.simulate.raise_if_overflowed(hist)
    # the host loop grows the list instead: same records as with room
    res = jdem.run(small, params, cfg, 30, record_every=10, progress=False)
    _, roomy = rollout(state, params, cfg, 3, 10)
    np.testing.assert_array_equal(res.history["kinetic_energy"], roomy["kinetic_energy"])


def test_an_interrupted_run_is_checkpointed_and_resumes_bit_for_bit(tmp_path, monkeypatch):
    from jdem import simulate

    state, params, cfg, crit = _box()
    params = params._replace(dt=jnp.asarray(0.1 * crit))
    kw = dict(record_every=100, chunk_steps=500, progress=False)
    whole = jdem.run(state, params, cfg, 3000, **kw)
    real, calls = simulate.check_current_step, []

    def interrupt_third_chunk(*a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(simulate, "check_current_step", interrupt_third_chunk)
    path = tmp_path / "run.h5"
    with pytest.raises(KeyboardInterrupt):
        jdem.run(state, params, cfg, 3000, checkpoint=path, **kw)
    monkeypatch.setattr(simulate, "check_current_step", real)
    saved = jdem.io.load_run(path)
    assert saved.attrs["run"]["records_done"] == 10 and saved.attrs["run"]["status"] == "interrupted"
    back = jdem.run(state, params, cfg, 3000, resume=path, **kw)
    for key in whole.history:
        np.testing.assert_array_equal(back.history[key], whole.history[key], err_msg=key)
    for a, b in zip(jax.tree_util.tree_leaves(back.state), jax.tree_util.tree_leaves(whole.state)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(InputError, match="n_steps = 3000"):
        jdem.run(state, params, cfg, 2000, resume=path, **kw)


def test_walls_that_pass_each_other_stop_the_run():
    """Two facing walls of a near spring-less material (1e-9 N/m) driven towards each other:
    the run stops once they have crossed, naming both."""
    from jdem.walls import crossed_pair

    pos, rad, (w, h) = _loose_discs(3, 3, gap=0.3, seed=1)
    p = jdem.make_particles(pos, rad)
    walls = jdem.make_walls([[0.0, 0.0], [0.0, h]], [[0, 1], [0, -1]], n_particles=len(pos),
                            vel=[[0.0, 0.5], [0.0, -0.5]], material=[1, 1])
    params = jdem.make_params(dim=2, n_materials=2, kn=[1e6, 1e-9], ks=[1e6, 1e-9], friction=0.3,
                              dt=1e-5)
    state, cfg = jdem.make_state(p, walls=walls)
    assert crossed_pair(state.walls) is None
    t_cross = h / 1.0                           # closing at 1 m/s
    with pytest.raises(jdem.SimulationDiverged, match="walls 0 and 1 have passed each other"):
        jdem.run(state, params, cfg, 100 * int(np.ceil(2 * t_cross / 1e-5 / 100)),
                 record_every=100, chunk_steps=100, progress=False)
