"""Rock specimen tests (jdem.labtests): uniaxial compression (002 §2), the
strain-energy ratio of 002 §1.4, the Brazilian test, restarts and ``jdem ucs``.

Runtime: one rectangle specimen (~330 discs, 0.7 cm x 1.4 cm) serves every
rectangle test, so each ``jdem.run`` chunk compiles once per shape: once
batched (the 5-member sweep) and once unbatched (energy ratio, restart and the
CLI, which regenerates the same specimen from the same seed).  The Brazilian
disc compiles once more.

The platen step (3 nm on 1.4 cm) is faster than the seed's 1 nm on 10 cm but
keeps ~10 wave transits through the specimen before the peak (the number of
transits to the peak is eps_peak c dt / platen_step, independent of the size).
"""
import functools

import numpy as np
import pytest

from jdem import InputError, cli, io
from jdem import labtests as lt
from jdem.specimen import generate

SIZE = (0.007, 0.014)            # [m] width x height
RADII = (0.2e-3, 0.35e-3)        # [m]
SEED = 2
N_BAR = 5.0                      # target coordination (002 §1.4: lambda ~ 1)
STEP = 1.5e-9                    # platen step [m] of the sweep
KAPPAS = (0.0, 3e-3, 2.4e-2)     # fracture strains of the sweep
SWEEP_STRAIN = 1.2e-3            # the slow member's final strain (the others reach 2x)


@pytest.fixture(scope="module")
def rect():
    return generate("rectangle", SIZE, *RADII, seed=SEED, target_coordination=N_BAR)


@pytest.fixture(scope="module")
def sweep(rect):
    """One batched run: kappa = 0, 0.3 %, 2.4 % at STEP, plus 2.4 % at STEP / 2
    and STEP / 4 (the loading-rate check).  The slowest member reaches
    SWEEP_STRAIN, the STEP / 2 member twice that, the others four times."""
    params = lt.rock_params(2, kappa=list(KAPPAS) + [KAPPAS[-1]] * 2)
    hist, state, config = lt.ucs_test(rect, params,
                                      platen_step=[STEP, STEP, STEP, STEP / 2, STEP / 4],
                                      max_strain=SWEEP_STRAIN)
    return hist, state, lt.peak_summary(hist)


@functools.lru_cache(maxsize=None)
def _params():
    return lt.rock_params(2, kappa=3e-3)


# ----------------------------------------------------------------------------- set-up
def test_rock_params_two_materials_and_batched_kappa():
    p = lt.rock_params(2, E=30e9, nu=0.22)
    assert p.kn.shape == (2,)
    assert float(p.kn[0]) == 30e9                        # E A_c / L with A_c = L = 2R
    assert float(p.ks[0]) == pytest.approx(30e9 / (2 * 1.22))
    assert float(p.kn[1]) > 5 * float(p.kn[0])            # stiff platen
    assert float(p.friction[1]) == 0.0                    # frictionless platens
    assert float(p.friction[0]) == pytest.approx(np.tan(np.deg2rad(30)))
    b = lt.rock_params(2, kappa=[0.0, 1e-3, 2.4e-2])
    assert b.dt.shape == (3,) and b.kn.shape == (3, 2)
    np.testing.assert_array_equal(b.bond_tensile_strain, b.bond_shear_strain)
    np.testing.assert_array_equal(b.bond_tensile_strain, [0.0, 1e-3, 2.4e-2])
    with pytest.raises(InputError, match="radius"):
        lt.rock_params(3)


# ----------------------------------------------------------------------------- at rest
def test_averaged_stress_at_rest_equals_platen_stress(rect):
    """1 MPa on the top platen (servo), at rest: the averaged stress tensor
    (000 eq 4-44, current volume) equals the platen stress within 2 %; the
    lateral stress is ~0 (free sides)."""
    res = lt.coordination_energy_ratio(rect, lt.rock_params(2, kappa=3e-3, nu=0.3),
                                       stress=1e6, min_steps=4000)
    assert res["converged"]
    sig = res["avg_stress"]
    assert abs(sig[1, 1] / 1e6 - 1) < 0.02
    assert abs(res["top_stress"] / 1e6 - 1) < 0.002 and abs(res["bottom_stress"] / 1e6 - 1) < 0.002
    assert abs(sig[0, 0]) < 0.02e6 and abs(sig[0, 1]) < 0.02e6
    # 002 §1.4 at N-bar ~ 5: the energy ratio is of order one
    assert 0.5 < res["lam_core"] < 2.0 and 0.5 < res["lam"] < 3.0
    assert res["L_e"] == pytest.approx((1 - 0.3**2) * 1e12 / (2 * 30e9) * SIZE[0] * SIZE[1])


# ----------------------------------------------------------------------------- UCS sweep
def test_sweep_is_batched_and_recorded(sweep):
    hist, state, _ = sweep
    n = len(KAPPAS) + 2
    assert hist["axial_stress"].shape[0] == n and hist["avg_stress"].shape[:1] == (n,)
    assert hist["avg_stress"].shape[-2:] == (2, 2)
    assert np.asarray(state.step).shape == (n,)
    for key in ("axial_strain", "lateral_strain", "fracture_degree", "n_broken", "n_tension",
                "n_shear", "bond_energy", "kinetic_energy", "end_point", "end_mode"):
        assert key in hist
    np.testing.assert_array_equal(hist["n_broken"], hist["n_tension"] + hist["n_shear"])
    # the slower members moved half and a quarter as far
    assert hist["axial_strain"][3, -1] == pytest.approx(0.5 * hist["axial_strain"][2, -1], rel=1e-6)
    assert hist["axial_strain"][4, -1] == pytest.approx(0.25 * hist["axial_strain"][2, -1], rel=1e-6)


def test_youngs_modulus_stable_when_loading_rate_halved(sweep):
    """Elastic stage: E (least-squares slope over 10-40 % of the peak) changes by
    less than 5 % when the platen speed is halved from STEP / 2 to STEP / 4
    (members 3 and 4: same kappa).

    At STEP itself the loading is not yet quasi-static on this small specimen:
    the stress waves from the platen's start still shape the curve inside the
    fitting window, and E at STEP is 5.5 % (seed 2) and 5.7 % (seed 3)
    below E at STEP / 2, while STEP / 2 and STEP / 4 agree to 1.1 % and 0.3 %
    (measured with the kappa = 2.4 % parameters)."""
    _, _, s = sweep
    e_fast, e_slow = s["youngs_modulus"][3], s["youngs_modulus"][4]
    assert np.isfinite(e_fast) and np.isfinite(e_slow)
    assert abs(e_fast / e_slow - 1) < 0.05
    assert 10e9 < e_slow < 40e9   # of the order of the bond modulus at N-bar ~ 5


def test_peak_then_softening_and_trends_with_kappa(sweep):
    """002 §2.2-2.3: every curve peaks and softens; the peak stress and the
    critical strain rise with kappa, the fracture degree at the end falls.  The
    fracture degree at the peak falls from kappa = 0 to 2.4 % and does not rise
    in between: with ~800 bonds the two most brittle members can break the same
    number before their peaks (measured once: 57 each)."""
    hist, _, s = sweep
    k = len(KAPPAS)
    for b in range(k):
        stress = hist["axial_stress"][b]
        assert s["peak_index"][b] < len(stress) - 10            # a peak inside the run
        assert stress[-1] < 0.7 * s["peak_stress"][b]           # then softening
        assert s["peak_stress"][b] > 2e6
    assert np.all(np.diff(s["peak_stress"][:k]) > 0)
    assert np.all(np.diff(s["critical_strain"][:k]) > 0)
    assert np.all(np.diff(s["fracture_degree_end"][:k]) < 0)
    fd_peak = s["fracture_degree_at_peak"][:k]
    assert np.all(np.diff(fd_peak) <= 0) and fd_peak[-1] < fd_peak[0]


def test_failure_pattern_and_damage_map(sweep):
    _, state, _ = sweep
    st = lt.member(state, 0)
    fp = lt.failure_pattern(st)
    n_broken = int(np.sum(np.asarray(st.bonds.broken) & np.asarray(st.bonds.valid)))
    assert fp["point"].shape == (n_broken, 2) and fp["segment"].shape == (n_broken, 2, 2)
    assert set(np.unique(fp["mode"])) <= {1, 2} and n_broken > 0
    dm = lt.damage_map(st)
    assert dm["chi"].shape == (int(np.sum(np.asarray(st.bonds.valid))),)
    assert np.all((dm["chi"] >= 0) & (dm["chi"] <= 1))
    assert np.all(dm["chi"][dm["broken"]] == pytest.approx(1.0))
    with pytest.raises(InputError, match="member"):
        lt.failure_pattern(state)


# ----------------------------------------------------------------------------- biaxial
def test_biaxial_servo_holds_the_confining_stress(rect):
    """With confining_stress the lateral walls are servo-controlled (000 eq 4-69):
    after the isotropic pre-load the specimen carries the confining stress in
    both directions, and during the elastic stage the lateral walls stay within
    3 % of it while the axial stress rises."""
    conf = 2e6
    hist, _, _ = lt.ucs_test(rect, _params(), platen_step=STEP, max_strain=5e-4,
                             confining_stress=conf, preload_steps=4000)
    assert abs(hist["avg_stress_lateral"][0] / conf - 1) < 0.03
    assert abs(hist["bottom_stress"][0] / conf - 1) < 0.03
    assert np.all(np.abs(hist["lateral_stress"] / conf - 1) < 0.03)
    assert hist["axial_stress"][-1] > 4 * conf
    assert hist["axial_strain"][0] < 1e-5          # strains count from the pre-loaded state


# ----------------------------------------------------------------------------- restart
def test_restart_from_hdf5_reproduces_the_continuation(rect, tmp_path):
    su = lt.ucs_setup(rect, _params(), platen_step=STEP)
    n = lt.UCS_CHUNK_STEPS
    h_all, s_all, _ = lt.platen_run(su.state, su.params, su.config, su.frame, 3 * n)
    h1, s1, c1 = lt.platen_run(su.state, su.params, su.config, su.frame, n)
    path = lt.save_checkpoint(tmp_path / "mid.h5", s1, su.params, c1, su.frame, h1)
    state, params, config, frame, hist = lt.load_checkpoint(path)
    assert frame == su.frame and config == c1
    np.testing.assert_array_equal(hist["axial_stress"], h1["axial_stress"])
    h2, s2, _ = lt.platen_run(state, params, config, frame, 2 * n)
    k = len(h1["step"])
    for key in ("step", "axial_strain", "axial_stress", "avg_stress", "fracture_degree",
                "bond_energy", "kinetic_energy", "lateral_strain"):
        np.testing.assert_array_equal(h2[key], h_all[key][k:], err_msg=key)
    for a, b in zip(np.asarray(s2.particles.pos), np.asarray(s_all.particles.pos)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(s2.bonds.normal_force, s_all.bonds.normal_force)
    assert float(np.max(h_all["axial_stress"])) > 1e6       # it really was loaded


# ----------------------------------------------------------------------------- Brazilian
@pytest.fixture(scope="module")
def brazil():
    disc = generate("disc", 0.012, *RADII, seed=SEED, target_coordination=N_BAR)
    params = lt.rock_params(2, kappa=0.0, c0=10e6)
    hist, state, _ = lt.brazilian_test(disc, params, platen_step=STEP, max_strain=0.004)
    return disc, hist, state


def test_first_breaks_orders_by_step_and_counts_a_tenth():
    """The earliest tenth (at least ``minimum``), same-step ties in row order."""
    steps = np.array([70, 30, 30, 90, 10, 50, 20, 80, 60, 40, 100, 30])
    first = lt.first_breaks(dict(step=steps), minimum=3)
    assert first.tolist() == [4, 6, 1]                  # 12 breaks: a tenth is 1 -> 3
    assert lt.first_breaks(dict(step=steps), minimum=5).tolist() == [4, 6, 1, 2, 11]
    many = np.arange(97)[::-1]                          # bond 96 broke first
    assert lt.first_breaks(dict(step=many)).tolist() == list(range(96, 87, -1))   # 9 of 97
    assert lt.first_breaks(dict(step=steps[:2])).tolist() == [1, 0]   # fewer than minimum


def test_brazilian_splits_along_the_loaded_diameter(brazil):
    """Diametral compression: the load peaks and drops; at the end most broken
    bonds (>= 70 %) lie in the band |x - x_c| < R/3 around the loaded diameter
    (the band holds ~ 2/3 x 1/3 of the disc area, ~42 %, so a uniform spread
    would put ~42 % of the bonds there); the first tenth of the breaks lies in
    that band too, and they are mostly tensile."""
    disc, hist, state = brazil
    big_r = disc.info["radius"]
    xc = np.asarray(disc.info["centre"])[0] if "centre" in disc.info else big_r
    load = hist["load"]
    k = int(np.argmax(load))
    assert k < len(load) - 5 and load[-1] < 0.5 * load[k]
    sig_t = hist["tensile_strength_indirect"][k]
    assert sig_t == pytest.approx(2 * load[k] / (np.pi * 2 * big_r))
    assert 0.5e6 < sig_t < 6e6                              # of the order of T0 = 3 MPa
    fp = lt.failure_pattern(state)
    assert len(fp["index"]) >= 20
    band = np.abs(fp["point"][:, 0] - xc) < big_r / 3
    assert band.mean() >= 0.7
    first = lt.first_breaks(fp)
    assert band[first].mean() >= 0.8
    assert np.mean(fp["mode"][first] == 1) >= 0.5


@pytest.mark.xfail(strict=True, reason=(
    "not reproduced: the first bonds break along the loaded diameter but spread over "
    "r ~ 0.2-0.95 R (flat platens on a few discs), not at the centre; on larger discs "
    "(D/d 55-273) they break at the top platen first (experiments/brazilian_size.py); "
    "soft or flattened loading faces raise the share within 0.4 R to 41-52 %, not 80 %"))
def test_brazilian_failure_starts_at_the_centre(brazil):
    """Expected behaviour not reproduced (strict xfail).  With flat rigid platens
    the load enters through one or two discs; the tensile stress along the loaded
    diameter is then nearly uniform over most of it, and the first breaks fall
    where the random packing is weakest along that line, mostly in the outer half
    (here r / R = 0.22, 0.60, 0.73, ... 0.94 for the first 13; a 2,400-disc disc,
    D / d ~ 55, and flattened loading faces of 20-30 deg (``lt.flatten_disc``)
    did not move them to the centre either).

    Why (``python experiments/brazilian_onset.py``, this disc at 47 % of the peak
    load, just before the first break): along the loaded diameter the mean tension
    of the horizontal bonds is highest at the centre (459 N within 0.2 R, 321 N at
    0.4-0.6 R), as elasticity says, but its spread grows towards the platens with
    the compression there (standard deviation 187 N within 0.2 R, 988-1,216 N
    beyond 0.6 R: force chains).  The most loaded bond within 0.4 R is at 0.56 of
    its tensile strength, beyond 0.6 R at 0.93-0.98, so the first bonds break out
    there.  Larger discs make it worse, not better:
    ``experiments/brazilian_size.py`` (run on a GPU; figures in
    experiments/results/brazilian_size_gpu/) found the median r / R of the first
    tenth of the breaks at 0.87, 0.95, 0.91 and 0.92 for D = 30, 60, 100, 150 mm
    (2,400 to 60,741 discs, D/d 55 to 273): the disc crushes under the top platen
    first and the split then runs down the loaded diameter, while sigma_t falls
    from 2.55 MPa (D = 12 mm) to 0.59 MPa (150 mm).

    Spreading the load does not do it either (same 12 mm disc, 384 discs,
    experiments/results/brazilian_loading/): the share of the first tenth within
    0.4 R is 20 % with rigid platens, 52 % with a soft cushion (platen stiffness
    0.003 of the rock's), 41 % with 20 deg flats on a 0.01 cushion and 43 % with
    the 0.01 cushion and kappa = 0.3 %.  Elasticity gives no strong pull to the
    centre: under line loads sigma_x is uniform along the loaded diameter, and
    under a load spread over an arc of 20 deg (Hondros) it is still 94 % of its
    centre value at 0.4 R and 88 % at 0.5 R: it favours the inner half of the
    diameter only mildly."""
    disc, hist, state = brazil
    big_r = disc.info["radius"]
    c = np.asarray(disc.info["centre"])          # generate("disc") records it
    fp = lt.failure_pattern(state)
    first = lt.first_breaks(fp)
    r = np.linalg.norm(fp["point"][first] - c, axis=1)
    assert np.mean(r < 0.4 * big_r) >= 0.8


# ----------------------------------------------------------------------------- CLI
def _toml(tmp_path, **loading):
    """The rect specimen and a short loading; ``loading`` overrides [loading] keys
    (strings are written verbatim)."""
    keys = dict(platen_step=STEP, max_strain=4e-4, stop_stress_ratio=0)
    keys.update(loading)
    lines = "\n".join(f"{k} = {v}" for k, v in keys.items())
    text = f"""
[specimen]
width = {SIZE[0]}
height = {SIZE[1]}
r_min = {RADII[0]}
r_max = {RADII[1]}
seed = {SEED}
coordination = {N_BAR}

[material]
kappa = 0.003

[loading]
{lines}
"""
    path = tmp_path / "ucs.toml"
    path.write_text(text)
    return path


def test_cli_ucs_writes_png_and_hdf5(tmp_path):
    out = tmp_path / "out"
    assert cli.main(["ucs", "--config", str(_toml(tmp_path)), "--out", str(out)]) == 0
    assert (out / "ucs.png").stat().st_size > 10_000
    rd = io.load_run(out / "ucs.h5")
    assert rd.history["axial_stress"].shape[0] >= 30     # 4,000 steps, a record every 100
    assert float(np.max(rd.history["axial_stress"])) > 1e6
    assert rd.state is not None and rd.params is not None and rd.config is not None


@pytest.mark.parametrize("override, match", [
    (dict(bogus=1), r"loading\.bogus = 1"),
    (dict(platen_step=-1e-9), r"loading\.platen_step.*-1e-09"),
    (dict(local_damping="'high'"), r"loading\.local_damping.*'high'"),
    (dict(record_every=7), r"loading\.record_every = 7"),
])
def test_cli_ucs_bad_key_or_value_names_it(tmp_path, override, match):
    path = _toml(tmp_path, **override)
    with pytest.raises(InputError, match=match):
        cli.ucs_settings(path)
    assert cli.main(["ucs", "--config", str(path), "--out", str(tmp_path / "o")]) == 2


def test_cli_unknown_section(tmp_path):
    path = tmp_path / "x.toml"
    path.write_text("[specimens]\nwidth = 0.01\n")
    with pytest.raises(InputError, match=r"specimens"):
        cli.ucs_settings(path)
