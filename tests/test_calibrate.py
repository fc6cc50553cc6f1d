"""The pure UCS test (jdem.lab.curve) and calibration (jdem.calibrate).

One ~106-disc specimen (4 mm x 8 mm) and one set-up serve every test, so the
curve and its gradient compile once each.  float64 (tests/conftest.py).

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
                       loading_rate=RATE, stiffness_margin=2.0)
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
    kw = dict(max_strain=MAX_STRAIN, loading_rate=RATE, stiffness_margin=2.0)
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


def test_gradients_match_finite_differences_before_breakage():
    """d(mean stress over the records before the first bond breaks)/d(parameter)
    by jax.grad vs central differences (relative steps 3e-3 and 1e-3) for every
    bond parameter.  The run goes on to the peak and softening, but past the
    first break the events cascade and the response is no longer smooth (finite
    differences then depend on their step; see jdem.lab.damping).  Before it, bonds
    yield and soften (so eps_lim and gamma_lim act).  The response is piecewise
    smooth (every yield is a kink) and the gradient must be within 5 % of the
    difference at 3e-3 for every parameter.  The differences at 3e-3 and 1e-3 must
    agree within 5 % (smooth at that scale) for every parameter whose effect in this
    window is at least 1 % of E's.  Smaller effects are made of few kinks, and
    the two steps see different ones: measured d ln sigma / d ln p = 3.78 for E,
    1.35e-2 for gamma_lim (AD; differences 1.31e-2 at 3e-3 and 1.24e-2 at 1e-3)
    and 1.84e-3 for eps_lim (differences 1.87e-3 and 1.93e-3).
    """
    model, params = model_and_params()
    c = target_curve()
    n_rec = int(np.argmax(c["fracture_degree"] > 0))
    assert n_rec > 10 and c["stress"][n_rec] > 0.5 * c["stress"].max()
    grad = jax.jit(jax.grad(_window_mean), static_argnums=2)(params, model, n_rec)
    f = jax.jit(_window_mean, static_argnums=2)
    report = {}
    for name in GRAD_FIELDS:
        x0 = float(getattr(params, name))
        fds = []
        for rel in (3e-3, 1e-3):
            h = rel * x0
            fp = f(params._replace(**{name: jnp.asarray(x0 + h)}), model, n_rec)
            fm = f(params._replace(**{name: jnp.asarray(x0 - h)}), model, n_rec)
            fds.append(float(fp - fm) / (2 * h) * x0)
        report[name] = (float(getattr(grad, name)) * x0, fds)
    print(report)
    largest = max(abs(fds[0]) for _, fds in report.values())
    smooth = [name for name, (_, fds) in report.items() if abs(fds[0]) >= 0.01 * largest]
    assert {"bond_youngs", "bond_poisson", "bond_tensile", "bond_cohesion"} <= set(smooth)
    for name, (ad, fds) in report.items():
        if name in smooth:
            assert abs(fds[0] - fds[1]) <= 0.05 * max(abs(fds[0]), abs(fds[1])), (name, fds)
        assert abs(ad - fds[0]) <= 0.05 * abs(fds[0]), (name, ad, fds)


def test_gradients_finite_through_breakage():
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
    with pytest.raises(InputError, match="must increase"):
        cb.load_target((e[::-1], s))
    s2 = s.copy()
    s2[4] = np.nan
    with pytest.raises(InputError, match=r"stress\[4\]"):
        cb.load_target((e, s2))
    with pytest.raises(InputError, match="differ in length"):
        cb.load_target((e, s[:-1]))


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


# ----------------------------------------------------------------------------- recovery
def test_calibration_recovers_fracture_strain(tmp_path):
    """kappa = eps_lim = gamma_lim from +50 % on the target's packing: within 15 %
    in at most 100 Adam steps; the result reopens from HDF5."""
    model, params = model_and_params()
    res = cb.calibrate(model, target_curve(), dict(kappa=1.5 * TRUE["kappa"]), params=params,
                       steps=100, progress=False, out=tmp_path / "cal.h5",
                       require_quasi_static=False)
    print(res.values, res.steps, res.loss)
    assert res.steps <= 100
    assert abs(res.values["kappa"] / TRUE["kappa"] - 1) < 0.15
    assert res.history["loss"][0] > 100 * res.loss
    back = cb.load_calibration(tmp_path / "cal.h5")
    assert back["values"] == pytest.approx(res.values)
    np.testing.assert_allclose(back["curves"]["fit_stress"], res.curves["fit_stress"])
    np.testing.assert_allclose(back["history"]["loss"], res.history["loss"])


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

    Why it fails (measured): Adam stops after 70 steps at E +3.5 %, strength
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
    res = cb.calibrate(model, target_curve(), start, steps=100, progress=False,
                       require_quasi_static=False)
    print(res.values, res.steps, res.loss)
    assert abs(res.values["E"] / TRUE["E"] - 1) < 0.03
    assert abs(res.values["strength"] / TRUE["strength"] - 1) < 0.05
    assert abs(res.values["kappa"] / TRUE["kappa"] - 1) < 0.15
