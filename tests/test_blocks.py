"""Rigid blocks (000 ch. 2, 3): geometry, detection, joint laws and the book's
verification cases against analytic values, in float64."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jdem import InputError
from jdem import blocks as bk
from jdem.blocks import cases, joint

G = 9.81


def _base():
    return bk.rectangle(-2.0, -1.0, 4.0, 1.0)


def _incline(width, height, slope_deg, phi_deg, *, kn=1e9, zeta=0.3):
    return cases.incline(width, height, slope_deg, phi_deg, kn=kn, contact_damping=zeta)


# ----------------------------------------------------------------------------- geometry
def test_polygon_properties_match_closed_forms():
    a, b = 0.6, 0.2
    area, c, polar = bk.polygon_properties(bk.rectangle(1.0, 2.0, a, b))
    assert area == pytest.approx(a * b, rel=1e-12)
    np.testing.assert_allclose(c, [1.0 + a / 2, 2.0 + b / 2], rtol=1e-12)
    assert polar == pytest.approx(a * b * (a * a + b * b) / 12.0, rel=1e-12)
    tri = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 3.0]])     # clockwise order is accepted
    blocks = bk.make_blocks([tri[::-1]], 2.0)
    assert float(blocks.mass[0]) == pytest.approx(2.0 * 4.5, rel=1e-12)
    np.testing.assert_allclose(blocks.pos[0], [1.0, 1.0], rtol=1e-12)
    # right isosceles triangle, legs L: J_c = L^4 / 18
    assert float(blocks.inertia[0]) == pytest.approx(2.0 * 3.0 ** 4 / 18.0, rel=1e-12)


def test_bad_blocks_are_refused_by_name():
    with pytest.raises(InputError, match="not convex"):
        bk.make_blocks([[[0, 0], [2, 0], [1, 0.2], [2, 2], [0, 2]]], 1.0)
    with pytest.raises(InputError, match="density"):
        bk.make_blocks([bk.rectangle(0, 0, 1, 1)], -1.0)
    with pytest.raises(InputError, match="polygon 0"):
        bk.make_blocks([[[0, 0], [1, 1]]], 1.0)
    with pytest.raises(InputError, match="local_damping"):
        bk.make_params(kn=1e9, local_damping=1.0)
    with pytest.raises(InputError, match="kn"):
        bk.make_params(kn=0.0)
    with pytest.raises(InputError, match="symmetric"):
        bk.make_params(kn=[[1e9, 1e8], [2e8, 1e9]])
    with pytest.raises(InputError, match="friction"):
        bk.make_params(kn=np.full((2, 2), 1e9), friction=np.ones((3, 3)))
    blocks = bk.make_blocks([_base(), bk.rectangle(0, 0, 1, 1)], 1.0, fixed=[0], material=[0, 1])
    state, config = bk.make_state(blocks)
    p = bk.make_params(kn=1e9)
    with pytest.raises(InputError, match="material index 1"):
        bk.run(state, p._replace(dt=jnp.asarray(1e-6)), config, 10, progress=False)


def test_flush_faces_give_two_points_and_a_corner_one():
    """Edge-edge: two contact points at the ends of the shared length, with the
    overlap as separation, also when the corners are exactly aligned (a stack of
    equal blocks, the corner-corner case of 000 fig 3-11).  Corner-edge: one."""
    under = bk.rectangle(0.0, 0.0, 1.0, 1.0)
    over = bk.rectangle(0.0, 0.999, 1.0, 1.0)              # aligned corners, 1 mm overlap
    g = bk.pair_geometry(bk.make_blocks([under, over], 1.0), jnp.array([0]), jnp.array([1]))
    np.testing.assert_allclose(g.normal[0], [0.0, 1.0], atol=1e-12)
    assert bool(jnp.all(g.exists[0]))
    np.testing.assert_allclose(g.separation[0], [-1e-3, -1e-3], rtol=1e-9)
    np.testing.assert_allclose(np.sort(g.point[0][:, 0]), [0.0, 1.0], atol=1e-12)
    assert float(g.length[0]) == pytest.approx(1.0, rel=1e-12)
    # a diamond standing on its corner, 2 mm deep
    s = 0.5
    diamond = np.array([[0.5, -0.002], [0.5 + s, s - 0.002], [0.5, 2 * s - 0.002],
                        [0.5 - s, s - 0.002]])
    g = bk.pair_geometry(bk.make_blocks([bk.rectangle(-1, -1, 3, 1), diamond], 1.0),
                         jnp.array([0]), jnp.array([1]))
    ex = np.asarray(g.exists[0])
    sep = np.asarray(g.separation[0])
    assert int(np.sum(ex & (sep < 0))) == 1
    assert float(sep[ex & (sep < 0)][0]) == pytest.approx(-0.002, rel=1e-9)
    # apart by 1 cm: positive separations, no force
    apart = bk.rectangle(0.0, 1.01, 1.0, 1.0)
    g = bk.pair_geometry(bk.make_blocks([under, apart], 1.0), jnp.array([0]), jnp.array([1]))
    assert float(jnp.min(g.separation[0])) == pytest.approx(0.01, rel=1e-9)


# ----------------------------------------------------------------------------- joint law
def test_coulomb_point_law():
    """000 eq 2-1, 2-2: F_n = k_n u_n, dF_s = -k_s du_s, |F_s| <= C + mu F_n while
    intact, then friction only and no tension."""
    kn, ks, mu, c, t = 1e6, 4e5, 0.5, 100.0, 50.0
    fn, fs, intact, slide = joint.coulomb_point(1e-4, 1e-4, 0.0, True, kn, ks, mu, c, t)
    assert float(fn) == pytest.approx(100.0) and float(fs) == pytest.approx(-40.0)
    assert bool(intact) and not bool(slide)
    fn, fs, intact, slide = joint.coulomb_point(1e-4, 1e-3, 0.0, True, kn, ks, mu, c, t)
    assert bool(slide) and not bool(intact)
    assert float(fs) == pytest.approx(-mu * 100.0)            # cohesion lost on failure
    fn, fs, intact, _ = joint.coulomb_point(-4e-5, 0.0, 0.0, True, kn, ks, mu, c, t)
    assert float(fn) == pytest.approx(-40.0) and bool(intact)  # below the tensile strength
    fn, fs, intact, _ = joint.coulomb_point(-6e-5, 0.0, 0.0, True, kn, ks, mu, c, t)
    assert float(fn) == 0.0 and not bool(intact)
    fn, _, _, _ = joint.coulomb_point(-1e-5, 0.0, 0.0, False, kn, ks, mu, c, t)
    assert float(fn) == 0.0


def test_barton_friction_angle():
    """000 eq 3-43: phi = phi_b + JRC log10(JCS / sigma_n)."""
    mu = joint.barton_friction(1e6, np.deg2rad(30.0), 10.0, 1e8)
    assert float(mu) == pytest.approx(np.tan(np.deg2rad(30.0 + 10.0 * 2.0)), rel=1e-12)
    assert float(joint.barton_friction(1e-9, 0.5, 10.0, 1e8)) == pytest.approx(
        np.tan(np.deg2rad(70.0)))


# ----------------------------------------------------------------------------- verification
def test_resting_block_oscillates_at_the_spring_frequency():
    """A block dropped onto two contact points (000 eq 2-1) with no damping
    bounces at omega = sqrt(2 k_n / m) about the static overlap m g / (2 k_n)."""
    state, p, config = _incline(0.5, 0.5, 0.0, 30.0, zeta=0.0)
    m = float(state.blocks.mass[1])
    p = p._replace(dt=jnp.asarray(0.1 * float(p.dt)))
    kn = float(p.kn[0, 0])
    period = 2 * np.pi * np.sqrt(m / (2 * kn))
    n = int(round(3 * period / float(p.dt)))
    _, hist = bk.run(state, p, config, n, record_every=1, progress=False)
    y = hist["pos"][:, 1, 1] - 0.25
    static = -m * G / (2 * kn)
    assert float(np.mean(y)) == pytest.approx(static, rel=2e-3)
    # period from the times of the lowest points
    k = np.flatnonzero((y[1:-1] < y[:-2]) & (y[1:-1] <= y[2:])) + 1
    measured = np.mean(np.diff(k)) * float(p.dt)
    assert measured == pytest.approx(period, rel=2e-3)


@pytest.mark.parametrize("slope, slides", [(28.0, False), (32.0, True), (40.0, True)])
def test_block_on_incline_slides_iff_slope_exceeds_friction_angle(slope, slides):
    """000 §2.2 Coulomb slip: on a 30 degree joint a block stays below 30 degrees and
    slides above, with acceleration g (sin theta - mu cos theta)."""
    state, p, config = _incline(0.5, 0.5, slope, 30.0)
    n = int(0.3 / float(p.dt))
    _, hist = bk.run(state, p, config, n, record_every=50, progress=False)
    x = hist["pos"][:, 1, 0]
    t = hist["step"] * float(p.dt)
    if not slides:
        assert abs(x[-1]) < 1e-4 and float(np.max(np.abs(hist["angle"][:, 1]))) < 1e-4
        return
    th, mu = np.deg2rad(slope), np.tan(np.deg2rad(30.0))
    late = t > 0.05
    accel = 2 * np.polyfit(t[late], x[late], 2)[0]
    assert accel == pytest.approx(G * (np.sin(th) - mu * np.cos(th)), rel=1e-3)


@pytest.mark.parametrize("width, height, slope, expect", [
    (0.5, 0.5, 20.0, "stable"),        # tan 20 < b/h = 1, 20 < phi
    (0.2, 0.8, 20.0, "topples"),       # tan 20 > b/h = 0.25, 20 < phi
    (0.5, 0.5, 35.0, "slides"),        # tan 35 < b/h, 35 > phi
    (0.2, 0.8, 35.0, "topples"),       # static chart: both; the pivot holds (|F_t|/F_n 0.35)
    (0.6, 1.0, 40.0, "slides"),        # static chart: both; mu = 0.58 < b/h = 0.6: no turn
    (0.5, 1.0, 50.0, "both"),          # pivot needs |F_t|/F_n = 0.64 > mu; mu > b/h
])
def test_block_on_incline_topples_or_slides(width, height, slope, expect):
    """The regimes of a block on an incline, phi = 30 degrees: the simulation
    does at onset what rigid-body dynamics says (:func:`jdem.blocks.cases.onset_regime`)."""
    assert cases.onset_regime(width, height, slope, 30.0) == expect
    state, p, config = _incline(width, height, slope, 30.0)
    _, hist = bk.run(state, p, config, int(0.3 / float(p.dt)), record_every=50,
                     progress=False)
    assert cases.observed_regime(hist, width, height) == expect


def test_stack_settles_with_base_reaction_equal_to_weight():
    """Three blocks stacked off-centre on a fixed base, damped to rest (local
    damping 0.7, 000 §3.2): the base carries their weight to 1 %, the stack
    does not move sideways."""
    state, p, config = cases.stack([(-0.5, 0.0, 1.0, 0.4), (-0.3, 0.401, 0.7, 0.3),
                                    (-0.2, 0.703, 0.3, 0.5)])
    blocks = state.blocks
    state, hist = bk.run(state, p, config, 20000, record_every=500, progress=False)
    _, force, _, _ = bk.contact_forces(state, p)
    weight = float(jnp.sum(blocks.mass[1:])) * G
    assert float(force[0, 1]) == pytest.approx(-weight, rel=1e-2)
    assert abs(float(force[0, 0])) < 1e-3 * weight
    assert float(np.max(np.abs(hist["pos"][-1, 1:, 0] - np.asarray(blocks.pos[1:, 0])))) < 1e-4
    assert float(np.max(np.abs(hist["vel"][-1]))) < 1e-4


def test_wave_across_a_joint_transmits_as_theory_says():
    """000 §9.2.1: a tone burst crosses a linear joint; T and R measured from
    int v^2 dt before and after the joint (eq 9-2, 9-3, 9-6) match the exact
    values of the block row to 0.5 % and the continuum joint |T| = (1 +
    (omega Z / 2K)^2)^(-1/2) to 0.02 (the row's dispersion at 20 blocks per
    wavelength: measured T 0.887 / 0.439 against 0.894 / 0.447, R 0.461 / 0.899
    against 0.447 / 0.894 for omega Z / 2K = 0.5 / 2); no energy is lost
    (eq 9-1: A^2 < 1e-4)."""
    for ratio in (0.5, 2.0):
        d = cases.wave_across_joint(ratio)
        print(ratio, {k: v for k, v in d.items() if isinstance(v, float)})
        assert d["T"] == pytest.approx(d["T_lattice"], rel=5e-3)
        assert d["R"] == pytest.approx(d["R_lattice"], rel=5e-3)
        assert abs(d["T"] - d["T_continuum"]) < 0.02
        assert abs(d["R"] - d["R_continuum"]) < 0.02
        assert d["A"] ** 2 < 1e-4
    assert cases.continuum_transmission(1.0, 2.0, 1.0)[0] == pytest.approx(2 ** -0.5)


def test_glued_joint_holds_up_to_its_tensile_strength():
    """A block hanging under a fixed one on a glued joint of tensile strength T
    per point (two points): it hangs while its weight is below 2 T and falls
    once it is above."""
    top = bk.rectangle(-1.0, 0.0, 2.0, 0.5)
    hang = bk.rectangle(-0.25, -0.5, 0.5, 0.5)
    blocks = bk.make_blocks([top, hang], 2500.0, fixed=[0])
    weight = float(blocks.mass[1]) * G
    for strength, falls in [(0.6 * weight, False), (0.4 * weight, True)]:
        state, config = bk.make_state(blocks)
        p = bk.make_params(kn=1e9, friction=0.5, tension=strength, contact_damping=0.5)
        p = p._replace(dt=jnp.asarray(bk.recommended_timestep(blocks, p)))
        state = bk.glue_joints(state, p, config)
        _, hist = bk.run(state, p, config, 8000, record_every=500, progress=False)
        drop = float(hist["pos"][0, 1, 1] - hist["pos"][-1, 1, 1])
        assert (drop > 0.05) == falls, (strength / weight, drop)


def test_timestep_above_critical_is_refused():
    state, p, config = _incline(0.5, 0.5, 0.0, 30.0)
    crit = float(bk.critical_timestep(state.blocks, p))
    with pytest.raises(InputError, match="params.dt"):
        bk.run(state, p._replace(dt=jnp.asarray(1.5 * crit)), config, 10, progress=False)


# ----------------------------------------------------------------------------- gradients
@pytest.mark.slow
def test_friction_and_stiffness_recovered_from_a_sliding_history():
    """Differentiable block method: the friction coefficient and the joint
    stiffness of a block sliding down a 35 degree slope (phi = 30) are recovered
    from its recorded downhill travel and settlement (least squares,
    forward-mode Jacobian through the rollout, by jdem.calibrate.fit_model: the
    calibration's bounded transform, solver and intervals), from -20 % and -50 % starts.
    (A start above the slope's angle would not slide: no information on mu; the
    contact dashpots at 0.7 of critical damp the bounce, which would otherwise
    make the misfit oscillate in k_n.)  Slow (~2 min): the block path's
    derivative is checked by default in tests/test_blocks_yielding.py, the fit
    machinery on an oscillator in tests/test_calibrate.py."""
    from jdem.calibrate import fit_model

    state, p, config = _incline(0.5, 0.5, 35.0, 30.0, kn=2e8, zeta=0.7)
    n_rec, every = 40, 100

    def history(mu, kn):
        table = lambda v: jnp.reshape(v, (1, 1))      # noqa: E731  one joint kind
        q = p._replace(friction=table(mu), kn=table(kn), ks=table(kn / 2.5))
        _, h = bk.rollout(state, q, config, n_rec, every)
        return h["pos"][:, 1, 0], h["pos"][:, 1, 1] - 0.25

    truth = (float(p.friction[0, 0]), float(p.kn[0, 0]))
    x_t, y_t = history(*truth)

    fit = fit_model(lambda v: history(v["friction"], v["kn"]), (x_t, y_t),
                    {"friction": 0.8 * truth[0], "kn": 0.5 * truth[1]})
    np.testing.assert_allclose([fit.values["friction"] / truth[0], fit.values["kn"] / truth[1]],
                               [1.0, 1.0], rtol=1e-3)
    assert fit.converged and fit.loss < 1e-10 and not fit.undetermined
    for name in ("friction", "kn"):     # an exact-data fit: tiny, finite standard errors
        assert 0 <= fit.stderr[name] < 1e-3 * fit.values[name]


# ----------------------------------------------------------------------------- generation, files
def test_joint_sets_cut_a_region_into_convex_blocks():
    """Two persistent sets (dip 0 at 0.5 m, dip 90 at 0.4 m) cut a 2 x 1 m
    region into 5 x 2 blocks whose areas sum to the region's; an inclined set
    keeps the total area and every block convex (make_blocks checks)."""
    region = bk.rectangle(0.0, 0.0, 2.0, 1.0)
    polys = bk.cut_region(region, [bk.JointSet(0.0, 0.5), bk.JointSet(90.0, 0.4)])
    assert len(polys) == 10
    areas = [bk.polygon_properties(p)[0] for p in polys]
    np.testing.assert_allclose(areas, 0.2, rtol=1e-12)
    polys = bk.cut_region(region, [bk.JointSet(35.0, 0.3, 0.1), bk.JointSet(110.0, 0.45)])
    assert sum(bk.polygon_properties(p)[0] for p in polys) == pytest.approx(2.0, rel=1e-12)
    blocks = bk.make_blocks(polys, 2600.0)
    assert int(jnp.sum(blocks.valid)) == len(polys)
    with pytest.raises(InputError, match="spacing"):
        bk.cut_region(region, [bk.JointSet(0.0, 0.0)])
    with pytest.raises(InputError, match="persistence"):
        bk.cut_region(region, [bk.JointSet(0.0, 0.5, persistence=1.5)])


def test_rock_bridges_of_a_non_persistent_set_hold_their_blocks():
    """A horizontal set of persistence 0.5 (joint pieces 0.5 m, bridges 0.5 m)
    under a fixed top row: the blocks hanging from bridges stay (glued with
    tension), those under joint pieces fall."""
    region = bk.rectangle(0.0, 0.0, 2.0, 1.0)
    sets = [bk.JointSet(0.0, 0.5, persistence=0.5, trace_length=0.5), bk.JointSet(90.0, 0.5)]
    polys = bk.cut_region(region, sets)
    centres = np.array([bk.polygon_properties(p)[1] for p in polys])
    top = centres[:, 1] > 0.5
    blocks = bk.make_blocks(polys, 2600.0, fixed=np.flatnonzero(top))
    state, config = bk.make_state(blocks)
    weight = float(blocks.mass[0]) * G
    p = bk.make_params(kn=1e9, friction=0.0, tension=weight, contact_damping=0.5)
    p = p._replace(dt=jnp.asarray(bk.recommended_timestep(blocks, p)))
    state = bk.glue_joints(state, p, config, where=lambda pt, n: bk.bridge_mask(pt, n, sets))
    _, hist = bk.run(state, p, config, 6000, record_every=500, progress=False)
    drop = hist["pos"][0, :, 1] - hist["pos"][-1, :, 1]
    bottom = ~top
    on_bridge = bottom & (np.mod(centres[:, 0], 1.0) > 0.5)
    assert np.all(drop[on_bridge] < 1e-4) and np.all(drop[bottom & ~on_bridge] > 0.02)


def test_block_file_round_trip_and_errors(tmp_path):
    polys = bk.cut_region(bk.rectangle(0.0, 0.0, 1.0, 1.0), [bk.JointSet(30.0, 0.3)])
    bk.write_polygons(tmp_path / "b.txt", polys)
    back = bk.read_polygons(tmp_path / "b.txt")
    assert len(back) == len(polys)
    for a, b in zip(polys, back):
        np.testing.assert_array_equal(a, b)
    (tmp_path / "bad.txt").write_text("# blocks\n0,0 1,0 1,1\n0,0 1;0 1,1\n")
    with pytest.raises(InputError, match="bad.txt:3"):
        bk.read_polygons(tmp_path / "bad.txt")
    with pytest.raises(InputError, match="does not exist"):
        bk.read_polygons(tmp_path / "none.txt")


def test_block_run_restarts_bit_for_bit_from_hdf5(tmp_path):
    """Save a sliding block's state and params half-way (jdem.io), reload, go on:
    the same final state as one uninterrupted run, bit for bit."""
    from jdem import io

    state, p, config = _incline(0.5, 0.5, 35.0, 30.0)
    whole, _ = bk.rollout(state, p, config, 4, 100)
    half, _ = bk.rollout(state, p, config, 2, 100)
    io.save_run(tmp_path / "half.h5", state=half, params=p, config=config)
    back = io.load_run(tmp_path / "half.h5")
    assert type(back.state).__name__ == "BlockState" and back.config == config
    again, _ = bk.rollout(back.state, back.params, back.config, 2, 100)
    for a, b in zip(jax.tree_util.tree_leaves(whole), jax.tree_util.tree_leaves(again)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_host_run_is_the_rollout_and_its_short_last_chunk_compiles_nothing_new():
    """A run of 53 records goes as chunks of 50 and 3: the 3 run in the program of
    the 50 (records past ``n_run`` skipped), so the host loop compiles one chunk
    program, and its history and final state are those of one 53-record rollout,
    bit for bit."""
    state, p, config = _incline(0.5, 0.5, 35.0, 30.0)
    final, hist = bk.run(state, p, config, 53 * 7, record_every=7, progress=False)
    before = bk.rollout._cache_size()
    final2, hist2 = bk.run(state, p, config, 54 * 7, record_every=7, progress=False)
    assert bk.rollout._cache_size() == before        # 50 + 4 reuses the same program
    whole, ref = bk.rollout(state, p, config, 53, 7)
    assert hist["pos"].shape[0] == 53 and hist2["pos"].shape[0] == 54
    for key in ref:
        np.testing.assert_array_equal(hist[key], np.asarray(ref[key]))
    for a, b in zip(jax.tree_util.tree_leaves(final), jax.tree_util.tree_leaves(whole)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert int(final2.step) == 54 * 7


def test_readme_block_example_runs_and_settles():
    """The README's block example, as written: it runs, and the floor ends up
    carrying the mass's weight (to 2 %, still settling after 30,000 steps)."""
    import pathlib
    import re

    text = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = text[text.index("## Rigid blocks"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    scope = {}
    exec(compile(code, "README.md (blocks)", "exec"), scope)
    state, params, blocks = scope["state"], scope["params"], scope["blocks"]
    _, force, _, _ = bk.contact_forces(state, params)
    weight = float(jnp.sum(blocks.mass[1:])) * G
    assert -float(force[0, 1]) == pytest.approx(weight, rel=2e-2)


def test_rough_joint_holds_a_block_a_smooth_one_lets_slide():
    """Barton's joint (000 eq 3-43) in the contact law: a flat block (b / h = 10,
    so the two points carry nearly equal loads) on a joint with phi_b = 25
    degrees, JRC 10 and JCS chosen so that the Barton angle at its normal stress
    is theta* (solved below, ~35 degrees): it stays 2 degrees below theta* and
    slides 2 degrees above it; without roughness it slides at both slopes."""
    width, height, phi_b, jrc = 1.0, 0.1, 25.0, 10.0
    mass = 2500.0 * width * height
    jcs = 1.2e5

    def barton(theta):        # the joint's angle at the block's normal stress [deg]
        sigma = mass * G * np.cos(np.deg2rad(theta)) / width
        return phi_b + jrc * np.log10(jcs / sigma)

    lo, hi = 20.0, 60.0
    for _ in range(60):       # theta* = barton(theta*)
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if barton(mid) > mid else (lo, mid)
    star = 0.5 * (lo + hi)
    assert 30.0 < star < 45.0
    for slope, rough_slides in ((star - 2.0, False), (star + 2.0, True)):
        for rough in (True, False):
            state, p, config = _incline(width, height, slope, phi_b)
            if rough:   # full_like: not weak-typed, so the smooth runs reuse the compilation
                p = p._replace(jrc=jnp.full_like(p.jrc, jrc), jcs=jnp.full_like(p.jcs, jcs))
            _, hist = bk.run(state, p, config, int(0.3 / float(p.dt)), record_every=100,
                             progress=False)
            slid = float(hist["pos"][-1, 1, 0]) > 1e-3
            assert slid == (rough_slides if rough else True), (slope, rough)


def test_vmapped_rollout_over_friction_equals_single_runs():
    """jax.vmap over the joint friction (a batch of three parameter sets in one
    compiled call) gives each member's single run."""
    state, p, config = _incline(0.5, 0.5, 35.0, 30.0)
    mus = jnp.tan(jnp.deg2rad(jnp.asarray([25.0, 30.0, 40.0])))

    def run_one(mu):
        _, h = bk.rollout(state, p._replace(friction=jnp.reshape(mu, (1, 1))), config, 5, 100)
        return h["pos"][:, 1, 0]

    batch = jax.vmap(run_one)(mus)
    for k in range(3):
        np.testing.assert_allclose(batch[k], run_one(mus[k]), rtol=1e-12, atol=1e-15)
    assert float(batch[2, -1]) < 1e-4 < float(batch[0, -1])      # the 40-degree joint holds


def test_diverging_block_run_stops_with_its_last_good_state():
    """A block glued to its base (so that it cannot fly off) run at 30x the
    critical step (the check bypassed: a user gets an InputError first) is
    flung through its base at hundreds of m/s, far more than half the skin per
    step: the run stops with SimulationDiverged carrying the finite state from
    before, instead of letting it tunnel and fall."""
    from unittest import mock

    from jdem.simulate import SimulationDiverged

    state, p, config = _incline(0.5, 0.5, 0.0, 30.0, zeta=0.0)
    p = p._replace(tension=jnp.full((1, 1), 1e30), cohesion=jnp.full((1, 1), 1e30))
    state = bk.glue_joints(state, p, config, tolerance=1e-9)
    assert float(jnp.sum(state.contacts.shear[:, 2:])) == 2.0      # both points glued
    fast = p._replace(dt=30.0 * p.dt)
    with mock.patch.object(bk.cycle, "critical_timestep", lambda *a, **k: jnp.inf):
        with pytest.raises(SimulationDiverged) as err:
            bk.run(state, fast, config, 200_000, record_every=100, progress=False)
    good = err.value.last_good_state
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(good.blocks)
               if jnp.issubdtype(x.dtype, jnp.floating))
    assert err.value.step == int(good.step)


def test_joint_history_follows_its_pair_when_a_rebuild_reorders_the_list():
    """000 §2.3.3: the shear force of a contact is history.  A block resting on a
    fixed base under a sideways load below mu m g holds a stretched shear spring
    (pair (1, 2)).  A third block (index 0) is driven past them, so the list is
    rebuilt and the new pairs (0, 1), (0, 2) sort before (1, 2): the row of
    (1, 2) moves, and its shear forces and intact flags must move with it (a
    carry by row position would hand them to another pair, and the resting block
    would lose its spring and slip)."""
    rest = bk.rectangle(0.0, 0.0, 1.0, 0.5)
    base = bk.rectangle(-1.0, -1.0, 3.0, 1.0)
    runner = bk.rectangle(-6.0, 0.6, 0.5, 0.5)
    blocks = bk.make_blocks([runner, rest, base], 2500.0, fixed=[0, 2],
                            vel=[[40.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    weight = float(blocks.mass[1]) * G
    blocks = blocks._replace(ext_force=blocks.ext_force.at[1, 0].set(0.3 * weight))
    p = bk.make_params(kn=1e8, friction=0.6, contact_damping=0.3, local_damping=0.7)
    p = p._replace(dt=jnp.asarray(bk.recommended_timestep(blocks, p)))
    state, config = bk.make_state(blocks)

    def rows(s):
        c = s.contacts
        return {(int(i), int(j)): k for k, (i, j, v) in
                enumerate(zip(np.asarray(c.i), np.asarray(c.j), np.asarray(c.valid))) if v}

    settle = jax.jit(lambda s: jax.lax.fori_loop(0, 2000, lambda _, x: bk.step(x, p, config), s))
    state = state._replace(blocks=state.blocks._replace(
        vel=state.blocks.vel.at[0].set(0.0)))                 # the runner waits
    state = settle(state)
    before = rows(state)
    assert set(before) == {(1, 2)}
    hist = np.asarray(state.contacts.shear[before[(1, 2)]])
    assert np.all(hist[2:] == 0)                              # no glued points
    assert abs(np.sum(hist[:2])) == pytest.approx(0.3 * weight, rel=1e-3)   # the load
    # the runner sets off and passes over the resting block within a few steps
    state = state._replace(blocks=state.blocks._replace(
        vel=state.blocks.vel.at[0].set(jnp.asarray([40.0, 0.0]))))
    one = jax.jit(lambda s: bk.step(s, p, config))
    for _ in range(int(6.0 / 40.0 / float(p.dt)) + 1):       # 6 m of travel lands it above
        state = one(state)
        if (0, 1) in rows(state):
            break
    after = rows(state)
    assert (0, 1) in after and after[(1, 2)] != before[(1, 2)]
    np.testing.assert_allclose(np.asarray(state.contacts.shear[after[(1, 2)]]), hist,
                               rtol=1e-6, atol=1e-9 * weight)


@pytest.mark.parametrize("slope, expect", [(20.0, 1), (45.0, 2)])
def test_contact_states_tell_sticking_from_sliding_and_are_drawn(tmp_path, slope, expect):
    """A block on a 30-degree joint: below the friction angle both of its contact
    points stick, above it both slide (jdem.plot.contact_states); the contact-state
    figure is written."""
    from jdem.plot import contact_states, plot_blocks

    state, p, config = _incline(0.5, 0.5, slope, 30.0)
    state, _ = bk.run(state, p, config, 400, record_every=400, progress=False)
    _, _, _, info = bk.contact_forces(state, p)
    kind = contact_states(info)
    assert sorted(kind[kind >= 0].tolist()) == [expect, expect]
    plot_blocks(state, p, tmp_path / "contacts.png", color="contacts")
    assert (tmp_path / "contacts.png").stat().st_size > 10_000
    with pytest.raises(InputError, match="color"):
        plot_blocks(state, p, color="stress")


# ----------------------------------------------------------------------------- 000 §9.2.2
def _basalt_rigid_moduli(s=0.2):
    joints = {k: v for k, v in cases.BASALT_JOINTS.items() if k != "spacing"}
    return cases.jointed_mass_moduli_rigid(**joints, s_s=s, s_n=s)


@pytest.mark.parametrize("stagger", [False, True])
def test_jointed_mass_under_the_books_biaxial_cycle(stagger):
    """000 §9.2.2 with the book's basalt joints (20 cm spacing) and loading: 5 MPa
    held along the rows, 2 -> 10 -> 2 MPa across them, on a 4 x 5 wall of blocks
    staggered as in fig 9-3 or in a square grid.  In the rigid-block limit of
    eq 9-7…9-10: E_n = k_nh s_n = 106.4 GPa at every level, loading and
    unloading.  In the grid nu_ns = 0 (the strain along the rows does not move
    while the load across them does) and E_s = k_nv s_s = 79.2 GPa.  (The
    running bond's courses shorten as staircases, which shears its horizontal
    joints: measured, its E_s is 1.8 % stiffer, and back at 2 MPa some of those
    joints slip and its strain along the rows moves by 1.5 %; eq 9-8's rigid
    limit has no such term.)"""
    theory = _basalt_rigid_moduli()
    sigma_n = np.array([2.0, 6.0, 10.0, 6.0, 2.0]) * 1e6
    eps, _ = cases.load_jointed_mass(cases.jointed_mass(4, 5, stagger=stagger), sigma_n,
                                     np.full(sigma_n.size, 5e6), steps_per_level=3000)
    np.testing.assert_allclose(sigma_n / (eps[:, 0] - eps[0, 0] + sigma_n[0] / theory["E_n"]),
                               theory["E_n"], rtol=1e-3)
    np.testing.assert_allclose(np.diff(sigma_n) / np.diff(eps[:, 0]), theory["E_n"], rtol=1e-3)
    if not stagger:
        np.testing.assert_allclose(eps[:, 1], eps[0, 1], rtol=1e-3)
        np.testing.assert_allclose(5e6 / eps[:, 1], theory["E_s"], rtol=1e-3)


@pytest.mark.parametrize("corner_radius", [0.0, 0.002])
def test_corners_of_a_square_grid_push_unless_faces_are_stiff_per_area_or_corners_round(
        corner_radius):
    """Why joints have a face stiffness or rounded corners: with the same springs
    as fixed point stiffnesses and sharp corners, the grid's diagonal neighbours
    overlap in a sliver at each four-block corner once the mass shortens both
    ways (000 fig 3-11), and each sliver is an edge-edge contact of two full
    points: E_n comes out 2.3 x k_nh s_n.  Corners rounded with 2 mm arcs (000
    eq 3-34, 3-35, the book's other remedy) keep the diagonal neighbours apart:
    E_n and E_s are the rigid-block values again."""
    theory = _basalt_rigid_moduli()
    case = cases.jointed_mass(4, 5, stagger=False)
    p = case.params
    case = case._replace(params=p._replace(kn_face=jnp.zeros_like(p.kn_face),
                                           ks_face=jnp.zeros_like(p.ks_face),
                                           corner_radius=jnp.asarray(corner_radius)))
    sigma_n = np.array([2.0, 10.0]) * 1e6
    eps, _ = cases.load_jointed_mass(case, sigma_n, np.full(2, 5e6), steps_per_level=3000)
    e_n = (sigma_n[1] - sigma_n[0]) / (eps[1, 0] - eps[0, 0])
    if corner_radius == 0.0:
        assert e_n > 2.0 * theory["E_n"]
    else:
        assert e_n == pytest.approx(theory["E_n"], rel=1e-3)
        np.testing.assert_allclose(5e6 / eps[:, 1], theory["E_s"], rtol=1e-3)


def test_rounded_corners_follow_eq_3_34_and_3_35():
    """000 eq 3-34, 3-35 with arcs of radius R: two squares meeting corner to
    corner across a diagonal gap g (in x and in y) touch along the diagonal with
    the gap sqrt(2) (g + 2 R) - 2 R; a sliver overlap of the sharp corners is no
    contact once rounded; flat faces keep their gap over the straight part of the
    face (length L - 2 R); a turned square's corner meets a face with its arc."""
    from jdem.blocks import detect

    R = 0.01
    pair = (jnp.array([0]), jnp.array([1]))
    a = bk.rectangle(0.0, 0.0, 1.0, 1.0)
    for g in (1e-3, -1e-3):
        blocks = bk.make_blocks([a, bk.rectangle(1 + g, 1 + g, 1.0, 1.0)], 1.0)
        geo = detect.pair_geometry(blocks, *pair, R)
        assert bool(geo.exists[0, 0]) and not bool(geo.exists[0, 1])
        assert float(geo.separation[0, 0]) == pytest.approx(np.sqrt(2) * (g + 2 * R) - 2 * R,
                                                            rel=1e-9)
        np.testing.assert_allclose(np.asarray(geo.normal[0]), [np.sqrt(0.5)] * 2, rtol=1e-9)
        sharp = detect.pair_geometry(blocks, *pair)
        assert (float(sharp.separation.min()) < 0) == (g < 0)
    flat = bk.make_blocks([a, bk.rectangle(0.2, 0.999, 0.5, 0.5)], 1.0)
    geo = detect.pair_geometry(flat, *pair, R)
    np.testing.assert_allclose(np.asarray(geo.separation[0]), -1e-3, rtol=1e-9)
    assert float(geo.length[0]) == pytest.approx(0.5 - 2 * R, rel=1e-9)
    # eq 3-35: a square turned by 20 degrees, its sharp corner 5 mm into a base;
    # the arc's centre lies R / sin(45 deg) from the corner on the bisector
    c, s_ = np.cos(np.deg2rad(20.0)), np.sin(np.deg2rad(20.0))
    square = np.array([[-0.2, -0.2], [0.2, -0.2], [0.2, 0.2], [-0.2, 0.2]]) @ np.array(
        [[c, s_], [-s_, c]])
    square[:, 1] -= square[:, 1].min() + 5e-3
    low = square[np.argmin(square[:, 1])]
    bisector = (np.mean(square, axis=0) - low) / np.linalg.norm(np.mean(square, axis=0) - low)
    centre = low + np.sqrt(2) * R * bisector
    blocks = bk.make_blocks([bk.rectangle(-1.0, -1.0, 2.0, 1.0), square], 1.0)
    geo = detect.pair_geometry(blocks, *pair, R)
    on = np.asarray(geo.exists[0]) & (np.asarray(geo.separation[0]) < 0)
    assert on.sum() == 1
    assert float(np.asarray(geo.separation[0])[on][0]) == pytest.approx(centre[1] - R, rel=1e-9)
    assert centre[1] - R > -5e-3                  # shallower than the sharp corner
    with pytest.raises(InputError, match="corner_radius"):
        bk.recommended_timestep(blocks, bk.make_params(kn=1e8, corner_radius=0.2))


def test_zero_corner_radius_as_an_array_is_the_sharp_geometry():
    """The engine passes ``corner_radius`` as an array, so radius 0 runs the
    rounding path: it must give the sharp geometry exactly, also for blocks with
    fewer vertices than the padded capacity (padding repeats vertex 0)."""
    from jdem.blocks import detect

    polys = bk.cut_region(bk.rectangle(0.0, 0.0, 3.0, 2.0),
                          [bk.JointSet(dip=30.0, spacing=0.35), bk.JointSet(100.0, 0.5)])
    blocks = bk.make_blocks(polys, 2600.0)
    counts = np.asarray(blocks.vert_valid).sum(axis=1)
    assert counts.min() < blocks.vert_valid.shape[1]          # some rows padded
    i, j = np.triu_indices(len(polys), 1)
    # both compiled: eager and compiled runs differ at round-off, which flips the
    # reference edge of pairs whose blocks touch exactly (separation 0)
    sharp = jax.jit(lambda b, i, j: detect.pair_geometry(b, i, j))(
        blocks, jnp.asarray(i), jnp.asarray(j))
    zero = jax.jit(detect.pair_geometry)(blocks, jnp.asarray(i), jnp.asarray(j),
                                         jnp.asarray(0.0))
    for field in sharp._fields:
        np.testing.assert_array_equal(np.asarray(getattr(zero, field)),
                                      np.asarray(getattr(sharp, field)), err_msg=field)


def test_face_stiffness_scales_with_the_contact_length():
    """000 fig 3-13: an edge-edge contact of length L on a joint of k [Pa/m] is two
    points of k L / 2.  A block resting flat on a base sinks m g / (k L); one
    resting partly over the base's edge has points of k L / 2 with L the part
    on the base; a tilted block touching with one corner keeps the point
    stiffness k_n."""
    k_face, kn, b = 2e9, 1e8, 0.4
    base = bk.rectangle(-1.0, -1.0, 2.0, 1.0)            # its top face ends at x = 1
    p = bk.make_params(kn=kn, kn_face=k_face, local_damping=0.7)
    for x0, length in ((0.0, b), (0.7, 0.3)):
        blocks = bk.make_blocks([base, bk.rectangle(x0, 0.0, b, 0.3)], 2500.0, fixed=[0])
        p = p._replace(dt=jnp.asarray(bk.recommended_timestep(blocks, p)))
        state, config = bk.make_state(blocks)
        state, _ = bk.run(state, p, config, 6000, record_every=6000, progress=False)
        _, force, _, info = bk.contact_forces(state, p)
        row = int(np.flatnonzero(np.asarray(info.active).any(axis=1))[0])
        fn, overlap = np.asarray(info.fn[row]), np.asarray(info.overlap[row])
        np.testing.assert_allclose(fn / overlap, k_face * length / 2, rtol=1e-6)
        weight = float(blocks.mass[1]) * G
        assert float(np.sum(fn)) == pytest.approx(weight, rel=1e-4)
        if x0 == 0.0:
            assert 0.15 - float(state.blocks.pos[1, 1]) == pytest.approx(
                weight / (k_face * length), rel=1e-3)
    # a square turned by 20 degrees, its lowest corner 0.1 mm into the base
    c, s_ = np.cos(np.deg2rad(20.0)), np.sin(np.deg2rad(20.0))
    square = np.array([[-0.2, -0.2], [0.2, -0.2], [0.2, 0.2], [-0.2, 0.2]]) @ np.array(
        [[c, s_], [-s_, c]])
    square[:, 1] -= square[:, 1].min() + 1e-4
    blocks = bk.make_blocks([base, square], 2500.0, fixed=[0])
    state, _ = bk.make_state(blocks)
    _, _, _, info = bk.contact_forces(state, p)
    act = np.asarray(info.active)
    assert act.sum() == 1
    assert float(np.asarray(info.fn)[act][0]) == pytest.approx(kn * 1e-4, rel=1e-6)


def test_gradients_are_finite_when_the_first_block_is_free_and_corners_are_rounded():
    """The pair list's padding rows pair block 0 with itself.  With rounded
    corners the nearest-vertex distance of such a row is 0; its square root had
    an infinite derivative, so a gradient through the steps of a system whose
    block 0 is free was NaN (found coupling discs to a single free block).
    Now d(velocity after two steps)/d(applied force) is 2 dt / m."""
    blocks = bk.make_blocks([bk.rectangle(0.0, 0.0, 0.2, 0.2)], 2500.0)
    state, config = bk.make_state(blocks)
    params = bk.make_params(kn=1e6, gravity=(0.0, 0.0), corner_radius=0.01)
    params = params._replace(dt=jnp.asarray(1e-4))

    def vx(force):
        b = state.blocks._replace(ext_force=state.blocks.ext_force.at[0, 0].set(force))
        s = state._replace(blocks=b)
        for _ in range(2):
            s = bk.step(s, params, config, False, True)
        return s.blocks.vel[0, 0]

    grad = float(jax.jit(jax.grad(vx))(jnp.asarray(1.0)))
    np.testing.assert_allclose(grad, 2e-4 / float(blocks.mass[0]), rtol=1e-12)
