"""The pure UCS test (jdem.lab.curve) and calibration (jdem.calibrate).

One ~106-disc specimen (4 mm x 8 mm) and one set-up serve every test, so the
curve and its gradient compile once each.  float64 (``precision="float64"``):
these tests check gradients against finite differences and runs against each
other to round-off; tests/test_precision.py compares float32 Jacobians with
float64 ones.

Speed: these tests exercise the gradient and the optimiser, not the rock, so
they load 8x faster than the quasi-static default (``RATE``) and pass
``require_quasi_static=False``; tests/test_lab.py checks the certificate that
calibration demands by default.
"""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jdem import InputError, lab
from jdem import calibrate as cb
from jdem import materials as lt
from jdem.specimen import generate

SIZE = (0.004, 0.008)
RADII = (0.2e-3, 0.35e-3)
TRUE = dict(E=30e9, strength=3e6, kappa=3e-3)
MAX_STRAIN = 1.2e-3
RATE = 3.2e-5                     # platen / wave speed: 8x the quasi-static default


@functools.lru_cache(maxsize=None)
def specimen(seed):
    return generate("rectangle", SIZE, *RADII, seed=seed, target_coordination=4.5)


@functools.lru_cache(maxsize=None)
def model_and_params():
    su = lab.UCS.setup(specimen(2), lt.rock_params(2, kappa=3e-3), max_strain=MAX_STRAIN,
                       loading_rate=RATE, stiffness_margin=2.0, precision="float64")
    return su, su.params


def _curve(hist):
    return dict(strain=hist["axial_strain"], stress=hist["axial_stress"],
                fracture_degree=hist["fracture_degree"])


@functools.lru_cache(maxsize=None)
def target_curve():
    model, params = model_and_params()
    hist, _ = lab.checked_curve(model, cb.material(params, TRUE))
    return _curve(hist)


# ----------------------------------------------------------------------------- the model
def test_curve_has_peak_softening_and_breakage():
    c = target_curve()
    s, fd = c["stress"], c["fracture_degree"]
    k = int(np.argmax(s))
    assert 0 < k < len(s) - 5
    assert s[-1] < 0.5 * s[k]                      # softening after the peak
    assert fd[-1] > 0.05 and fd[k // 2] == 0.0       # bonds break, none early
    assert np.all(np.diff(c["strain"]) > 0)


def test_ensemble_members_equal_single_runs():
    """Two packings padded to common capacities and run as one vmapped call, each
    with its own parameter set (member 1: E 10 % higher), give each packing's own
    curve."""
    params0 = lt.rock_params(2, kappa=3e-3)
    kw = dict(max_strain=MAX_STRAIN, loading_rate=RATE, stiffness_margin=2.0,
              precision="float64")
    ens = lab.UCS.setup([specimen(2), specimen(3)], params0, **kw)
    single = lab.UCS.setup(specimen(3), params0, dt=float(ens.params.dt),
                           record_every=ens.plan.record_every, **kw)
    # the ensemble's schedule (its ramp spans the taller member's transits)
    single = single.replace(plan=single.plan.replace(n_records=ens.plan.n_records,
                                                     ramp_records=ens.plan.ramp_records))
    pe = ens.params
    assert ens.n_members == 2
    assert float(pe.dt) <= float(model_and_params()[1].dt) * (1 + 1e-12)
    p1 = cb.material(pe, dict(E=33e9))
    both = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), pe, p1)
    ce, _ = lab.checked_curve(ens, both)
    cs, _ = lab.checked_curve(single, p1)
    ce, cs = _curve(ce), _curve(cs)
    n = min(ce["stress"].shape[-1], cs["stress"].shape[-1])
    k = int(np.argmax(cs["stress"][:n]))
    # The same arithmetic: in the elastic stage the member equals the single run to
    # round-off (measured: bit for bit over the first 11 of the 24 records to the
    # peak).  Once bonds yield, every kink amplifies the round-off of the different
    # padding, and up to the peak the two then agree to a few 1e-6 (measured 3.6e-6).
    peak = float(cs["stress"][k])
    np.testing.assert_allclose(ce["stress"][1, :k // 3], cs["stress"][:k // 3], rtol=1e-12,
                               atol=1e-12 * peak)
    np.testing.assert_allclose(ce["stress"][1, :k + 1], cs["stress"][:k + 1], rtol=1e-5,
                               atol=1e-5 * peak)
    assert not np.allclose(ce["stress"][0, :n], ce["stress"][1, :n])


# ----------------------------------------------------------------------------- gradients
GRAD_FIELDS = ("bond_youngs", "bond_poisson", "bond_tensile", "bond_cohesion",
               "bond_friction_angle", "bond_tensile_strain", "bond_shear_strain")


def _window_mean(params, model, n_rec):
    out = lab.curve(model, params).history
    return jnp.mean(out["axial_stress"][:n_rec]) / 1e6


def test_jacobians_match_finite_differences_before_breakage():
    """d(mean stress over the records before the first bond breaks)/d(parameter)
    by forward mode (jax.jacfwd), by reverse mode (jax.grad) and by central
    differences (relative steps 3e-3 and 1e-3) for every bond parameter.

    Forward and reverse mode differentiate the same piecewise-smooth program and
    agree to 1e-4 (relative): they sum in different orders, and each yield kink
    passes the round-off on (measured: 1.3e-8 for E, 5.1e-6 for eps_lim).  The run goes on to the peak and softening, but past the
    first break the events cascade and the response is no longer smooth.  Before
    it, bonds yield and soften (so eps_lim and gamma_lim act); the response is
    piecewise smooth (every yield is a kink).  Where the response is smooth at the
    scale of the differences (their two steps agree within 1 %), AD must be within
    1 % of the difference at 3e-3; for every parameter within 5 %.  Smaller
    effects are made of few kinks, and the two steps see different ones: measured
    d ln sigma / d ln p = 3.78 for E, 1.35e-2 for gamma_lim (AD; differences
    1.31e-2 at 3e-3 and 1.24e-2 at 1e-3) and 1.84e-3 for eps_lim.
    """
    full, params = model_and_params()
    c = target_curve()
    n_rec = int(np.argmax(c["fracture_degree"] > 0))
    assert n_rec > 10 and c["stress"][n_rec] > 0.5 * c["stress"].max()
    # only the records before the first break enter: run the test that far
    model = full.replace(plan=full.plan.replace(n_records=n_rec))
    prefix = np.asarray(lab.curve(model, cb.material(params, TRUE)).history["axial_stress"])
    np.testing.assert_array_equal(prefix, c["stress"][:n_rec])
    grad = jax.jit(jax.grad(_window_mean), static_argnums=2)(params, model, n_rec)
    x0 = jnp.asarray([float(getattr(params, n)) for n in GRAD_FIELDS])

    def of_fields(x):
        return _window_mean(params._replace(**{n: x[i] for i, n in enumerate(GRAD_FIELDS)}),
                            model, n_rec)

    fwd = np.asarray(jax.jit(jax.jacfwd(of_fields))(x0)) * np.asarray(x0)
    # the 28 difference points (7 fields x 2 steps x +-) as one vmapped run
    rels, signs = (3e-3, 1e-3), (1.0, -1.0)
    eye = np.eye(len(GRAD_FIELDS))
    points = np.asarray([np.asarray(x0) * (1 + sg * rel * eye[k]) for k in range(len(GRAD_FIELDS))
                         for rel in rels for sg in signs])
    values = np.asarray(jax.jit(jax.vmap(of_fields))(jnp.asarray(points)))
    values = values.reshape(len(GRAD_FIELDS), len(rels), len(signs))
    report = {}
    for k, name in enumerate(GRAD_FIELDS):
        x = float(x0[k])
        fds = [float(values[k, i, 0] - values[k, i, 1]) / (2 * rel)     # x df/dx, step rel x
               for i, rel in enumerate(rels)]
        report[name] = (float(getattr(grad, name)) * x, float(fwd[k]), fds)
    print(report)
    largest = max(abs(fds[0]) for _, _, fds in report.values())
    smooth = [name for name, (_, _, fds) in report.items()
              if abs(fds[0]) >= 0.01 * largest
              and abs(fds[0] - fds[1]) <= 0.01 * max(abs(fds[0]), abs(fds[1]))]
    assert {"bond_youngs", "bond_poisson", "bond_tensile", "bond_cohesion"} <= set(smooth)
    for name, (rev, fw, fds) in report.items():
        assert abs(fw - rev) <= 1e-4 * abs(rev), (name, fw, rev)
        tol = 0.01 if name in smooth else 0.05
        assert abs(rev - fds[0]) <= tol * abs(fds[0]), (name, rev, fds)


@pytest.mark.slow
def test_gradients_finite_through_breakage():
    """Reverse-mode gradient of the whole curve's loss (through the peak and the
    bond breaks) is finite and non-zero for every bond parameter.  Slow (~100 s);
    the default suite differentiates through breakage in forward mode in the
    calibration tests."""
    model, params = model_and_params()
    target = cb.load_target(target_curve())
    start = cb.material(params, dict(E=36e9, strength=2.5e6, kappa=4e-3))
    (loss, out), g = jax.value_and_grad(cb.calibration_loss, has_aux=True)(start, model, target)
    assert float(out["fracture_degree"][-1]) > 0.05
    assert np.isfinite(float(loss)) and float(loss) > 0
    for name in GRAD_FIELDS:
        v = np.asarray(getattr(g, name))
        assert np.all(np.isfinite(v)), name
    assert float(g.bond_youngs) != 0.0 and float(g.bond_tensile) != 0.0


def test_calibration_refuses_a_set_up_that_is_not_quasi_static():
    """The old default of the differentiable test (5 nm per step on this
    specimen, 1.1e-4 of the wave speed) is not quasi-static: calibration says so
    and stops before fitting."""
    fast = lab.UCS.setup(specimen(2), lt.rock_params(2, kappa=3e-3), max_strain=MAX_STRAIN,
                         platen_step=5e-9)
    with pytest.raises(InputError, match="not quasi-static"):
        cb.calibrate(fast, target_curve(), dict(E=36e9), progress=False)


def test_target_in_percent_or_mpa_is_refused():
    e = np.linspace(0, 3e-3, 301)
    s = 1e10 * e * np.exp(-e / 1e-3)
    with pytest.raises(InputError, match="percent"):
        cb.load_target((100 * e, s))
    with pytest.raises(InputError, match="MPa"):
        cb.load_target((e, s / 1e6))


# ----------------------------------------------------------------------------- targets, loss
def test_load_target_sources_and_errors(tmp_path):
    e = np.linspace(0, 3e-3, 301)
    # linear (1e10 Pa) to 5 MPa, then a peak of 7 MPa at 1.5e-3, then softening
    s = np.where(e <= 5e-4, 1e10 * e, np.where(e <= 1.5e-3, 5e6 + 2e9 * (e - 5e-4),
                                               7e6 - 3e9 * (e - 1.5e-3)))
    t = cb.load_target((e, s))
    assert t.peak_strain == pytest.approx(1.5e-3) and t.peak_stress == pytest.approx(7e6)
    assert t.modulus == pytest.approx(1e10, rel=1e-9)
    f = tmp_path / "curve.csv"
    f.write_text("strain,stress\n" + "".join(f"{a},{b}\n" for a, b in zip(e, s)))
    np.testing.assert_allclose(cb.load_target(f).stress, s)
    assert cb.load_target({"axial_strain": e, "axial_stress": s}).peak_stress == t.peak_stress
    bad = tmp_path / "bad.csv"
    bad.write_text("0,0\n1e-3,5e6\nx,y\n")
    with pytest.raises(InputError, match="line 3"):
        cb.load_target(bad)
    with pytest.raises(InputError, match="does not exist"):
        cb.load_target(tmp_path / "missing.csv")
    # a spreadsheet's byte-order mark is not a header: the first row is kept
    bom = tmp_path / "bom.csv"
    bom.write_bytes("\ufeff".encode() + "".join(f"{a},{b}\n" for a, b in zip(e, s)).encode())
    assert len(cb.load_target(bom).strain) == len(e)
    typo = tmp_path / "typo.csv"
    typo.write_text("0.0o1,5e6\n" + "".join(f"{a},{b}\n" for a, b in zip(e[1:], s[1:])))
    with pytest.raises(InputError, match="line 1"):     # a typo, not a header
        cb.load_target(typo)
    with pytest.raises(InputError, match="not a file"):
        cb.load_target(tmp_path)
    binary = tmp_path / "curve.xlsx"
    binary.write_bytes(b"PK\x03\x04\x14\x00\x06\x00\x08\x00\xff\xfe\x00")
    with pytest.raises(InputError, match="not a text CSV"):
        cb.load_target(binary)
    with pytest.raises(InputError, match="must increase"):
        cb.load_target((e[::-1], s))
    s2 = s.copy()
    s2[4] = np.nan
    with pytest.raises(InputError, match=r"stress\[4\]"):
        cb.load_target((e, s2))
    with pytest.raises(InputError, match="differ in length"):
        cb.load_target((e, s[:-1]))


def test_lateral_strain_without_readings_carries_no_residual(tmp_path):
    """A lateral-strain column may stop (a gauge that failed at the peak): empty
    CSV cells / NaN are "no reading" and carry no residual; a column with fewer
    than 3 readings is refused."""
    e = np.linspace(0, 3e-3, 301)
    s = 1e10 * e * np.exp(-e / 1e-3)
    lat = -0.2 * e
    f = tmp_path / "lat.csv"
    f.write_text("strain,stress,lateral\n" + "".join(
        f"{a},{b},{c if i <= 150 else ''}\n" for i, (a, b, c) in enumerate(zip(e, s, lat))))
    t = cb.load_target(f, lateral_column=2)
    assert np.all(np.isnan(t.lateral_strain[151:]))
    assert np.all(np.isfinite(t.lateral_strain[:151]))
    wrong_after = np.where(np.arange(e.size) <= 150, lat, 5 * lat)   # differs only unread
    r_same = cb.curve_residuals(jnp.asarray(e), jnp.asarray(s), t, lateral=jnp.asarray(lat))
    r_off = cb.curve_residuals(jnp.asarray(e), jnp.asarray(s), t,
                               lateral=jnp.asarray(wrong_after))
    np.testing.assert_allclose(r_same[-301:], 0.0, atol=1e-12)     # the lateral part
    np.testing.assert_array_equal(r_off, r_same)
    r_read = cb.curve_residuals(jnp.asarray(e), jnp.asarray(s), t, lateral=jnp.asarray(0.5 * lat))
    assert float(jnp.sum(r_read ** 2)) > 0.01
    # the solvers pass the target into their compiled step as an argument: the
    # residuals must trace with the target's arrays abstract
    traced = jax.jit(lambda tt, lat_: cb.curve_residuals(jnp.asarray(e), jnp.asarray(s), tt,
                                                          lateral=lat_))
    np.testing.assert_allclose(np.asarray(traced(t, jnp.asarray(0.5 * lat))), np.asarray(r_read),
                               rtol=1e-12, atol=1e-15)
    few = np.full(e.size, np.nan)
    few[:2] = 0.0
    with pytest.raises(InputError, match="2 readings"):
        cb.load_target(dict(strain=e, stress=s, lateral_strain=few))


def test_curve_loss_interpolates_onto_target_strains():
    e = np.linspace(0, 3e-3, 301)
    s = 1e10 * e * np.exp(-e / 1e-3)
    t = cb.load_target((e[::7], s[::7]))          # the target sampled elsewhere
    same = float(cb.curve_loss(jnp.asarray(e), jnp.asarray(s), t))
    off = float(cb.curve_loss(jnp.asarray(e), jnp.asarray(1.1 * s), t))
    assert same < 1e-5
    assert off > 100 * same and off > 0.01


def test_material_and_bad_names():
    p = lt.rock_params(2, kappa=3e-3)
    q = cb.material(p, dict(E=45e9, strength=4e6, kappa=5e-3))
    assert float(q.bond_youngs) == 45e9
    assert float(q.bond_tensile) == float(q.bond_cohesion) == 4e6
    assert float(q.bond_tensile_strain) == float(q.bond_shear_strain) == 5e-3
    assert float(q.kn[0]) == pytest.approx(1.5 * float(p.kn[0]))
    assert float(q.kn[1]) == float(p.kn[1])                      # platen unchanged
    with pytest.raises(InputError, match="'Young'"):
        cb.material(p, {"Young": 1.0})
    model, params = model_and_params()
    with pytest.raises(InputError, match="outside its bounds"):
        cb.calibrate(model, target_curve(), dict(E=30e9), params=params,
                     bounds={"E": (1e9, 2e9)}, progress=False)
    # rock_params' placeholder time step instead of the set-up's: refused, since the
    # run may stay finite while its derivatives blow up (measured: d stress / d log E
    # ~1e25 MPa after ~55 records)
    with pytest.raises(InputError, match=r"params\.dt = 1e-08 s, but set-up 0 \(ucs\)"):
        cb.calibrate(model, target_curve(), dict(E=30e9), params=lt.rock_params(2, kappa=3e-3),
                     progress=False)


# ----------------------------------------------------------------------------- recovery
@pytest.mark.slow
def test_calibration_three_parameters_on_the_targets_packing(tmp_path):
    """The issue's recovery check on the target's own packing, noise-free, from
    E +40 %, strength -30 %, kappa +50 %: Levenberg-Marquardt with forward-mode
    Jacobians ends with E within 1 %, strength within 2 %, kappa within 10 % in at
    most 20 iterations; the result reopens from HDF5.

    Slow (about 1 minute on two cores, the fit 45 s; measured E -0.05 %, strength -0.26 %,
    kappa +1.2 % in 20 iterations); the default suite asserts the two-parameter
    recovery of the calibration demo (tests/test_cli.py)."""
    model, params = model_and_params()
    start = dict(E=1.4 * TRUE["E"], strength=0.7 * TRUE["strength"], kappa=1.5 * TRUE["kappa"])
    res = cb.calibrate(model, target_curve(), start, params=params, steps=20, progress=False,
                       out=tmp_path / "cal.h5", require_quasi_static=False)
    print(cb.report(res, TRUE))
    assert res.method == "lm" and res.jacobian == "forward"
    tolerance = dict(E=0.01, strength=0.02, kappa=0.10)
    assert all(abs(res.values[n] / TRUE[n] - 1) < tol for n, tol in tolerance.items())
    # the "a typical fit converges in <= 15 iterations": the iterate is
    # inside every tolerance by the 15th evaluation and stays there
    inside = [all(abs(res.history[n][k] / TRUE[n] - 1) < tol for n, tol in tolerance.items())
              for k in range(res.steps)]
    print("inside the tolerances at iterations", [k for k, v in enumerate(inside) if v])
    assert inside.index(True) < 15 and all(inside[inside.index(True):])
    assert res.history["loss"][0] > 100 * res.loss
    assert res.correlation.shape == (3, 3)
    np.testing.assert_allclose(np.diag(res.correlation), 1.0, rtol=1e-9)
    for n in start:
        lo, hi = res.intervals[n]
        assert lo < res.values[n] < hi and res.std_errors[n] > 0
    back = cb.load_calibration(tmp_path / "cal.h5")
    assert back["values"] == pytest.approx(res.values)
    assert back["intervals"]["E"] == pytest.approx(res.intervals["E"])
    np.testing.assert_allclose(back["curves"]["fit_stress"], res.curves["fit_stress"])
    np.testing.assert_allclose(back["history"]["loss"], res.history["loss"])
    np.testing.assert_allclose(back["correlation"], res.correlation)


def test_calibration_file_layout_and_version_1_files(tmp_path):
    """save_calibration writes groups (attrs/fit, history/iterations, ...) that
    plain h5py reads; load_calibration reads them and the flat, prefixed names
    of format version 1 alike."""
    import h5py

    from jdem import io

    _, params = model_and_params()
    res = cb.CalibrationResult(
        values=dict(E=3.1e10), loss=0.5, start=dict(E=4.2e10),
        history=dict(loss=np.array([2.0, 0.5]), E=np.array([4.2e10, 3.1e10])), steps=2,
        converged=True, params=params, curves=dict(strain=np.arange(3.0),
                                                   fit_stress=np.arange(3.0) * 2),
        wall_time=1.0, std_errors=dict(E=1e8), intervals=dict(E=(2.9e10, 3.3e10)),
        correlation=np.eye(1), poorly_determined={}, warnings=["w"], stop="converged")
    cb.save_calibration(tmp_path / "c.h5", res)
    with h5py.File(tmp_path / "c.h5", "r") as f:
        assert f["attrs/fit"].attrs["E"] == 3.1e10
        np.testing.assert_array_equal(f["history/iterations/loss"][()], [2.0, 0.5])
    back = cb.load_calibration(tmp_path / "c.h5")
    v1 = tmp_path / "v1.h5"
    io.save_run(v1, params=params, history={"iter_loss": res.history["loss"],
                                            "iter_E": res.history["E"], **res.curves,
                                            "correlation": np.eye(1)},
                attrs=dict(fit_E=3.1e10, start_E=4.2e10, stderr_E=1e8,
                           ci95_E=[2.9e10, 3.3e10], loss=0.5, steps=2, converged=True,
                           wall_time=1.0, method="lm", jacobian="forward", names=["E"],
                           diverged=[], warnings=["w"]))
    old = cb.load_calibration(v1)
    assert back["stop"] == "converged" and old["stop"] == ""      # version 1 had none
    for got in (back, old):
        assert got["values"] == res.values and got["start"] == res.start
        assert got["intervals"] == res.intervals and got["std_errors"] == res.std_errors
        assert got["steps"] == 2 and got["converged"] and got["warnings"] == ["w"]
        np.testing.assert_array_equal(got["history"]["loss"], res.history["loss"])
        np.testing.assert_array_equal(got["curves"]["fit_stress"], res.curves["fit_stress"])
        np.testing.assert_array_equal(got["correlation"], np.eye(1))


def test_interrupted_calibration_resumes_from_its_checkpoint(tmp_path):
    """E from +40 %: a fit stopped after 1 iteration leaves a checkpoint; a fit
    resumed from it keeps that iteration in its history, continues from the
    best point so far (its first new loss equals the best, to the round-off of
    the bounded transform), and two resumptions of
    the same checkpoint give the same result bit for bit.  The solver's damping
    is not in the checkpoint: a resumed Levenberg-Marquardt fit restarts it at
    the saved point, so it does not retrace the uninterrupted fit's path."""
    model, params = model_and_params()
    start = dict(E=1.4 * TRUE["E"])
    kw = dict(params=params, progress=False, require_quasi_static=False)
    part = cb.calibrate(model, target_curve(), start, steps=1, checkpoint=tmp_path / "ck.h5",
                        **kw)
    assert part.steps == 1 and (tmp_path / "ck.h5").exists()
    assert part.stop == "steps" and not part.converged
    saved = cb.load_calibration(tmp_path / "ck.h5")
    assert saved["steps"] == 1 and saved["values"] == pytest.approx(part.values)
    runs = [cb.calibrate(model, target_curve(), start, steps=3, resume=tmp_path / "ck.h5", **kw)
            for _ in range(2)]
    print(part.history["loss"], runs[0].history["loss"], runs[0].values)
    for res in runs:
        assert res.steps == 3
        np.testing.assert_array_equal(res.history["loss"][:1], part.history["loss"])
        assert res.history["loss"][1] <= min(part.history["loss"]) * (1 + 1e-3)
        assert res.loss <= part.loss
    assert runs[0].values == runs[1].values
    np.testing.assert_array_equal(runs[0].history["loss"], runs[1].history["loss"])
    assert abs(runs[0].values["E"] / TRUE["E"] - 1) < abs(start["E"] / TRUE["E"] - 1)


def test_a_fit_without_progress_stops_as_stalled_not_converged():
    """A fit that asks for a 99.9 % fall of the loss per iteration (patience 1)
    stops on the first accepted iteration that falls short: ``stop`` is "stalled",
    ``converged`` False, and a warning says so (a stall used to be reported as
    converged)."""
    model, params = model_and_params()
    with pytest.warns(UserWarning, match="stalled"):
        res = cb.calibrate(model, target_curve(), dict(E=1.4 * TRUE["E"]), params=params,
                           steps=6, patience=1, min_improvement=0.999, progress=False,
                           require_quasi_static=False)
    print(res.history["loss"], res.stop)
    assert res.stop == "stalled" and not res.converged and res.steps < 6
    assert any("stalled" in w for w in res.warnings)
    assert "stalled" in cb.report(res)


def test_rejected_steps_stop_a_fit_only_without_real_progress_between_them():
    """The stall bookkeeping of the solvers (solvers.Progress), on the README
    demo's loss sequence: after the loss settles, ``MAX_REJECTED`` rejected
    steps stop the fit; an accepted step that improves by less than
    ``min_improvement`` does not start the count again (one did at iteration
    17 of the demo, and the fit ran on to its budget), one that improves by
    more does; ``patience`` counts only accepted steps without such an
    improvement."""
    from jdem.calibrate.solvers import MAX_REJECTED, Progress

    def run(events, patience=3):
        progress = Progress(np.inf, patience, 1e-3)
        for k, (loss, accepted) in enumerate(events):
            why = progress.update(loss, accepted)
            if why is not None:
                return k, why
        return None, None

    settle = [(0.25, True), (1.0e-2, True), (1.0e-4, True), (9.9e-5, True)]
    k, why = run(settle + [(5.0, False)] * MAX_REJECTED)
    assert k == len(settle) + MAX_REJECTED - 1 and "rejected" in why
    # a 0.05 % improvement between the rejections does not reset their count ...
    tiny = settle + [(5.0, False)] * 2 + [(9.895e-5, True)] + [(5.0, False)] * MAX_REJECTED
    k, why = run(tiny, patience=5)
    assert k == len(settle) + MAX_REJECTED and "rejected" in why
    # ... a 1 % improvement does
    real = settle + [(5.0, False)] * 2 + [(9.8e-5, True)] + [(5.0, False)] * (MAX_REJECTED - 1)
    assert run(real) == (None, None)
    # patience: accepted steps without a 0.1 % improvement, rejections not counted
    flat = settle + [(9.899e-5, True), (5.0, False), (9.898e-5, True), (9.897e-5, True)]
    k, why = run(flat)
    assert k == len(flat) - 1 and "accepted iterations" in why


@pytest.mark.slow
def test_extrapolated_fit_recovers_the_strength_the_run_at_the_rate_misses():
    """Against the quasi-static estimate of the true curve (lab.quasi_static_history:
    the run at the model's rate and at half of it, extrapolated to rate zero),
    fitting the strength on the run at the rate leaves the rate in it (the
    dynamic peak is higher, so the fitted strength is low by > 5 %), while
    ``extrapolate_rate=True`` recovers it within 0.5 %.  Its residuals are those
    of the extrapolation of the two runs' histories.

    The fit weighs the curve up to the peak and the peak (post_peak = 0): past
    the first breaks the exact derivative of the curve follows the realised
    break sequence and is spiky (|J|^2 of the post-peak points ~5, their J.r
    ~0.02 at strength -15 %), which shrinks Gauss-Newton steps to ~1 % of the
    way from a far start.  Measured: plain -19.5 %, extrapolated +0.006 % in 6
    iterations.  Slow (~4 min)."""
    model, params = model_and_params()
    qs = lab.quasi_static_history(model, cb.material(params, TRUE))
    target = dict(strain=qs["axial_strain"], stress=qs["axial_stress"])
    start = dict(strength=0.85 * TRUE["strength"])
    weights = cb.LossWeights(post_peak=0.0)
    kw = dict(params=params, progress=False, require_quasi_static=False, steps=6, weights=weights)
    plain = cb.calibrate(model, target, start, **kw)
    extrap = cb.calibrate(model, target, start, extrapolate_rate=True, **kw)
    err = {k: r.values["strength"] / TRUE["strength"] - 1 for k, r in
           (("plain", plain), ("extrapolated", extrap))}
    print(err, plain.steps, extrap.steps)
    assert err["plain"] < -0.05
    assert abs(err["extrapolated"]) < 5e-3
    # the fitted curve reported is the extrapolated one
    np.testing.assert_allclose(np.max(extrap.curves["fit_stress"]), np.max(target["stress"]),
                               rtol=5e-3)
    # residuals: those of the extrapolation of the two runs' histories
    from jdem.calibrate.problem import make_terms, residual_problem, term_residuals
    from jdem.calibrate.transform import bounds_for, to_internal
    lims = {"strength": bounds_for("strength", start["strength"], None)}
    terms = make_terms(model, target, weights, extrapolate_rate=True)
    fn, args = residual_problem(["strength"], lims, terms, [params])
    r, _ = fn(jnp.asarray([to_internal(start["strength"], *lims["strength"])]), args)
    prm = cb.material(params, start)
    hist = lab.extrapolated_history(lab.curve(model, prm).history,
                                    lab.curve(terms[0].slow, prm).history)
    np.testing.assert_allclose(r, term_residuals(hist, terms[0])[0], rtol=1e-9, atol=1e-12)


# slow (~50 s): Levenberg-Marquardt, the default, is what the default suite fits with
@pytest.mark.slow
def test_adam_with_forward_mode_gradient_lowers_the_loss():
    """The first-order alternative: three Adam steps on E from +40 %, the gradient
    2 J^T r by forward mode, lower the loss and move E towards the truth."""
    model, params = model_and_params()
    res = cb.calibrate(model, target_curve(), dict(E=1.4 * TRUE["E"]), params=params,
                       method="adam", steps=3, learning_rate=0.2, progress=False,
                       require_quasi_static=False)
    print(res.history)
    assert res.method == "adam" and res.jacobian == "forward" and res.steps == 3
    assert res.history["loss"][-1] < res.history["loss"][0]
    assert res.values["E"] < 1.4 * TRUE["E"]


def test_a_fitted_curve_without_a_peak_is_reported():
    """A curve (or a peak / strength target) whose run peaks at its last record
    has no failure in it: ``peakless`` names the term and the member."""
    model, _ = model_and_params()
    rising = dict(axial_stress=np.linspace(0, 1e7, 50)[None].repeat(2, 0))
    rising["axial_stress"][0, 30:] = 5e6                     # member 0 peaks inside
    ens_term = cb.Term(model, (cb.Scalar("peak_stress", 1e7, 1e6),), cb.LossWeights())
    msgs = cb.peakless([ens_term], [rising])
    assert len(msgs) == 1 and "[1]" in msgs[0] and "max_strain" in msgs[0]
    peaked = dict(axial_stress=np.sin(np.linspace(0, 3, 50)) * 1e7)
    assert cb.peakless([ens_term], [peaked]) == []
    modulus_only = cb.Term(model, (cb.Scalar("youngs_modulus", 3e10, 1e9),), cb.LossWeights())
    assert cb.peakless([modulus_only], [dict(axial_stress=np.linspace(0, 1e7, 50))]) == []


def test_ensemble_member_that_diverges_is_isolated():
    """Two packings in one vmapped run, member 1 with a time step 30x too large:
    it diverges, its residuals count as a 100 % misfit (1 each), member 0's are
    its own curve's, and the term's residuals are the two members' mean."""
    params0 = lt.rock_params(2, kappa=3e-3)
    kw = dict(max_strain=MAX_STRAIN, loading_rate=RATE, stiffness_margin=2.0,
              precision="float64")
    ens = lab.UCS.setup([specimen(2), specimen(3)], params0, **kw)
    pe = ens.params
    bad = pe._replace(dt=30.0 * pe.dt)
    both = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), pe, bad)
    hist = {k: np.asarray(v) for k, v in lab.curve(ens, both).history.items()}
    assert hist["member_first_bad_step"][0] < 0 <= hist["member_first_bad_step"][1]
    term = cb.problem.make_terms(ens, target_curve(), cb.LossWeights())[0]
    mean, ok, r = (np.asarray(x) for x in cb.term_residuals(hist, term))
    assert ok.tolist() == [True, False]
    np.testing.assert_allclose(r[1], 1.0)
    np.testing.assert_allclose(mean, (r[0] + 1.0) / 2, rtol=1e-12)
    own = cb.curve_residuals(jnp.asarray(hist["axial_strain"][0]),
                             jnp.asarray(hist["axial_stress"][0]), term.target)
    # the residuals are O(1e-3..1); where the member's curve meets the target
    # they are round-off (3e-16), and the vmapped and the plain evaluation round
    # differently there (measured 3.1e-16 against 2.4e-16), hence the atol
    np.testing.assert_allclose(r[0], np.asarray(own), rtol=1e-12, atol=1e-12)


def test_scalar_targets_are_z_scores_and_terms_concatenate():
    """A curve term and a scalar term (peak stress 10 % above the simulated one,
    sigma 5 % of it) give the curve's residuals followed by the z-score -2."""
    model, params = model_and_params()
    c = target_curve()
    peak = float(np.max(c["stress"]))
    terms = cb.problem.make_terms([model, model], [c, cb.Scalar("peak_stress", 1.1 * peak, 0.05 * peak)],
                      cb.LossWeights())
    names, lims = ("E",), {"E": (1e9, 1e11)}
    u = jnp.asarray([cb.transform.to_internal(TRUE["E"], *lims["E"])])
    r, aux = jax.jit(lambda u, a: cb.problem.residual_fn(u, a, names=names, lims=lims,
                                                  terms=tuple(terms)))(
        u, ((model, None, cb.material(params, TRUE)), (model, None, cb.material(params, TRUE))))
    r = np.asarray(r)
    assert r.shape == (len(c["strain"]) + 2 + 1,)
    # the same run by hand (E through the bounded transform).  Two compiled
    # programs sum forces in different orders; up to the first break that is
    # round-off, and past it the bond events amplify it (measured up to 5e-4).
    e_used = float(cb.transform.to_value(u[0], *lims["E"]))
    hist = lab.curve(model, cb.material(params, dict(TRUE, E=e_used))).history
    expect = np.asarray(cb.curve_residuals(hist["axial_strain"], hist["axial_stress"],
                                           terms[0].target))
    first_break = int(np.argmax(c["fracture_degree"] > 0))
    np.testing.assert_allclose(r[:first_break], expect[:first_break], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(r[:-1], expect, atol=2e-3)
    assert r[-1] == pytest.approx(-2.0, rel=2e-3)   # (peak - 1.1 peak) / (0.05 peak)
    assert float(aux["loss"]) == pytest.approx(float(np.sum(r ** 2)))
    with pytest.raises(InputError, match="quantity"):
        cb.problem.make_terms(model, cb.Scalar("ucs", 1e8, 1e7), cb.LossWeights())
    with pytest.raises(InputError, match="MPa"):
        cb.problem.make_terms(model, cb.Scalar("peak_stress", 200.0, 10.0), cb.LossWeights())


@pytest.mark.slow
def test_poisson_ratio_from_the_lateral_strain_on_the_targets_packing():
    """The issue's nu check: E and nu from E +40 %, nu -30 %, the target curve
    with its mid-height gauge lateral strain up to the peak (NaN after it, as a
    gauge that fails at the peak): E within 1 %, nu within 10 % in at most 20
    iterations.

    Measured (this 2-core CPU, 319 s): 19 iterations, E -0.01 %, nu -0.02 %.  The
    macroscopic Poisson ratio of this 2D packing moves little with the bar's nu
    (lateral / axial strain at half the peak: 0.154, 0.161, 0.168 for nu = 0.15,
    0.22, 0.30), so nu needs the lateral curve to about 1 %.  From the other side
    (E -30 %, nu +40 %) the fit stops after 13 iterations at E +0.2 %, nu +29 %,
    loss 4.4e-4 instead of 1e-7, with E and nu flagged as correlated (+0.99):
    there the stress-curve misfit of the pre-peak bond yields is a local minimum."""
    model, params = model_and_params()
    hist, _ = lab.checked_curve(model, cb.material(params, TRUE))
    k = int(np.argmax(hist["axial_stress"]))
    lateral = np.where(np.arange(hist["lateral_strain"].size) <= k, hist["lateral_strain"],
                       np.nan)
    target = dict(strain=hist["axial_strain"], stress=hist["axial_stress"],
                  lateral_strain=lateral)
    nu = float(params.bond_poisson)
    res = cb.calibrate(model, target, dict(E=1.4 * TRUE["E"], nu=0.7 * nu), params=params,
                       steps=20, progress=False, require_quasi_static=False)
    print(cb.report(res, dict(E=TRUE["E"], nu=nu)))
    truth, tolerance = dict(E=TRUE["E"], nu=nu), dict(E=0.01, nu=0.10)
    assert all(abs(res.values[n] / truth[n] - 1) < tol for n, tol in tolerance.items())
    inside = [all(abs(res.history[n][k] / truth[n] - 1) < tol for n, tol in tolerance.items())
              for k in range(res.steps)]
    print("inside the tolerances at iterations", [k for k, v in enumerate(inside) if v])
    assert inside.index(True) < 15 and all(inside[inside.index(True):])


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="not met: packings of the same statistics differ by "
                   "15 % (~100 discs) / 11 % (~330 discs) std in peak stress at equal "
                   "parameters (experiments/results/packing_scatter/), more than the 5 % "
                   "strength tolerance; fitted on packing 3 (16 % weaker than the target's "
                   "packing 2): E +3.5 %, strength +11 %, kappa +74 %")
def test_recovery_three_parameters_on_a_different_packing():
    """The issue's recovery check: target on packing 2, calibration on packing 3
    from E +40 %, strength -35 %, kappa +50 %: E within 3 %, strength within 5 %,
    kappa within 15 %, in at most 100 steps.

    Measured with the earlier Adam fit (not re-measured since calibrate moved to
    Levenberg-Marquardt; this slow check runs on request).  Why it fails: Adam stopped
    after 70 steps at E +3.5 %, strength
    +11.0 %, kappa +74 % (loss 2.6e-3).  With the true parameters packing 3 peaks at
    11.37 MPa and packing 2 at 13.50 MPa, so packing 3 needs a higher strength to
    reproduce the target curve.  Between packings, the peak stress with the true
    parameters scatters by 14.9 % std over 8 packings of ~100 discs and 11.2 % over 8
    of ~330 discs, the slope of the pre-peak curve by 12-65 % depending on the window
    (``python experiments/packing_scatter.py [--size 0.007 0.014]``); at a 4x slower
    platen the peak scatter is 23.3 % and 16.3 %.  A fit on another packing (or an
    ensemble) therefore lands about that far from the target packing's strength and
    modulus, and the 5 % / 3 % tolerances are met only by chance.

    The same start on the target's own packing 2 ends, after 100 steps, at E -0.15 %,
    strength -5.6 %, kappa +18 % (loss 4.0e-4), near but not inside the tolerances:
    past the peak the loss is rough (bond events) and kappa is weakly determined.
    With a 4x slower platen (1.25 nm, 40-record ramp) it stops after 45 steps at
    E -3.9 %, strength -18 %, kappa +158 % (loss 0.018)."""
    params0 = lt.rock_params(2, kappa=3e-3)
    model = lab.UCS.setup(specimen(3), params0, max_strain=MAX_STRAIN, loading_rate=RATE,
                          stiffness_margin=2.0)
    start = dict(E=1.4 * TRUE["E"], strength=0.65 * TRUE["strength"], kappa=1.5 * TRUE["kappa"])
    res = cb.calibrate(model, target_curve(), start, steps=20, progress=False,
                       require_quasi_static=False)
    print(res.values, res.steps, res.loss)
    assert abs(res.values["E"] / TRUE["E"] - 1) < 0.03
    assert abs(res.values["strength"] / TRUE["strength"] - 1) < 0.05
    assert abs(res.values["kappa"] / TRUE["kappa"] - 1) < 0.15


def test_the_forward_jacobian_wrapper_has_the_exact_reverse_derivative():
    """with_materialised_jacobian (what Levenberg-Marquardt differentiates): its VJP
    J^T ct, by jax.jacrev, is the Jacobian by jax.jacfwd of the plain function,
    and the loss in its aux gets 2 J^T r; values unchanged."""
    from jdem.calibrate.solvers import with_materialised_jacobian

    def fn(u, a):
        r = jnp.stack([jnp.sin(u[0]) * a["c"], u[0] * u[1] ** 2, jnp.exp(-u[1])])
        return r, dict(loss=jnp.sum(r ** 2), ok=jnp.array([True]))

    u, args = jnp.asarray([0.3, -1.2]), dict(c=jnp.asarray(2.0))
    wrapped = with_materialised_jacobian(fn)
    np.testing.assert_allclose(wrapped(u, args)[0], fn(u, args)[0], rtol=0, atol=0)
    exact = jax.jacfwd(lambda v: fn(v, args)[0])(u)
    np.testing.assert_allclose(jax.jacrev(lambda v: wrapped(v, args)[0])(u), exact, rtol=1e-12)
    np.testing.assert_allclose(jax.grad(lambda v: wrapped(v, args)[1]["loss"])(u),
                               jax.grad(lambda v: fn(v, args)[1]["loss"])(u), rtol=1e-12)


def test_fit_model_recovers_an_oscillator_and_reports_what_the_data_do_not_fix():
    """jdem.calibrate.fit_model on a closed-form model: the frequency and decay
    of a damped oscillation are recovered from -30 % / +40 % starts, and a
    parameter the prediction does not depend on is reported as undetermined."""
    import jax.numpy as jnp

    from jdem.calibrate import fit_model

    t = jnp.linspace(0.0, 1.0, 200)
    curve = lambda v: jnp.exp(-v["decay"] * t) * jnp.cos(v["omega"] * t)  # noqa: E731
    data = curve({"omega": 12.0, "decay": 1.5})
    fit = fit_model(curve, data, {"omega": 0.7 * 12.0, "decay": 1.4 * 1.5})
    np.testing.assert_allclose([fit.values["omega"], fit.values["decay"]], [12.0, 1.5],
                               rtol=1e-6)
    assert fit.converged and fit.loss < 1e-12
    idle = fit_model(lambda v: curve(v) + 0.0 * v["unused"], data,
                     {"omega": 12.0, "decay": 1.5, "unused": 3.0})
    assert "unused" in idle.undetermined
    with pytest.raises(InputError, match="outside its bounds"):
        fit_model(curve, data, {"omega": 12.0, "decay": 1.5}, bounds={"omega": (1.0, 5.0)})


def _linear_ensemble_trial(rng, with_spread):
    """One held-out fit of a linear model: K = 4 members f_m = X theta + d_m and a
    target from a fifth "packing", y = X theta_true + d_5, with smooth packing
    deviations d = Z w (w normal); theta fitted to the members' mean by least
    squares, the intervals of :func:`uncertainty` with or without the member
    blocks.  Returns whether each true value lies inside its interval."""
    from jdem.calibrate.result import MemberBlock, uncertainty

    n, K = 60, 4
    x = np.linspace(0.0, 1.0, n)
    X = np.stack([x, np.minimum(x, 0.6)], 1)                # elastic and yield-like shapes
    Z = np.stack([x, x ** 2, np.sin(3.0 * x)], 1)
    true, names = np.array([1.0, 0.5]), ["a", "b"]
    lims = {"a": (-10.0, 10.0), "b": (-10.0, 10.0)}        # linear space
    d = (rng.normal(size=(K + 1, 3)) * 0.05) @ Z.T
    y = X @ true + d[K]
    fit = np.linalg.lstsq(X, y - d[:K].mean(0), rcond=None)[0]
    u = np.array([cb.transform.to_internal(v, *lims[m]) for v, m in zip(fit, names)])
    scale = np.array([cb.transform.dscale_du(ui, *lims[m]) for ui, m in zip(u, names)])
    members = (X @ fit)[None] + d[:K] - y[None]              # term_residuals' layout
    J = X * scale                                            # of the members' mean
    blocks = [MemberBlock(0, n, members, np.ones(K, bool))] if with_spread else []
    unc = uncertainty(J, members.mean(axis=0), u, names, lims, n, blocks)
    return [unc.intervals[m][0] <= t <= unc.intervals[m][1] for m, t in zip(names, true)]


def test_intervals_with_the_packing_spread_cover_a_held_out_packing_95_percent():
    """The held-out check in miniature, where the answer is known: a linear model
    whose members differ by smooth packing deviations, the target from a packing
    outside the ensemble, 2,000 trials.  The Gauss-Newton intervals alone (from the
    misfit of the mean at the optimum) hold the truth 2 % and 0.4 % of the time, the ones with
    the packing-to-packing spread (4 members, Student t with 3 degrees of freedom)
    95 % (measured 95.25 % and 95.35 %; binomial standard deviation 0.5 %)."""
    rng = np.random.default_rng(0)
    alone = np.mean([_linear_ensemble_trial(rng, False) for _ in range(2000)], axis=0)
    spread = np.mean([_linear_ensemble_trial(rng, True) for _ in range(2000)], axis=0)
    assert np.all(alone < 0.5), alone
    assert np.all((spread > 0.935) & (spread < 0.965)), spread


def test_ensemble_fit_reports_its_packing_spread():
    """An ensemble of two packings fitted to a third's curve (E and strength, up
    to the peak): the standard errors carry the packing-to-packing part
    (``packing_std_errors``, positive, at most the whole), the 95 % intervals take
    Student's t (between 1.96 and 12.71 standard errors for 2 members)."""
    params0 = lt.rock_params(2, kappa=3e-3)
    ens = lab.UCS.setup([specimen(3), specimen(4)], params0, max_strain=MAX_STRAIN,
                        loading_rate=RATE, stiffness_margin=2.0)
    res = cb.calibrate(ens, target_curve(), dict(E=1.2 * TRUE["E"], strength=0.8 * TRUE["strength"]),
                       steps=2, weights=cb.LossWeights(post_peak=0.0), progress=False,
                       require_quasi_static=False)
    assert res.loss < res.history["loss"][0]
    print(cb.report(res, TRUE))
    for n, v in res.values.items():
        se, pack = res.std_errors[n], res.packing_std_errors[n]
        assert 0 < pack <= se * (1 + 1e-9), (n, pack, se)
        lo, hi = res.intervals[n]
        half = np.log(hi / lo) / 2 / (se / v)          # quantile used (log-space bounds)
        assert 1.96 < half < 12.71 + 1e-6, (n, half)


def test_finite_difference_jacobian_is_central_differences_with_the_aux_folded():
    """finite_difference_jacobian on a smooth function: the central differences
    (error h^2 f'''/6), the primal residuals unchanged; a shifted run that
    overflows or diverges marks the base run's aux; bad modes are refused."""
    from jdem.calibrate.solvers import finite_difference_jacobian, with_materialised_jacobian

    def fn(u, a):
        r = jnp.stack([jnp.sin(u[0]) * a, u[0] * u[1] ** 2, jnp.exp(-u[1])])
        over = u[1] > -1.1995                    # only the +h shift of u[1] crosses
        return r, dict(loss=jnp.sum(r ** 2), overflowed=over[None],
                       ok=(jnp.array([True, ~over]),))

    u, a = jnp.asarray([0.3, -1.2]), jnp.asarray(2.0)
    r, aux, J = finite_difference_jacobian(fn, u, a, step=1e-3)
    np.testing.assert_array_equal(r, fn(u, a)[0])
    np.testing.assert_allclose(J, jax.jacfwd(lambda v: fn(v, a)[0])(u), rtol=2e-6)
    assert bool(aux["overflowed"][0]) and np.asarray(aux["ok"][0]).tolist() == [True, False]
    wrapped = with_materialised_jacobian(fn, "finite-difference", 1e-3)
    np.testing.assert_allclose(jax.jacrev(lambda v: wrapped(v, a)[0])(u), J, rtol=1e-12)
    with pytest.raises(InputError, match="mode"):
        with_materialised_jacobian(fn, "secant")


@pytest.mark.slow
def test_finite_difference_and_forward_jacobians_agree_before_breakage():
    """Slow (~70 s, two float64 compilations).  The calibration's residual Jacobian d r / d u for E on the records before
    the first bond break (smooth there): central differences over the default
    step (0.02 in u, 1.6 % in E) within 1 % of forward mode on every residual
    that moves (float64)."""
    from jdem.calibrate.solvers import jacobian_at

    full, params = model_and_params()
    c = target_curve()
    n_rec = int(np.argmax(c["fracture_degree"] > 0))
    model = full.replace(plan=full.plan.replace(n_records=n_rec))
    target = dict(strain=c["strain"][:n_rec], stress=c["stress"][:n_rec])
    terms = cb.problem.make_terms(model, target, cb.LossWeights())
    names, lims = ("E",), {"E": (6e9, 1.5e11)}
    fn, args = cb.problem.residual_problem(names, lims, terms, [params])
    u = jnp.asarray([cb.transform.to_internal(1.1 * TRUE["E"], *lims["E"])])
    r_fw, J_fw = jacobian_at(fn, u, args, "forward")
    r_fd, J_fd = jacobian_at(fn, u, args, "finite-difference")
    np.testing.assert_allclose(r_fd, r_fw, rtol=1e-12, atol=1e-18)   # two programs' round-off
    moving = np.abs(J_fw[:, 0]) > 0.05 * np.abs(J_fw[:, 0]).max()
    assert moving.sum() > 10
    np.testing.assert_allclose(J_fd[moving, 0], J_fw[moving, 0], rtol=0.01)
