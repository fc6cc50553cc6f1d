"""The lab-test layer (jdem.lab): uniaxial compression (002 §2), biaxial and
triaxial compression, the Brazilian test, direct tension, the pure curve
against the host loop, the quasi-static certificate, the strain-energy ratio of
002 §1.4, checkpoints and ``jdem ucs``.

The 002 reproduction checks (the kappa sweep, the Brazilian disc) use the seed's
local damping 0.8 (``lab.local(0.8)``) and a fixed platen step; the layer's
own checks use its default smooth damping.

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

from jdem import InputError, cli, io, lab
from jdem.batch import member
from jdem.lab import energy
from jdem.materials import rock_params
from jdem.specimen import flatten_disc, generate

#: restart and bookkeeping checks load faster than quasi-statically on purpose
#: (seconds, not minutes); the certificate's warning is expected there
LOADED_FAST = pytest.mark.filterwarnings("ignore:ucs.*not quasi-static:UserWarning")

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
    params = rock_params(2, kappa=list(KAPPAS) + [KAPPAS[-1]] * 2)
    setup = lab.UCS.setup(rect, params, platen_step=[STEP, STEP, STEP, STEP / 2, STEP / 4],
                          max_strain=SWEEP_STRAIN, damping=lab.local(0.8), record_every=50)
    res = lab.run(setup, progress=False, warn_dynamic=False)
    return res.history, res.state, lab.peak_summary(res.history)


@functools.lru_cache(maxsize=None)
def _params():
    return rock_params(2, kappa=3e-3)


# ----------------------------------------------------------------------------- set-up
def test_rock_params_two_materials_and_batched_kappa():
    p = rock_params(2, E=30e9, nu=0.22)
    assert p.kn.shape == (2,)
    assert float(p.kn[0]) == 30e9                        # E A_c / L with A_c = L = 2R
    assert float(p.ks[0]) == pytest.approx(30e9 / (2 * 1.22))
    assert float(p.kn[1]) > 5 * float(p.kn[0])            # stiff platen
    assert float(p.friction[1]) == 0.0                    # frictionless platens
    assert float(p.friction[0]) == pytest.approx(np.tan(np.deg2rad(30)))
    b = rock_params(2, kappa=[0.0, 1e-3, 2.4e-2])
    assert b.dt.shape == (3,) and b.kn.shape == (3, 2)
    np.testing.assert_array_equal(b.bond_tensile_strain, b.bond_shear_strain)
    np.testing.assert_array_equal(b.bond_tensile_strain, [0.0, 1e-3, 2.4e-2])
    with pytest.raises(InputError, match="radius"):
        rock_params(3)


# ----------------------------------------------------------------------------- at rest
def test_averaged_stress_at_rest_equals_platen_stress(rect):
    """1 MPa on the top platen (servo), at rest: the averaged stress tensor
    (000 eq 4-44, current volume) equals the platen stress within 2 %; the
    lateral stress is ~0 (free sides)."""
    res = energy.coordination_energy_ratio(rect, rock_params(2, kappa=3e-3, nu=0.3),
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
    # the slower members moved half and a quarter as far (ramps of equal length)
    assert hist["axial_strain"][3, -1] == pytest.approx(0.5 * hist["axial_strain"][2, -1], rel=0.02)
    assert hist["axial_strain"][4, -1] == pytest.approx(0.25 * hist["axial_strain"][2, -1], rel=0.04)


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
    st = member(state, 0)
    fp = lab.failure_pattern(st)
    n_broken = int(np.sum(np.asarray(st.bonds.broken) & np.asarray(st.bonds.valid)))
    assert fp["point"].shape == (n_broken, 2) and fp["segment"].shape == (n_broken, 2, 2)
    assert set(np.unique(fp["mode"])) <= {1, 2} and n_broken > 0
    dm = lab.damage_map(st)
    assert dm["chi"].shape == (int(np.sum(np.asarray(st.bonds.valid))),)
    assert np.all((dm["chi"] >= 0) & (dm["chi"] <= 1))
    assert np.all(dm["chi"][dm["broken"]] == pytest.approx(1.0))
    with pytest.raises(InputError, match="member"):
        lab.failure_pattern(state)


# ----------------------------------------------------------------------------- biaxial
def test_biaxial_servo_holds_the_confining_stress(rect):
    """With confining_stress the lateral walls are servo-controlled (000 eq 4-69):
    after the isotropic pre-load the specimen carries the confining stress in
    both directions, and during the elastic stage the lateral walls stay within
    3 % of it while the axial stress rises."""
    conf = 2e6
    setup = lab.BIAXIAL.setup(rect, _params(), platen_step=STEP, max_strain=5e-4,
                              confining_stress=conf)
    hist = lab.run(setup, progress=False).history
    assert abs(hist["avg_stress_lateral"][0] / conf - 1) < 0.03
    assert abs(hist["bottom_stress"][0] / conf - 1) < 0.03
    assert np.all(np.abs(hist["lateral_stress"] / conf - 1) < 0.03)
    assert hist["axial_stress"][-1] > 4 * conf
    assert hist["axial_strain"][0] < 1e-5          # strains count from the pre-loaded state
    # chunks shorter than the pre-load, with the bar (which shows the axial stress
    # after every chunk): the same history.  Deriving the stress of a history
    # still inside the pre-load raised IndexError before.
    assert setup.plan.preload_records > 3
    shown = lab.run(setup, progress=True, chunk_records=3).history
    np.testing.assert_array_equal(shown["axial_stress"], hist["axial_stress"])


# ----------------------------------------------------------------------------- restart
@LOADED_FAST
def test_interrupted_run_resumes_bit_for_bit(rect, tmp_path):
    """A run stopped after its first chunk (the checkpoint it wrote then) and
    resumed gives the uninterrupted history and final state, bit for bit."""
    setup = lab.UCS.setup(rect, _params(), platen_step=STEP, max_strain=4e-4, record_every=50)
    full = lab.run(setup, progress=False, chunk_records=10)
    part = setup.replace(plan=setup.plan.replace(n_records=10))   # the first chunk only
    lab.run(part, progress=False, chunk_records=10, checkpoint=tmp_path / "c.h5")
    back = lab.run(setup, progress=False, chunk_records=10, resume=tmp_path / "c.h5")
    for key in ("step", "axial_strain", "axial_stress", "avg_stress", "fracture_degree",
                "bond_energy", "kinetic_energy", "lateral_strain"):
        np.testing.assert_array_equal(back.history[key], full.history[key], err_msg=key)
    np.testing.assert_array_equal(back.state.particles.pos, full.state.particles.pos)
    np.testing.assert_array_equal(back.state.bonds.normal_force, full.state.bonds.normal_force)
    assert float(np.max(full.history["axial_stress"])) > 1e6       # it really was loaded
    # a checkpoint of format version 1 (flat raw_ / lab_ names) resumes the same way
    rd = io.load_run(tmp_path / "c.h5")
    assert set(rd.attrs["lab"]) == {"test", "record", "n_records", "record_every", "status"}
    io.save_run(tmp_path / "v1.h5", state=rd.state, params=rd.params, config=rd.config,
                history={f"raw_{k}": v for k, v in rd.history["raw"].items()},
                attrs={f"lab_{k}": v for k, v in rd.attrs["lab"].items()})
    old = lab.run(setup, progress=False, chunk_records=10, resume=tmp_path / "v1.h5")
    np.testing.assert_array_equal(old.history["axial_stress"], full.history["axial_stress"])
    with pytest.raises(InputError, match="not of the 'biaxial'"):
        lab.run(lab.BIAXIAL.setup(rect, _params(), confining_stress=1e6, max_strain=1e-4),
                progress=False, resume=tmp_path / "c.h5")


# ----------------------------------------------------------------------------- Brazilian
@pytest.fixture(scope="module")
def brazil():
    disc = generate("disc", 0.012, *RADII, seed=SEED, target_coordination=N_BAR)
    params = rock_params(2, kappa=0.0, c0=10e6)
    setup = lab.BRAZILIAN.setup(disc, params, platen_step=STEP, max_strain=0.004,
                                damping=lab.local(0.8), record_every=50)
    res = lab.run(setup, progress=False, stop_stress_ratio=0.3, warn_dynamic=False)
    return disc, res.history, res.state


def test_first_breaks_orders_by_step_and_counts_a_tenth():
    """The earliest tenth (at least ``minimum``), same-step ties in row order."""
    steps = np.array([70, 30, 30, 90, 10, 50, 20, 80, 60, 40, 100, 30])
    first = lab.first_breaks(dict(step=steps), minimum=3)
    assert first.tolist() == [4, 6, 1]                  # 12 breaks: a tenth is 1 -> 3
    assert lab.first_breaks(dict(step=steps), minimum=5).tolist() == [4, 6, 1, 2, 11]
    many = np.arange(97)[::-1]                          # bond 96 broke first
    assert lab.first_breaks(dict(step=many)).tolist() == list(range(96, 87, -1))   # 9 of 97
    assert lab.first_breaks(dict(step=steps[:2])).tolist() == [1, 0]   # fewer than minimum


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
    fp = lab.failure_pattern(state)
    assert len(fp["index"]) >= 20
    band = np.abs(fp["point"][:, 0] - xc) < big_r / 3
    assert band.mean() >= 0.7
    first = lab.first_breaks(fp)
    assert band[first].mean() >= 0.8
    assert np.mean(fp["mode"][first] == 1) >= 0.5


def test_brazilian_reports_the_onset_location(brazil):
    """The check "failure starts at the centre" is withdrawn: with flat rigid
    platens on discs of this size the first breaks fall along the loaded
    diameter but near the platens (experiments/brazilian_onset.py: the bond
    tension along the diameter is highest at the centre on average, but its
    spread is 5-6x wider near the platens, where the force chains are).  The
    onset is reported: the median r / R of the first tenth of the breaks, which
    lies inside the disc and on the loaded diameter's band."""
    disc, hist, state = brazil
    big_r = disc.info["radius"]
    c = np.asarray(disc.info["centre"])
    fp = lab.failure_pattern(state)
    first = lab.first_breaks(fp)
    r = np.linalg.norm(fp["point"][first] - c, axis=1) / big_r
    print(f"onset: median r / R of the first {len(first)} breaks = {np.median(r):.2f}")
    assert np.all(r < 1.0)
    assert np.all(np.abs(fp["point"][first, 0] - c[0]) < big_r / 3)


# ----------------------------------------------------------------------------- CLI
def _toml(tmp_path, **loading):
    """The rect specimen and a short loading; ``loading`` overrides [loading] keys
    (strings are written verbatim)."""
    keys = dict(platen_step=STEP, max_strain=4e-4, stop_stress_ratio=0, record_every=100)
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


@LOADED_FAST
def test_cli_ucs_writes_png_and_hdf5(tmp_path):
    """``jdem ucs --animate --paraview``: the PNG and HDF5, a GIF of the failure
    developing and a ParaView series, which reopen with Pillow and meshio and
    show the bonds breaking as the run's final state says."""
    import meshio
    from PIL import Image

    out = tmp_path / "out"
    assert cli.main(["ucs", "--config", str(_toml(tmp_path)), "--out", str(out), "--animate",
                     "--paraview"]) == 0
    assert (out / "ucs.png").stat().st_size > 10_000
    rd = io.load_run(out / "ucs.h5")
    n_rec = rd.history["axial_stress"].shape[0]
    assert n_rec >= 30     # 4,000 steps, a record every 100
    assert float(np.max(rd.history["axial_stress"])) > 1e6
    assert rd.state is not None and rd.params is not None and rd.config is not None
    assert set(rd.attrs["settings"]) == {"specimen", "material", "loading"}      # groups
    assert rd.attrs["settings"]["specimen"]["seed"] == SEED
    assert rd.attrs["summary"]["peak_stress"] == pytest.approx(
        float(np.max(rd.history["axial_stress"])))
    with Image.open(out / "failure.gif") as gif:
        assert gif.n_frames == min(40, n_rec) and gif.size[0] > 500
    pvd = (out / "paraview" / "ucs.pvd").read_text()
    files = sorted((out / "paraview").glob("ucs_*.vtu"))
    assert len(files) == n_rec and pvd.count("<DataSet") == n_rec
    last = meshio.read(files[-1])
    state = rd.state
    n = int(np.sum(np.asarray(state.particles.valid)))
    np.testing.assert_allclose(last.points[:, :2], np.asarray(state.particles.pos)[:n])
    np.testing.assert_allclose(last.point_data["radius"], np.asarray(state.particles.radius)[:n])
    lines = last.cells_dict["line"]
    assert lines.shape[0] == int(np.sum(np.asarray(state.bonds.valid)))
    broken_at_end = int(np.sum(np.asarray(state.bonds.broken) & np.asarray(state.bonds.valid)))
    assert int(np.sum(last.cell_data_dict["broken"]["line"])) == broken_at_end
    # this short run stops before any bond breaks: mark bonds broken at chosen
    # steps and check that each record shows those broken by then, by mode
    from jdem import export

    b = state.bonds
    steps = rd.history["step"]
    rows = np.nonzero(np.asarray(b.valid))[0][:30]
    when = np.full(b.break_step.shape, -1)
    when[rows] = steps[np.linspace(0, n_rec - 1, rows.size).astype(int)]
    mode = np.zeros(b.break_mode.shape, np.int32)
    mode[rows] = 1 + np.arange(rows.size) % 2
    state = state._replace(bonds=b._replace(break_step=when, break_mode=mode,
                                            broken=when >= 0))
    pvd = export.write_series(tmp_path / "pv", state, rd.history, name="s", every=7)
    for k in range(0, n_rec, 7):
        m = meshio.read(tmp_path / "pv" / f"s_{k:04d}.vtu")
        got = m.cell_data_dict["break_mode"]["line"]
        expect = np.where((when >= 0) & (when <= steps[k]), mode, 0)[np.asarray(b.valid)]
        np.testing.assert_array_equal(got, expect)
    assert pvd.read_text().count("<DataSet") == len(range(0, n_rec, 7))


@pytest.mark.parametrize("override, match", [
    (dict(bogus=1), r"loading\.bogus = 1"),
    (dict(platen_step=-1e-9), r"loading\.platen_step.*-1e-09"),
    (dict(local_damping="'high'"), r"loading\.local_damping.*'high'"),
    (dict(record_every=-7), r"loading\.record_every.*-7"),
    (dict(damping="'viscous'"), r"loading\.damping.*'viscous'"),
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


def test_cli_config_that_is_a_folder_a_binary_or_has_a_bom(tmp_path):
    with pytest.raises(InputError, match="is a directory"):
        cli.ucs_settings(tmp_path)
    binary = tmp_path / "cfg.toml"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff")
    with pytest.raises(InputError, match="not a text TOML"):
        cli.ucs_settings(binary)
    bom = tmp_path / "bom.toml"
    bom.write_bytes("\ufeff[specimen]\nwidth = 0.012\n".encode())
    assert cli.ucs_settings(bom)["specimen"]["width"] == 0.012


def test_small_replaces_the_configs_specimen_and_rate_and_says_so(tmp_path, capsys):
    """``--small`` is a smoke test of the user's own file: the README's fit.toml sets a
    2 cm x 4 cm specimen, and ``--small`` must still run ~100 discs at the fast rate,
    keeping the file's material, parameters and steps, and print what it replaced."""
    path = tmp_path / "fit.toml"
    path.write_text("[specimen]\nwidth = 0.02\nheight = 0.04\nmembers = 2\n"
                    "[material]\nE = 31e9\n[loading]\nplaten_step = 1e-9\n"
                    "[fit]\nparameters = [\"E\", \"kappa\"]\nsteps = 5\n")
    full = cli.calibrate_settings(path)
    assert (full["specimen"]["width"], full["loading"]["platen_step"]) == (0.02, 1e-9)
    small = cli.calibrate_settings(path, small=True)
    for sec, vals in cli.CALIBRATE_SMALL.items():
        assert {k: small[sec][k] for k in vals} == vals
    assert small["specimen"]["members"] == 2 and small["material"]["E"] == 31e9
    assert small["fit"]["steps"] == 5 and small["fit"]["parameters"] == ["E", "kappa"]
    said = capsys.readouterr().out
    assert "specimen.width = 0.004 instead of 0.02" in said
    assert "loading.platen_step = 0.0 instead of 1e-09" in said
    assert cli.calibrate_settings(None, small=True)["fit"]["steps"] == cli.CALIBRATE_SMALL_STEPS
    ucs_file = tmp_path / "ucs.toml"
    ucs_file.write_text("[specimen]\nwidth = 0.05\n[material]\nkappa = 0.01\n")
    ucs_small = cli.ucs_settings(ucs_file, small=True)
    assert ucs_small["specimen"]["width"] == cli.UCS_SMALL["specimen"]["width"]
    assert ucs_small["material"]["kappa"] == 0.01


# ----------------------------------------------------------------------------- one definition
DEMO_SIZE = (0.004, 0.008)


@functools.lru_cache(maxsize=None)
def _demo_spec():
    return generate("rectangle", DEMO_SIZE, *RADII, seed=2, target_coordination=4.5)


@functools.lru_cache(maxsize=None)
def _box():
    return generate("box", (0.003, 0.003, 0.005), 0.3e-3, 0.45e-3, seed=1,
                    target_coordination=5.5)


def _pure_equals_host(setup):
    pure, _ = lab.checked_curve(setup)
    host = lab.run(setup, progress=False, chunk_records=7, warn_dynamic=False).history
    for key in ("axial_strain", "axial_stress", "fracture_degree", "kinetic_energy"):
        scale = max(float(np.max(np.abs(host[key]))), 1e-300)
        np.testing.assert_allclose(pure[key], host[key], rtol=1e-9, atol=1e-9 * scale,
                                   err_msg=key)
    return host


@pytest.mark.parametrize("case", ["ucs2d", "biaxial2d",
                                  # 3D by default through triaxial3d; ucs3d on request
                                  pytest.param("ucs3d", marks=pytest.mark.slow), "triaxial3d"])
def test_pure_curve_equals_host_loop(case):
    """The same definition run as one pure function and as the chunked host loop
    (chunks of 7 records) gives the same curve to round-off."""
    kw = dict(max_strain=4e-4, loading_rate=3.2e-5)
    if case.endswith("2d"):
        spec, params = _demo_spec(), rock_params(2, kappa=3e-3)
    else:
        spec, params = _box(), rock_params(3, kappa=3e-3, radius=0.375e-3)
    test = lab.UCS if case.startswith("ucs") else lab.BIAXIAL
    if test is lab.BIAXIAL:
        kw["confining_stress"] = 2e6
    host = _pure_equals_host(test.setup(spec, params, precision="float64", **kw))
    assert float(np.max(host["axial_stress"])) > 1e6


@pytest.mark.slow   # a study of the old default; the refusal is tested in test_calibrate
def test_certificate_flags_the_old_default_and_passes_the_new():
    """On the demo's 104-disc specimen: the old default of the differentiable
    test (5 nm per step, 1.1e-4 of the wave speed) changes its peak by far more
    than 2 % at half the rate; the new default rate changes it by less than 2 %,
    and so does the modulus."""
    params = rock_params(2, kappa=3e-3)
    old = lab.certify(lab.UCS.setup(_demo_spec(), params, platen_step=5e-9, max_strain=1.2e-3))
    new = lab.certify(lab.UCS.setup(_demo_spec(), params, max_strain=1.2e-3))
    print("\nold default:", old, "\nnew default:", new)
    assert not old.quasi_static and abs(float(old.peak_change)) > 0.05
    assert new.quasi_static
    assert abs(float(new.peak_change)) < 0.02 and abs(float(new.modulus_change)) < 0.02
    assert new.kinetic_ratio < old.kinetic_ratio


def test_smooth_and_local_damping_agree_when_quasi_static():
    """At a certified rate the curve does not depend on the damping: the smooth
    default and the seed's local damping 0.8 agree within 3 % in peak stress and
    modulus on the ~100-disc specimen."""
    params = rock_params(2, kappa=3e-3)
    kw = dict(max_strain=1.2e-3, loading_rate=2e-6)
    s = lab.peak_summary(lab.run(lab.UCS.setup(_demo_spec(), params, **kw),
                                 progress=False).history)
    loc = lab.peak_summary(lab.run(lab.UCS.setup(_demo_spec(), params, damping=lab.local(0.8),
                                                 **kw), progress=False).history)
    print(f"\nsmooth: {s['peak_stress'] / 1e6:.3f} MPa, {s['youngs_modulus'] / 1e9:.2f} GPa; "
          f"local: {loc['peak_stress'] / 1e6:.3f} MPa, {loc['youngs_modulus'] / 1e9:.2f} GPa")
    assert abs(s["peak_stress"] / loc["peak_stress"] - 1) < 0.03
    assert abs(s["youngs_modulus"] / loc["youngs_modulus"] - 1) < 0.03


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=(
    "measured (experiments/rate_convergence.py): at the default rate the smooth curve "
    "peaks at 9.319 MPa, the local one at 9.645 MPa (+3.5 %); moduli 23.08 / 23.19 GPa. "
    "The smooth curve has converged (+1.55 % from 8e-6 to 4e-6), the local one has not "
    "(+6.58 %): local damping needs a slower rate on this block"))
def test_smooth_and_local_damping_agree_on_a_large_specimen():
    """The same check on the reduced study's 1.8 cm x 3.6 cm block (~2,200 discs)
    at the default rate, both dampings as one batch (about 190,000 steps)."""
    spec = generate("rectangle", (0.018, 0.036), *RADII, seed=2, target_coordination=5.0)
    params = rock_params(2, kappa=3e-3)
    setups = [lab.UCS.setup(spec, params, max_strain=1.2e-3, damping=d)
              for d in (lab.smooth(), lab.local(0.8))]
    s = lab.peak_summary(lab.run(lab.stack_setups(setups), progress=False).history)
    print(f"\npeak {s['peak_stress'] / 1e6} MPa, modulus {s['youngs_modulus'] / 1e9} GPa")
    assert abs(s["peak_stress"][0] / s["peak_stress"][1] - 1) < 0.03
    assert abs(s["youngs_modulus"][0] / s["youngs_modulus"][1] - 1) < 0.03


def test_direct_tension_peaks_near_the_bond_strength_and_breaks():
    """Direct tension between grips: linear, then a peak of the order of the
    bond tensile strength (T0 = 3 MPa; the bars' cross-section and the packing
    make the macro strength lower), then the specimen splits (the stress falls,
    bonds break mostly in tension); the pure curve equals the host loop."""
    params = rock_params(2, kappa=3e-3)
    setup = lab.TENSION.setup(_demo_spec(), params, max_strain=5e-4, loading_rate=1.6e-5,
                              precision="float64")
    host = _pure_equals_host(setup)
    s = lab.peak_summary(host)
    assert 0.3e6 < s["peak_stress"] < 3e6
    assert host["axial_stress"][-1] < 0.5 * s["peak_stress"]
    assert host["n_tension"][-1] > host["n_shear"][-1] and host["n_broken"][-1] > 5


def test_brazilian_tensile_strength_is_reported(brazil):
    """sigma_t = 2 P / (pi D t) at the peak load, in the history and the summary
    (to the round-off of the run's working precision, float32 by default)."""
    disc, hist, _ = brazil
    s = lab.peak_summary(hist)
    d = 2 * disc.info["radius"]
    eps = np.finfo(np.asarray(hist["axial_stress"]).dtype).eps
    assert s["tensile_strength"] == pytest.approx(2 * s["peak_stress"] / (np.pi * d), rel=8 * float(eps))


def test_bad_lab_input_names_the_field():
    params = rock_params(2, kappa=3e-3)
    with pytest.raises(InputError, match="loading_rate must be > 0"):
        lab.UCS.setup(_demo_spec(), params, loading_rate=-1.0)
    with pytest.raises(InputError, match="needs confining_stress"):
        lab.BIAXIAL.setup(_demo_spec(), params)
    with pytest.raises(InputError, match="damping must be"):
        lab.UCS.setup(_demo_spec(), params, damping="local")
    with pytest.raises(InputError, match="alpha must lie"):
        lab.local(1.0)
    setup = lab.UCS.setup(_demo_spec(), params)
    for bad in (0, -3, 2.5):
        with pytest.raises(InputError, match="chunk_records"):
            lab.run(setup, progress=False, chunk_records=bad)


# ----------------------------------------------------------------------------- rate extrapolation
def test_rate_extrapolation_removes_a_first_order_rate_term():
    """A figure linear in the loading rate, S(v) = S0 + a v, is extrapolated to S0
    exactly from v and v / f.  A curve whose peak stress and peak strain both
    grow linearly with the rate, S_v(e) = A(v) g(e / e_p(v)), g(x) = x (2 - x),
    recorded at other strains by the slower run, is extrapolated to the
    rate-zero curve A0 g(e / e0) (to the linear interpolation of the slower
    run), batched or not; its peak strain is found between records."""
    s0, a, v = 8.7e6, 3e10, 8e-6
    for f in (2.0, 4.0):
        np.testing.assert_allclose(lab.rate_extrapolated(s0 + a * v, s0 + a * v / f, f), s0,
                                   rtol=1e-12)
    a0, e0 = 9e6, 4.7e-4

    def hist(n, rate):
        amp, ep = a0 * (1 + 2e4 * rate), e0 * (1 + 1e4 * rate)
        e = np.linspace(0.0, 1.5 * ep, n)
        return dict(axial_strain=e, axial_stress=amp * (e / ep) * (2 - e / ep),
                    step=np.arange(n), first_bad_step=np.int64(-1))

    fast, slow = hist(601, v), hist(1203, v / 2)
    assert float(lab.peak_strain(fast["axial_strain"], fast["axial_stress"])) == \
        pytest.approx(e0 * (1 + 1e4 * v), rel=1e-12)
    out = lab.extrapolated_history(fast, slow)
    e = np.asarray(out["axial_strain"])
    np.testing.assert_allclose(e, fast["axial_strain"] * e0 / (e0 * (1 + 1e4 * v)), rtol=1e-12)
    np.testing.assert_allclose(out["axial_stress"], a0 * (e / e0) * (2 - e / e0), rtol=0,
                               atol=2e-5 * a0)
    np.testing.assert_allclose(np.max(out["axial_stress"]), a0, rtol=2e-6)
    np.testing.assert_array_equal(out["axial_stress_at_rate"], fast["axial_stress"])
    two = lambda h: {k: np.stack([x, x]) for k, x in h.items()}   # noqa: E731
    both = lab.extrapolated_history(two(fast), two(slow))
    np.testing.assert_allclose(both["axial_stress"][1], out["axial_stress"], rtol=1e-12)
    # pointwise extrapolation at equal strains would overshoot the peak here
    naive = lab.rate_extrapolated(fast["axial_stress"],
                                  np.interp(fast["axial_strain"], slow["axial_strain"],
                                            slow["axial_stress"]))
    assert np.max(naive) > 1.001 * a0
    # past the peak the runs drop at different fractions of their peak strain: no
    # overshoot, the slower run's drop scaled by the ratio at the peak
    def dropped(h, at):
        x = h["axial_strain"] / lab.peak_strain(h["axial_strain"], h["axial_stress"])
        return dict(h, axial_stress=np.where(x > at, 0.4, 1.0) * h["axial_stress"])
    out = lab.extrapolated_history(dropped(fast, 1.1), dropped(slow, 1.3))
    xi = fast["axial_strain"] / (e0 * (1 + 1e4 * v))
    np.testing.assert_allclose(np.max(out["axial_stress"]), a0, rtol=2e-6)
    late = xi > 1.31
    np.testing.assert_allclose(out["axial_stress"][late],
                               0.4 * a0 * xi[late] * (2 - xi[late]), rtol=0, atol=2e-5 * a0)


def test_certificate_estimates_the_distance_to_the_quasi_static_peak():
    """With a peak change c at half the rate, the first-order error of the run's
    peak is 2 c, and the extrapolated peak is what lies that far below it."""
    fast = dict(peak_stress=np.float64(9.242e6))
    slow = dict(peak_stress=np.float64(8.980e6))
    cert = lab.Certificate(peak_change=9.242 / 8.980 - 1, modulus_change=0.0, kinetic_ratio=0.0,
                           quasi_static=False, tolerance=0.02, loading_rate=8e-6, summary=fast,
                           slow_summary=slow)
    np.testing.assert_allclose(cert.quasi_static_peak, 8.718e6, rtol=1e-12)
    np.testing.assert_allclose(cert.peak_error, 2 * (9.242 / 8.980 - 1), rtol=1e-12)
    # the first-order error of the fast peak, measured from the extrapolated peak
    np.testing.assert_allclose(9.242e6 / cert.quasi_static_peak - 1,
                               cert.peak_error * 8.980 / 8.718, rtol=1e-12)
    assert "from the quasi-static peak" in str(cert)


def test_curve_stages_of_a_piecewise_curve():
    """jdem.lab.curve_stages on a curve whose four stages are known (002 Fig 10):
    linear to 5.9 MPa at 200e-6 (E 29.5 GPa), a parabolic rise to its peak
    (7.375 MPa) at 300e-6, a straight fall to 1 MPa at 400e-6, then a flat
    residual stage;
    bonds break from 250e-6 on, 40 % of them in tension."""
    e = np.linspace(0.0, 1e-3, 2001)
    E, e1, s1, e2, e3, s3 = 29.5e9, 200e-6, 5.9e6, 300e-6, 400e-6, 1e6
    # rise: s1 + E (e - e1) - c (e - e1)^2 with zero slope at e2
    c = E / (2 * (e2 - e1))
    s2 = s1 + E * (e2 - e1) / 2
    rise = s1 + E * (e - e1) - c * (e - e1) ** 2
    s = np.where(e <= e1, E * e, np.where(e <= e2, rise, np.where(
        e <= e3, s2 + (s3 - s2) * (e - e2) / (e3 - e2), s3)))
    assert np.max(s) == pytest.approx(s1 + E * (e2 - e1) / 2)   # the peak the rise reaches
    broken = np.where(e >= 250e-6, np.round((e - 250e-6) * 4e6), 0).astype(int)
    hist = dict(axial_strain=e, axial_stress=s, n_broken=broken,
                n_tension=(0.4 * broken).astype(int), n_shear=broken - (0.4 * broken).astype(int))
    st = lab.curve_stages(hist)
    peak = s1 + E * (e2 - e1) / 2
    assert st["peak_stress"] == pytest.approx(peak) and st["peak_strain"] == pytest.approx(e2)
    # 1 % below the line E e: c x^2 = 0.01 E (e1 + x), x = e - e1, i.e.
    # x^2 - 2e-6 x - 4e-10 = 0: x = 21.0e-6
    x = (2e-6 + np.sqrt(4e-12 + 1.6e-9)) / 2
    assert st["linear_end_strain"] == pytest.approx(e1 + x, abs=1e-6)
    assert st["rise_ratio"] == pytest.approx((e2 - e1 - x) / (e1 + x), rel=0.02)
    assert st["first_break_strain"] == pytest.approx(250.5e-6, abs=1e-6)
    assert st["descent_modulus"] == pytest.approx((s3 - peak) / (e3 - e2), rel=1e-6)
    assert st["residual_stress"] == pytest.approx(s3, rel=2e-3)   # from a windowed start
    assert e3 - 50e-6 <= st["residual_strain"] <= e3
    k = int(np.argmax(s))
    assert st["n_tension_at_peak"] == hist["n_tension"][k]
    assert st["n_shear_end"] == hist["n_shear"][-1]
    batched = {key: np.stack([v, v]) for key, v in hist.items()}
    assert np.all(lab.curve_stages(batched)["peak_stress"] == st["peak_stress"])
