"""The ``jdem`` command line.

    jdem demo [--out results/demo] [--small]   first run: single-bond tension and direct
                                               shear (002 §1.3), plots + HDF5
    jdem ucs [--config file.toml] [--out DIR] [--small]
                                               uniaxial compression of a bonded rock
                                               specimen (002 §2): PNG + HDF5

``jdem ucs`` reads an optional TOML file with the sections and keys below (all
optional; anything else is an error naming the key).  Built-in defaults are the
seed's 002 §2 specimen (5 cm x 10 cm, r in [0.228, 0.422] mm) at the
quasi-static default loading rate (days on a CPU); ``--small`` replaces the
specimen's size with a reduced one (1 cm x 2 cm, ~500 discs: minutes), also where
the file sets it, and says so.

    [specimen]  width, height [m], r_min, r_max [m], seed (int), porosity (target,
                omit for the densest packing), coordination (target N-bar, default 5)
    [material]  E [Pa], nu, T0 [Pa], c0 [Pa], phi_deg, kappa (fracture strain, or a
                list of them: one batched sweep), density [kg/m^3], bond_section
                ("circular", the seed's 002 eq 5, or "slab": unit thickness)
    [loading]   loading_rate (platen speed / wave speed; default quasi-static,
                see jdem.lab.platen), platen_step [m per step] (instead of
                loading_rate; 0 = unused), max_strain, damping ("smooth", the
                default, or "local"), local_damping (alpha of "local", 0.8 in
                002 §2.1), stop_stress_ratio (stop once the stress fell below this
                fraction of the peak; 0 = never), record_every (steps; 0 = about
                200 records), precision ("float32", the default, or "float64";
                jdem.precision)
"""
from __future__ import annotations

# The commands import jdem's modules inside their functions: each switches JAX to
# float64 first (platen steps below a nanometre need it), which must happen
# before any array is made.
import argparse
import os
import pathlib
import sys
import time
import warnings


def demo(out="results/demo", small=False):
    """Single-bond tension and direct shear with the seed's parameters."""
    import numpy as np

    from jdem import io, plot
    from jdem.lab import single_bond
    from jdem.materials import seed_params

    out = _out_dir(out)
    t0 = time.time()
    print("jdem demo: two bonded spheres, R = 0.5 m, E = 10 GPa, T0 = c0 = 3 MPa (002 §1.3)")
    histories = {}
    for mode in ("tension", "shear"):
        kw = dict(strain_rate_per_step=1e-6) if small else {}
        hist, state, config = single_bond.single_bond_test(mode, dim=3, progress=not small, **kw)
        params = seed_params(3)
        analytic = single_bond.analytic_single_bond_curve(mode, hist["strain"], params)
        label = "tensile" if mode == "tension" else "shear"
        plot.plot_single_bond(hist, analytic, f"single linked bar: {mode}",
                          f"{label} strain [%]", f"{label} stress [MPa]", out / f"{mode}.png")
        histories[mode] = hist
        peak = float(np.max(hist["stress"]))
        print(f"  {mode:8s}: peak {peak / 1e6:.3f} MPa, final {hist['stress'][-1] / 1e6:.3f} MPa"
              f"  -> {out / (mode + '.png')}")
    path = io.save_run(out / "demo.h5", history={f"{m}_{k}": v for m, h in histories.items()
                                               for k, v in h.items()},
                       attrs={"what": "single-bond tension and direct shear, 002 §1.3"})
    print(f"  histories -> {path}  ({time.time() - t0:.0f} s)")
    calibration_demo(out, small=small)
    return path


def calibration_demo(out, small=False):
    """Calibration of E and the bond strength against a target UCS curve
    simulated with known values (:func:`jdem.calibrate.demo_problem`), by
    Levenberg-Marquardt with forward-mode Jacobians."""
    import jax

    jax.config.update("jax_enable_x64", True)   # set-ups built in float64, run in float32
    from jdem import calibrate, plot

    t0 = time.time()
    print("jdem demo: calibrating E and T0 = c0 of a ~100-disc specimen against a target "
          "UCS curve (Levenberg-Marquardt, forward-mode Jacobian)")
    # A demonstration of the solver: it loads faster than the certified
    # quasi-static rate (lab.platen.DEFAULT_LOADING_RATE) so that it runs in a
    # minute or two; `jdem calibrate` certifies the rate by default.
    rate = 6.4e-5 if small else 1.6e-5
    print(f"  loading rate {rate:g} (platen / wave speed): faster than the certified "
          f"quasi-static default, so the fitted values describe this rate; "
          f"see README 'Calibrate against your laboratory curve'")
    # E and the strength set the curve up to its peak; kappa (known here) the part
    # after it, where the derivatives follow the realised break sequence and can stall
    # a fit from far away (README, "Known limitations"): fit up to the peak.
    print("  fitting the curve up to its peak and the peak (LossWeights(post_peak=0)): "
          "kappa, which shapes the softening, is known here")
    setup, params, target, true, start = calibrate.demo_problem(loading_rate=rate)
    res = calibrate.calibrate(setup, target, start, steps=12 if small else 20,
                              weights=calibrate.LossWeights(post_peak=0.0),
                              progress=True, out=out / "calibration.h5",
                              require_quasi_static=False)
    plot.plot_calibration(res, out / "calibration.png", true_values=true)
    print(calibrate.report(res, true))
    print(f"  loss {res.history['loss'][0]:.3g} -> {res.loss:.3g} in {res.steps} iterations "
          f"-> {out / 'calibration.png'}, {out / 'calibration.h5'}  ({time.time() - t0:.0f} s)")
    return res


# ----------------------------------------------------------------------------- ucs
UCS_DEFAULTS = {
    "specimen": dict(width=0.05, height=0.10, r_min=0.228e-3, r_max=0.422e-3, seed=0,
                     porosity=None, coordination=5.0),
    "material": dict(E=30e9, nu=0.22, T0=3e6, c0=3e6, phi_deg=30.0, kappa=3e-3,
                     density=2500.0, bond_section="circular"),
    "loading": dict(loading_rate=4e-6, platen_step=0.0, max_strain=3e-3, damping="smooth",
                    local_damping=0.8, stop_stress_ratio=0.3, record_every=0,
                    precision="float32"),
}
UCS_SMALL = {                     # --small: replaces these, also where the file sets them
    "specimen": dict(width=0.01, height=0.02),
}


def _number(where, value, *, lo=None, hi=None, lo_open=False, hi_open=False, integer=False):
    from jdem.validate import InputError
    import math

    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or (integer and not isinstance(value, int)):
        kind = "an integer" if integer else "a number"
        raise InputError(f"{where} must be {kind}, got {value!r}")
    if not math.isfinite(value):
        raise InputError(f"{where} must be finite, got {value!r}")
    if lo is not None and (value < lo or (lo_open and value == lo)):
        raise InputError(f"{where} must be {'>' if lo_open else '>='} {lo}, got {value!r}")
    if hi is not None and (value > hi or (hi_open and value == hi)):
        raise InputError(f"{where} must be {'<' if hi_open else '<='} {hi}, got {value!r}")
    return value


def ucs_settings(config_path=None, small=False, defaults=None, small_settings=None) -> dict:
    """The settings of ``jdem ucs`` (or of ``jdem calibrate``, ``defaults =
    CALIBRATE_DEFAULTS, small_settings = CALIBRATE_SMALL``): built-in defaults,
    overridden by the TOML file; ``--small`` (``small``) then replaces the specimen
    size and the loading rate, also where the file sets them (a smoke test of the
    file: everything else is the file's), and prints each value it replaced.
    Unknown sections / keys and bad values raise :class:`jdem.validate.InputError`
    naming the key and the value."""
    import copy
    import tomllib

    from jdem.validate import InputError, read_text_file

    cfg = copy.deepcopy(UCS_DEFAULTS if defaults is None else defaults)
    small_settings = UCS_SMALL if small_settings is None else small_settings
    from_file = {}
    if config_path is not None:
        path = pathlib.Path(config_path)
        try:
            data = tomllib.loads(read_text_file(path, "--config file", "TOML"))
        except tomllib.TOMLDecodeError as e:
            raise InputError(f"{path}: not valid TOML: {e}") from None
        for sec, vals in data.items():
            if sec not in cfg:
                raise InputError(f"{path}: unknown section [{sec}] (allowed: "
                                 f"{', '.join(cfg)})")
            if not isinstance(vals, dict):
                raise InputError(f"{path}: {sec} must be a table [{sec}], got {vals!r}")
            for key, value in vals.items():
                if key not in cfg[sec]:
                    raise InputError(f"{path}: unknown key {sec}.{key} = {value!r} (allowed in "
                                     f"[{sec}]: {', '.join(cfg[sec])})")
                cfg[sec][key] = value
                from_file[sec, key] = value
    if small:
        for sec, vals in small_settings.items():
            for key, value in vals.items():
                if (sec, key) in from_file and from_file[sec, key] != value:
                    print(f"  --small: {sec}.{key} = {value!r} instead of "
                          f"{from_file[sec, key]!r} from {config_path}")
                cfg[sec][key] = value
    sp, mat, ld = cfg["specimen"], cfg["material"], cfg["loading"]
    for k in ("width", "height", "r_min", "r_max"):
        _number(f"specimen.{k}", sp[k], lo=0, lo_open=True)
    if sp["r_min"] > sp["r_max"]:
        raise InputError(f"specimen.r_min = {sp['r_min']!r} exceeds specimen.r_max = "
                         f"{sp['r_max']!r}")
    if 2 * sp["r_max"] * 4 > min(sp["width"], sp["height"]):
        raise InputError(f"specimen.r_max = {sp['r_max']!r} is too large for a "
                         f"{sp['width']!r} x {sp['height']!r} specimen (want >= 4 diameters "
                         f"across)")
    _number("specimen.seed", sp["seed"], lo=0, integer=True)
    if sp["porosity"] is not None:
        _number("specimen.porosity", sp["porosity"], lo=0, hi=1, lo_open=True, hi_open=True)
    if sp["coordination"] is not None:
        _number("specimen.coordination", sp["coordination"], lo=0, hi=6, lo_open=True,
                hi_open=True)
    _number("material.E", mat["E"], lo=0, lo_open=True)
    _number("material.nu", mat["nu"], lo=-1, hi=0.5, lo_open=True, hi_open=True)
    _number("material.T0", mat["T0"], lo=0)
    _number("material.c0", mat["c0"], lo=0)
    _number("material.phi_deg", mat["phi_deg"], lo=0, hi=90, hi_open=True)
    _number("material.density", mat["density"], lo=0, lo_open=True)
    from jdem.state import BOND_SECTIONS

    if mat["bond_section"] not in BOND_SECTIONS:
        raise InputError(f"material.bond_section must be one of {', '.join(BOND_SECTIONS)}, "
                         f"got {mat['bond_section']!r}")
    kap = mat["kappa"]
    if isinstance(kap, list):
        if not kap:
            raise InputError("material.kappa must be a number or a non-empty list, got []")
        for i, k in enumerate(kap):
            _number(f"material.kappa[{i}]", k, lo=0)
    else:
        _number("material.kappa", kap, lo=0)
    _number("loading.loading_rate", ld["loading_rate"], lo=0, lo_open=True)
    _number("loading.platen_step", ld["platen_step"], lo=0)
    if ld["max_strain"] is not None:
        _number("loading.max_strain", ld["max_strain"], lo=0, hi=0.5, lo_open=True)
    if ld["damping"] not in ("smooth", "local"):
        raise InputError(f"loading.damping must be \"smooth\" or \"local\", got "
                         f"{ld['damping']!r}")
    _number("loading.local_damping", ld["local_damping"], lo=0, hi=1, hi_open=True)
    _number("loading.stop_stress_ratio", ld["stop_stress_ratio"], lo=0, hi=1, hi_open=True)
    _number("loading.record_every", ld["record_every"], lo=0, integer=True)
    from jdem.precision import PRECISIONS

    if ld["precision"] not in PRECISIONS:
        raise InputError(f"loading.precision must be one of {PRECISIONS}, got "
                         f"{ld['precision']!r}")
    return cfg


def _out_dir(out) -> pathlib.Path:
    """``--out`` as a folder that exists and can be written, or ``InputError``."""
    from jdem.validate import InputError

    out = pathlib.Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out '{out}' is a file, not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"--out '{out}' cannot be created: {e.strerror or e}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise InputError(f"--out '{out}' is not writable")
    return out


def _resume_file(path: pathlib.Path, resume: bool):
    """The checkpoint to continue from with ``--resume`` (it must exist)."""
    from jdem.validate import InputError

    if not resume:
        return None
    if not path.exists():
        raise InputError(f"--resume: no checkpoint '{path}' (run without --resume first)")
    return path


def ucs(config=None, out="results/ucs", small=False, progress=True, animate=False,
        paraview=False, resume=False):
    """``jdem ucs``: generate the specimen, compress it, write ``ucs.png`` and
    ``ucs.h5`` to ``out``; with ``animate`` also ``failure.gif`` (the first
    softening strain's failure developing, :func:`jdem.plot.animate_failure`),
    with ``paraview`` the ParaView series ``paraview/ucs.pvd``
    (:func:`jdem.export.write_series`); returns the HDF5 path."""
    import jax
    import numpy as np

    # the set-up is built in float64 and cast to loading.precision (jdem.precision)
    jax.config.update("jax_enable_x64", True)
    from jdem import io, lab, plot, specimen
    from jdem.materials import rock_params

    cfg = ucs_settings(config, small)
    sp, mat, ld = cfg["specimen"], cfg["material"], cfg["loading"]
    out = _out_dir(out)
    t0 = time.time()
    print(f"jdem ucs: {sp['width'] * 100:g} cm x {sp['height'] * 100:g} cm specimen, "
          f"r in [{sp['r_min'] * 1e3:g}, {sp['r_max'] * 1e3:g}] mm")
    spec = specimen.generate("rectangle", (sp["width"], sp["height"]), sp["r_min"], sp["r_max"],
                             seed=sp["seed"], density=mat["density"],
                             target_porosity=sp["porosity"],
                             target_coordination=sp["coordination"], progress=progress)
    print(f"  {spec.info['n_particles']} discs, {spec.info['n_bonds']} bonds, porosity "
          f"{spec.porosity:.3f}, N-bar {spec.coordination:.2f} ({time.time() - t0:.0f} s)")
    kappas = mat["kappa"] if isinstance(mat["kappa"], list) else [mat["kappa"]]
    params = rock_params(2, E=mat["E"], nu=mat["nu"], T0=mat["T0"], c0=mat["c0"],
                         phi_deg=mat["phi_deg"], kappa=mat["kappa"])
    damping = lab.local(ld["local_damping"]) if ld["damping"] == "local" else lab.smooth()
    rate = dict(platen_step=ld["platen_step"]) if ld["platen_step"] else \
        dict(loading_rate=ld["loading_rate"])
    setup = lab.UCS.setup(spec, params, max_strain=ld["max_strain"], damping=damping,
                          record_every=ld["record_every"] or None,
                          bond_section=mat["bond_section"], precision=ld["precision"],
                          **rate)
    print(f"  {setup.plan.n_records * setup.plan.record_every} steps at loading rate "
          f"{setup.plan.option('loading_rate'):.3g} (platen / wave speed), damping "
          f"{setup.plan.damping}")
    t1 = time.time()
    checkpoint = out / "ucs_checkpoint.h5"
    res = lab.run(setup, progress=progress, stop_stress_ratio=ld["stop_stress_ratio"] or None,
                  checkpoint=checkpoint, resume=_resume_file(checkpoint, resume))
    hist, state, config_ = res.history, res.state, res.setup.plan.config
    run_time = time.time() - t1
    summary = lab.peak_summary(hist)
    plot.plot_ucs(hist, kappas, out / "ucs.png")
    attrs = {"what": "uniaxial compression, 002 §2", "run_time_s": run_time,
             "n_particles": int(spec.info["n_particles"]), "porosity": float(spec.porosity),
             "coordination": float(spec.coordination)}
    attrs["settings"] = {sec: {k: "none" if v is None else v for k, v in vals.items()}
                         for sec, vals in cfg.items()}
    attrs["summary"] = {k: np.asarray(v).tolist() for k, v in summary.items()}
    path = io.save_run(out / "ucs.h5", state=state, params=params, config=config_,
                       history=hist, attrs=attrs)
    if animate or paraview:
        from jdem import export
        from jdem.batch import member

        batched = np.ndim(state.step) == 1
        first = member(state, 0) if batched else state
        one = {k: (np.asarray(v)[0] if batched else np.asarray(v)) for k, v in hist.items()
               if k in ("step", "axial_strain", "axial_stress")}
        if animate:
            plot.animate_failure(first, one, out / "failure.gif")
            print(f"  -> {out / 'failure.gif'}")
        if paraview:
            every = max(1, one["step"].size // 50)
            pvd = export.write_series(out / "paraview", first, one, name="ucs", every=every)
            print(f"  -> {pvd} (open in ParaView)")
    for b, k in enumerate(kappas):
        s = {key: np.atleast_1d(v)[b] for key, v in summary.items()}
        print(f"  kappa {k * 100:g} %: peak {s['peak_stress'] / 1e6:.2f} MPa at strain "
              f"{s['critical_strain'] * 1e6:.0f}e-6, E {s['youngs_modulus'] / 1e9:.1f} GPa, "
              f"fracture degree {s['fracture_degree_at_peak'] * 100:.2f} % (peak) / "
              f"{s['fracture_degree_end'] * 100:.2f} % (end)")
    print(f"  {int(np.max(np.asarray(state.step)))} steps in {run_time:.0f} s -> "
          f"{out / 'ucs.png'}, {path}")
    return path


# ----------------------------------------------------------------------------- calibrate
CALIBRATE_DEFAULTS = {
    "specimen": dict(UCS_DEFAULTS["specimen"], width=0.02, height=0.04, members=1),
    "material": dict(UCS_DEFAULTS["material"]),
    "loading": dict(UCS_DEFAULTS["loading"], max_strain=None),
    "fit": dict(parameters=["E", "strength"], method="lm", steps=20, bounds={},
                require_quasi_static=True, extrapolate_rate=False, jacobian="auto"),
}
# --small: a ~100-disc specimen at a fast, uncertified rate (a smoke test of the user's
# CSV and TOML); replaces these, also where the file sets them
CALIBRATE_SMALL = {"specimen": dict(width=0.004, height=0.008, r_min=0.2e-3, r_max=0.35e-3,
                                    seed=2, porosity=None, coordination=4.5),
                   "loading": dict(loading_rate=6.4e-5, platen_step=0.0),
                   "fit": dict(require_quasi_static=False)}
CALIBRATE_SMALL_STEPS = 8         # --small's default iteration budget (the file may set it)


def calibrate_settings(config_path=None, small=False) -> dict:
    """The settings of ``jdem calibrate`` (as :func:`ucs_settings`, plus the
    ``[specimen] members`` ensemble size and the ``[fit]`` table)."""
    import copy

    from jdem.calibrate.fit import JACOBIANS, METHODS
    from jdem.materials import PARAMETERS
    from jdem.validate import InputError

    defaults = copy.deepcopy(CALIBRATE_DEFAULTS)
    if small:
        defaults["fit"]["steps"] = CALIBRATE_SMALL_STEPS
    cfg = ucs_settings(config_path, small, defaults=defaults, small_settings=CALIBRATE_SMALL)
    _number("specimen.members", cfg["specimen"]["members"], lo=1, integer=True)
    if isinstance(cfg["material"]["kappa"], list):
        raise InputError(f"material.kappa must be one number for calibration, got "
                         f"{cfg['material']['kappa']!r}")
    fit = cfg["fit"]
    names = fit["parameters"]
    if not isinstance(names, list) or not names:
        raise InputError(f"fit.parameters must be a non-empty list of names, got {names!r}")
    for n in names:
        if n not in PARAMETERS:
            raise InputError(f"fit.parameters: unknown parameter {n!r}; choose from "
                             f"{sorted(PARAMETERS)}")
    if fit["method"] not in METHODS:
        raise InputError(f"fit.method must be \"lm\", \"gauss_newton\" or \"adam\", got "
                         f"{fit['method']!r}")
    jacobians = ("auto",) + JACOBIANS
    if fit["jacobian"] not in jacobians:
        raise InputError(f"fit.jacobian must be one of {jacobians}, got {fit['jacobian']!r}")
    _number("fit.steps", fit["steps"], lo=1, integer=True)
    if not isinstance(fit["bounds"], dict):
        raise InputError(f"fit.bounds must be a table name = [lo, hi], got {fit['bounds']!r}")
    for n, b in fit["bounds"].items():
        if n not in names:
            raise InputError(f"fit.bounds.{n}: {n!r} is not in fit.parameters {names}")
        if not (isinstance(b, list) and len(b) == 2):
            raise InputError(f"fit.bounds.{n} must be [lo, hi], got {b!r}")
        for k, v in enumerate(b):
            _number(f"fit.bounds.{n}[{k}]", v)
    for key in ("require_quasi_static", "extrapolate_rate"):
        if not isinstance(fit[key], bool):
            raise InputError(f"fit.{key} must be true or false, got {fit[key]!r}")
    return cfg


def _start_value(name, mat):
    import math

    return {"E": mat["E"], "nu": mat["nu"], "T0": mat["T0"], "c0": mat["c0"],
            "phi": math.radians(mat["phi_deg"]), "eps_lim": mat["kappa"],
            "gamma_lim": mat["kappa"], "strength": mat["T0"], "kappa": mat["kappa"]}[name]


def calibrate_cli(curve, config=None, out="results/calibrate", small=False, progress=True,
                  resume=False):
    """``jdem calibrate CURVE.csv``: fit the ``[fit] parameters`` of a bonded
    specimen in the UCS test to a laboratory curve (strain, stress [Pa], and a
    third column, the lateral strain, when the file has one); writes
    ``calibration.png`` and ``calibration.h5`` to ``out``.  Returns the result."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from jdem import calibrate, lab, plot, specimen
    from jdem.materials import rock_params

    cfg = calibrate_settings(config, small)
    sp, mat, ld, fit = cfg["specimen"], cfg["material"], cfg["loading"], cfg["fit"]
    target = calibrate.load_target(curve, lateral_column="auto")
    out = _out_dir(out)
    t0 = time.time()
    print(f"jdem calibrate: target {curve}: {len(target.strain)} points, peak "
          f"{target.peak_stress / 1e6:.3g} MPa at strain {target.peak_strain:.3g}, E "
          f"{target.modulus / 1e9:.3g} GPa")
    specs = [specimen.generate("rectangle", (sp["width"], sp["height"]), sp["r_min"],
                               sp["r_max"], seed=sp["seed"] + m, density=mat["density"],
                               target_porosity=sp["porosity"],
                               target_coordination=sp["coordination"], progress=False)
             for m in range(sp["members"])]
    print(f"  {len(specs)} packing(s) of {specs[0].info['n_particles']} discs, "
          f"{sp['width'] * 100:g} cm x {sp['height'] * 100:g} cm")
    params = rock_params(2, E=mat["E"], nu=mat["nu"], T0=mat["T0"], c0=mat["c0"],
                         phi_deg=mat["phi_deg"], kappa=mat["kappa"])
    damping = lab.local(ld["local_damping"]) if ld["damping"] == "local" else lab.smooth()
    rate = dict(platen_step=ld["platen_step"]) if ld["platen_step"] else \
        dict(loading_rate=ld["loading_rate"])
    max_strain = ld["max_strain"] or 1.05 * float(target.strain[-1])
    setup = lab.UCS.setup(specs if len(specs) > 1 else specs[0], params, max_strain=max_strain,
                          damping=damping, record_every=ld["record_every"] or None,
                          stiffness_margin=2.0, bond_section=mat["bond_section"],
                          precision=ld["precision"], **rate)
    start = {n: _start_value(n, mat) for n in fit["parameters"]}
    bounds = {n: tuple(b) for n, b in fit["bounds"].items()}
    print(f"  fitting {', '.join(start)} ({fit['method']}, at most {fit['steps']} iterations); "
          f"loading rate {setup.plan.option('loading_rate'):.3g}"
          + (" and half of it, extrapolated to rate zero" if fit["extrapolate_rate"] else "")
          + ("" if fit["require_quasi_static"] else
             " -- quasi-static check OFF: the values describe this loading rate"))
    result = out / "calibration.h5"
    res = calibrate.calibrate(setup, target, start, bounds=bounds or None, method=fit["method"],
                              steps=fit["steps"], progress=progress, out=result,
                              require_quasi_static=fit["require_quasi_static"],
                              extrapolate_rate=fit["extrapolate_rate"],
                              jacobian=fit["jacobian"],
                              resume=_resume_file(result.with_suffix(".checkpoint.h5"), resume))
    plot.plot_calibration(res, out / "calibration.png")
    print(calibrate.report(res))
    print(f"  -> {out / 'calibration.png'}, {out / 'calibration.h5'}  "
          f"({time.time() - t0:.0f} s)")
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(prog="jdem", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("demo", help="first run with built-in defaults: plots + HDF5")
    d.add_argument("--out", default="results/demo")
    d.add_argument("--small", action="store_true", help="coarser loading, for a smoke test")
    u = sub.add_parser("ucs", help="uniaxial compression of a bonded rock specimen (002 §2)")
    u.add_argument("--config", default=None, help="TOML file (see `jdem --help`)")
    u.add_argument("--out", default="results/ucs")
    u.add_argument("--small", action="store_true",
                   help="reduced specimen (1 cm x 2 cm, ~500 discs), replacing the "
                        "config's size")
    u.add_argument("--animate", action="store_true",
                   help="also write failure.gif: the cracks developing (first kappa)")
    u.add_argument("--paraview", action="store_true",
                   help="also write paraview/ucs.pvd + .vtu files (first kappa) for ParaView")
    c = sub.add_parser("calibrate", help="fit micro-parameters to a laboratory stress-strain "
                                          "curve (CSV: strain, stress in Pa)")
    c.add_argument("curve", help="CSV file: strain [-], axial stress [Pa] and optionally the "
                                 "lateral strain [-] (empty where not read); one header line "
                                 "allowed")
    c.add_argument("--config", default=None, help="TOML file: [specimen], [material] (start "
                                                  "values), [loading], [fit]")
    c.add_argument("--out", default="results/calibrate")
    c.add_argument("--small", action="store_true",
                   help="~100-disc specimen, fast loading, no quasi-static check, replacing "
                        "the config's specimen and rate (a smoke test of the CSV and config)")
    for p in (u, c):
        p.add_argument("--resume", action="store_true",
                       help="continue an interrupted run from the checkpoint in --out "
                            "(ucs_checkpoint.h5 / calibration.checkpoint.h5), bit for bit")
    args = ap.parse_args(argv)
    from jdem.validate import InputError

    # a warning is a message to the user, not to a programmer: no file and line
    plain = warnings.formatwarning
    warnings.formatwarning = lambda message, category, *rest: \
        f"jdem {args.cmd}: {category.__name__}: {message}\n"
    try:
        if args.cmd == "demo":
            demo(args.out, args.small)
        elif args.cmd == "ucs":
            ucs(args.config, args.out, args.small, animate=args.animate, paraview=args.paraview,
                resume=args.resume)
        else:
            calibrate_cli(args.curve, args.config, args.out, args.small, resume=args.resume)
    except InputError as e:
        print(f"jdem {args.cmd}: error: {e}", file=sys.stderr)
        return 2
    finally:
        warnings.formatwarning = plain
    return 0


if __name__ == "__main__":
    sys.exit(main())
