"""Calibration of micro-parameters against stress-strain curves, and batched sweeps.

* Named material parameters (:data:`jdem.materials.PARAMETERS`,
  :func:`jdem.materials.material`) are set on ``Params`` consistently.
* :func:`load_target` reads a target curve (arrays, a dict, a CSV file).
* :func:`curve_loss` compares a simulated curve with a target sampled at other
  strains: interpolation onto common strains, weighting of the pre-peak and
  post-peak parts, peak-stress and modulus terms.
* :func:`calibrate` fits chosen parameters with an optax optimiser (Adam) through
  ``jax.grad`` of the pure lab test (:func:`jdem.lab.curve`, the same
  definition a production run uses), in a bounded log space, with early
  stopping; the result saves to HDF5.  With a set-up built on several packings
  (an ensemble) the loss is averaged over them.  The set-up must be
  quasi-static (:func:`jdem.lab.certify`): calibration refuses one that is not,
  unless ``require_quasi_static=False``.
* Batched parameter sweeps of the platen tests live in :mod:`jdem.sweep`
  (which uses :func:`material` here).

Named parameters (``PARAMETERS``): ``E`` bond Young's modulus [Pa], ``nu``,
``T0`` tensile strength [Pa], ``c0`` cohesion [Pa], ``phi`` friction angle
[rad], ``eps_lim`` / ``gamma_lim`` tensile / shear fracture strains, and the
tied pairs ``strength`` (T0 = c0) and ``kappa`` (eps_lim = gamma_lim, 002 §2.1).
"""
from __future__ import annotations

import csv
import math
import pathlib
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import lab
from jdem import io
from jdem.lab.summary import fit_modulus
from jdem.materials import PARAMETERS, check_names, material, rock_params, values_of  # noqa: F401
from jdem.specimen import generate
from jdem.state import Params
from jdem.validate import InputError

#: default bounds as factors of the starting value (log space), or absolute
DEFAULT_BOUNDS = {"nu": (0.0, 0.45), "phi": (0.0, np.deg2rad(60.0))}
DEFAULT_FACTOR = 5.0
_check_names = check_names


# ----------------------------------------------------------------------------- target curves
class Target(NamedTuple):
    """A target curve and its key figures (NumPy; strain ascending).

    strain, stress    (K,) [-], [Pa]
    peak_stress, peak_strain
    modulus           least-squares slope over 10 %..40 % of the peak, pre-peak
    modulus_window    (lo, hi) strains of that fit
    """

    strain: np.ndarray
    stress: np.ndarray
    peak_stress: float
    peak_strain: float
    modulus: float
    modulus_window: tuple


def load_target(source, *, strain_column=0, stress_column=1) -> Target:
    """A :class:`Target` from ``(strain, stress)`` arrays, a dict with ``strain``
    and ``stress`` (e.g. a simulated curve or history; ``axial_strain`` /
    ``axial_stress`` also work), or a CSV file of two columns (strain, stress in
    Pa; a header line is allowed).  Malformed input raises ``InputError``."""
    if isinstance(source, (str, pathlib.Path)):
        strain, stress = _read_csv(pathlib.Path(source), strain_column, stress_column)
    elif isinstance(source, dict):
        key_e = "strain" if "strain" in source else "axial_strain"
        key_s = "stress" if "stress" in source else "axial_stress"
        if key_e not in source or key_s not in source:
            raise InputError(f"target dict needs 'strain' and 'stress', got keys {sorted(source)}")
        strain, stress = source[key_e], source[key_s]
    else:
        try:
            strain, stress = source
        except (TypeError, ValueError):
            raise InputError("target must be (strain, stress) arrays, a dict or a CSV path, "
                             f"got {type(source).__name__}") from None
    strain = np.asarray(strain, np.float64).ravel()
    stress = np.asarray(stress, np.float64).ravel()
    if strain.shape != stress.shape:
        raise InputError(f"target strain and stress differ in length: {strain.size} vs "
                         f"{stress.size}")
    if strain.size < 5:
        raise InputError(f"target curve needs at least 5 points, got {strain.size}")
    for name, a in (("strain", strain), ("stress", stress)):
        if not np.all(np.isfinite(a)):
            k = int(np.argmin(np.isfinite(a)))
            raise InputError(f"target {name}[{k}] = {a[k]!r} is not finite")
    if np.any(np.diff(strain) <= 0):
        k = int(np.argmin(np.diff(strain) > 0))
        raise InputError(f"target strain must increase: strain[{k + 1}] = {strain[k + 1]!r} "
                         f"after {strain[k]!r}")
    k = int(np.argmax(stress))
    peak = float(stress[k])
    if not peak > 0:
        raise InputError(f"target stress has no positive peak (max {peak!r})")
    if float(np.max(np.abs(strain))) > 0.2:
        raise InputError(f"target strain reaches {float(np.max(np.abs(strain)))!r}: strain is "
                         f"dimensionless (0.003, not 0.3 %); divide a percent column by 100")
    if peak < 1e4:
        raise InputError(f"target peak stress is {peak!r} Pa: stress must be in Pa "
                         f"(this looks like MPa: multiply by 1e6)")
    modulus, window = fit_modulus(strain, stress, min_points=2)
    if not np.isfinite(modulus):
        modulus, window = peak / max(float(strain[k]), 1e-300), (0.0, float(strain[k]))
    return Target(strain, stress, peak, float(strain[k]), modulus, window)


def _read_csv(path, ce, cs):
    if not path.exists():
        raise InputError(f"target file {str(path)!r} does not exist")
    rows = []
    with open(path, newline="") as f:
        for n, row in enumerate(csv.reader(f)):
            if not row or all(not c.strip() for c in row) or row[0].lstrip().startswith("#"):
                continue
            try:
                rows.append((float(row[ce]), float(row[cs])))
            except ValueError:
                if rows:   # only the first line may be a header
                    raise InputError(f"{path}: line {n + 1} is not two numbers: {row!r}") from None
            except IndexError:
                raise InputError(f"{path}: line {n + 1} has {len(row)} column(s), need "
                                 f"{max(ce, cs) + 1}: {row!r}") from None
    if not rows:
        raise InputError(f"{path} holds no (strain, stress) rows")
    a = np.asarray(rows)
    return a[:, 0], a[:, 1]


# ----------------------------------------------------------------------------- loss
class LossWeights(NamedTuple):
    """Weights of :func:`curve_loss` (each term is dimensionless)."""

    pre_peak: float = 1.0
    post_peak: float = 1.0
    peak: float = 1.0
    modulus: float = 1.0


def curve_loss(strain, stress, target: Target, weights: LossWeights = LossWeights()):
    """Mismatch of a simulated curve ``(strain, stress)`` (R,) with ``target``.

    The simulated stress is interpolated (linearly) onto the target strains
    inside the simulated range; the squared differences, divided by the target
    peak squared, are averaged with weight ``pre_peak`` up to the target's peak
    strain and ``post_peak`` after it.  Added: ``peak`` x (relative peak-stress
    error)^2 and ``modulus`` x (relative error of the slope over the target's
    10 %..40 % window)^2.  Differentiable in ``stress``; works on one curve
    (use ``jax.vmap`` for several).
    """
    et = jnp.asarray(target.strain)
    st = jnp.asarray(target.stress)
    inside = (et >= strain[0]) & (et <= strain[-1])
    sim = jnp.interp(et, strain, stress)
    w = jnp.where(et <= target.peak_strain, weights.pre_peak, weights.post_peak) * inside
    curve = jnp.sum(w * (sim - st) ** 2) / jnp.maximum(jnp.sum(w), 1e-300) / target.peak_stress**2
    peak = (jnp.max(stress) / target.peak_stress - 1.0) ** 2
    lo, hi = target.modulus_window
    sel = (strain >= lo) & (strain <= hi)
    n = jnp.maximum(jnp.sum(sel), 1)
    em = jnp.sum(jnp.where(sel, strain, 0.0)) / n
    sm = jnp.sum(jnp.where(sel, stress, 0.0)) / n
    slope = (jnp.sum(jnp.where(sel, (strain - em) * (stress - sm), 0.0))
             / jnp.maximum(jnp.sum(jnp.where(sel, (strain - em) ** 2, 0.0)), 1e-300))
    modulus = (slope / target.modulus - 1.0) ** 2
    return curve + weights.peak * peak + weights.modulus * modulus


# ----------------------------------------------------------------------------- bounded transform
def _bounds_for(name, start, bounds):
    if bounds and name in bounds:
        lo, hi = (float(b) for b in bounds[name])
    elif name in DEFAULT_BOUNDS:
        lo, hi = DEFAULT_BOUNDS[name]
    else:
        lo, hi = start / DEFAULT_FACTOR, start * DEFAULT_FACTOR
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise InputError(f"bounds of {name!r} must be finite with lo < hi, got ({lo!r}, {hi!r})")
    if not lo < start < hi:
        raise InputError(f"start value of {name!r} = {start!r} is outside its bounds "
                         f"({lo!r}, {hi!r})")
    return lo, hi


def _to_value(u, lo, hi):
    """Internal (unbounded) -> value: log-uniform between lo > 0 and hi, linear if lo <= 0."""
    s = jax.nn.sigmoid(u)
    if lo > 0:
        return jnp.exp(math.log(lo) + s * (math.log(hi) - math.log(lo)))
    return lo + s * (hi - lo)


def _to_internal(v, lo, hi):
    s = (math.log(v / lo) / math.log(hi / lo)) if lo > 0 else (v - lo) / (hi - lo)
    return math.log(s / (1.0 - s))


# ----------------------------------------------------------------------------- calibrate
class CalibrationResult(NamedTuple):
    """values   fitted parameters (name -> float), the best iterate
    loss       its loss
    start      the starting values
    history    dict: ``loss`` (S,), ``<name>`` (S,) values per iteration
    steps      optimiser steps taken; ``converged``: stopped by ``tol``/``patience``
    params     ``Params`` with the fitted values
    curves     dict: ``target_strain``, ``target_stress`` and the simulated
               ``strain``, ``start_stress``, ``fit_stress`` (members x records for
               an ensemble)
    wall_time  seconds"""

    values: dict
    loss: float
    start: dict
    history: dict
    steps: int
    converged: bool
    params: Params
    curves: dict
    wall_time: float


def calibration_loss(params: Params, setup, target: Target, weights=LossWeights()):
    """Loss of ``params`` on a lab-test :class:`jdem.lab.Setup` (mean over an
    ensemble's members) and the history of the pure run."""
    hist = lab.curve(setup, params).history
    e, s = hist["axial_strain"], hist["axial_stress"]
    if setup.plan.batched:
        losses = jax.vmap(lambda a, b: curve_loss(a, b, target, weights))(e, s)
        return jnp.mean(losses), hist
    return curve_loss(e, s, target, weights), hist


def calibrate(setup, target, start: dict, *, params=None, bounds=None, steps=100,
              learning_rate=0.1, weights=LossWeights(), tol=1e-5, patience=20,
              min_improvement=1e-3, progress=True, out=None, require_quasi_static=True):
    """Fit the named parameters of ``start`` to ``target`` by gradient descent.

    setup          a :class:`jdem.lab.Setup` (e.g. ``jdem.lab.UCS.setup(specimen,
                   params, stiffness_margin=2)``: one packing or an ensemble)
    params         default ``setup.params``
    target         anything :func:`load_target` takes
    start          name -> starting value (names from ``PARAMETERS``)
    bounds         name -> (lo, hi); default: ``DEFAULT_BOUNDS`` or start / 5 .. start x 5.
                   The optimiser works on u with value = lo (hi/lo)^sigmoid(u)
                   (log space; linear when lo <= 0), so bounds always hold
    steps          at most this many Adam steps (optax); the step size in u decays
                   from ``learning_rate`` to 5 % of it (cosine) over ``steps``
    tol            stop when the loss falls below it
    patience       stop when the best loss has not improved by a fraction
                   ``min_improvement`` for this many steps
    out            optional HDF5 path for the result (:func:`save_calibration`)
    require_quasi_static  run :func:`jdem.lab.certify` at the start values first and
                   raise ``InputError`` if the set-up is not quasi-static (the fit
                   would describe the loading rate, not the rock)
    """
    import optax

    params = setup.params if params is None else params
    target = target if isinstance(target, Target) else load_target(target)
    check_names(start)
    names = list(start)
    lims = {n: _bounds_for(n, float(start[n]), bounds) for n in names}
    u = {n: jnp.asarray(_to_internal(float(start[n]), *lims[n])) for n in names}
    if require_quasi_static:
        cert = lab.certify(setup, material(params, start))
        if not cert.quasi_static:
            raise InputError(f"the calibration set-up is not quasi-static: {cert}; lower "
                             f"loading_rate, or pass require_quasi_static=False")
    curve0, setup = lab.checked_curve(setup, material(params, start))

    def loss_fn(u):
        vals = {n: _to_value(u[n], *lims[n]) for n in names}
        loss, out = calibration_loss(material(params, vals), setup, target, weights)
        return loss, (out["overflowed"], out["first_bad_step"])

    # Adam with a cosine decay to 5 % of the rate: large early steps, then settling
    opt = optax.adam(optax.cosine_decay_schedule(learning_rate, max(int(steps), 1), alpha=0.05))
    state = opt.init(u)
    grad_fn = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))
    hist = {"loss": []}
    hist.update({n: [] for n in names})
    best = (np.inf, dict(start))
    since_best = 0
    converged = False
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, desc="calibrate", unit="it", leave=False)
    t0 = time.time()
    k = 0
    try:
        while k < steps:
            (loss, (over, bad)), g = grad_fn(u)
            if bool(over):
                setup = lab.grow(setup)
                grad_fn = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))
                continue
            if int(bad) >= 0 or not np.isfinite(float(loss)):
                raise RuntimeError(f"calibration step {k}: the test diverged at step {int(bad)} "
                                   f"(loss {float(loss)!r}); narrow the bounds")
            vals = {n: float(_to_value(u[n], *lims[n])) for n in names}
            loss = float(loss)
            hist["loss"].append(loss)
            for n in names:
                hist[n].append(vals[n])
            if loss < best[0] * (1.0 - min_improvement):
                since_best = 0
            else:
                since_best += 1
            if loss < best[0]:
                best = (loss, vals)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.3g}")
            k += 1
            if loss < tol or since_best >= patience:
                converged = True
                break
            updates, state = opt.update(g, state, u)
            u = optax.apply_updates(u, updates)
    finally:
        if bar is not None:
            bar.close()
    fitted = material(params, best[1])
    curve1, setup = lab.checked_curve(setup, fitted)
    curves = dict(target_strain=target.strain, target_stress=target.stress,
                  strain=curve0["axial_strain"], start_stress=curve0["axial_stress"],
                  fit_stress=curve1["axial_stress"])
    res = CalibrationResult(values=best[1], loss=best[0], start=dict(start),
                            history={k_: np.asarray(v) for k_, v in hist.items()}, steps=k,
                            converged=converged, params=fitted, curves=curves,
                            wall_time=time.time() - t0)
    if out is not None:
        save_calibration(out, res)
    return res


def save_calibration(path, res: CalibrationResult):
    """Write a :class:`CalibrationResult` to HDF5 (``jdem.io.save_run``: params,
    history = loss/parameter history and curves, attrs = fitted and start values)."""
    history = {f"iter_{k}": v for k, v in res.history.items()}
    history.update(res.curves)
    attrs = {f"fit_{k}": v for k, v in res.values.items()}
    attrs.update({f"start_{k}": v for k, v in res.start.items()})
    attrs.update(loss=res.loss, steps=res.steps, converged=res.converged,
                 wall_time=res.wall_time)
    return io.save_run(path, params=res.params, history=history, attrs=attrs)


def load_calibration(path) -> dict:
    """``{values, start, loss, steps, converged, history, curves, params}`` from
    :func:`save_calibration`."""
    rd = io.load_run(path)
    a = rd.attrs or {}
    hist = rd.history or {}
    return dict(values={k[4:]: float(v) for k, v in a.items() if k.startswith("fit_")},
                start={k[6:]: float(v) for k, v in a.items() if k.startswith("start_")},
                loss=float(a["loss"]), steps=int(a["steps"]), converged=bool(a["converged"]),
                history={k[5:]: v for k, v in hist.items() if k.startswith("iter_")},
                curves={k: v for k, v in hist.items() if not k.startswith("iter_")},
                params=rd.params)


def plot_calibration(res: CalibrationResult, path=None, *, true_values=None):
    """Target, starting and fitted curves (left) and the loss history (right);
    written as PNG when ``path`` is given.  Returns the matplotlib figure."""
    import matplotlib

    if path is not None:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = res.curves
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4))
    ax.plot(c["target_strain"] * 100, c["target_stress"] / 1e6, "k-", lw=2.5, label="target")
    for key, style, label in (("start_stress", "C1--", "start"), ("fit_stress", "C0-", "fitted")):
        s = np.atleast_2d(c[key])
        e = np.atleast_2d(c["strain"])
        for m in range(s.shape[0]):
            ax.plot(e[m] * 100, s[m] / 1e6, style, lw=1.2, label=label if m == 0 else None)
    ax.set_xlabel("axial strain [%]")
    ax.set_ylabel("axial stress [MPa]")
    ax.grid(alpha=0.3)
    ax.legend()
    text = "\n".join(f"{k}: {res.start[k]:.4g} -> {v:.4g}"
                     + (f" (true {true_values[k]:.4g})" if true_values and k in true_values else "")
                     for k, v in res.values.items())
    ax.set_title("stress-strain", fontsize=10)
    ax.text(0.98, 0.02, text, transform=ax.transAxes, ha="right", va="bottom", fontsize=8,
            bbox=dict(fc="white", alpha=0.8))
    bx.semilogy(np.arange(len(res.history["loss"])), res.history["loss"], "C0-")
    bx.set_xlabel("optimiser step")
    bx.set_ylabel("loss")
    bx.grid(alpha=0.3, which="both")
    bx.set_title(f"{res.steps} steps, {res.wall_time:.0f} s", fontsize=10)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
        plt.close(fig)
    return fig


# ----------------------------------------------------------------------------- demo problem
#: true values of the demonstration problem (002 §2 material, kappa = 0.3 %)
DEMO_TRUE = dict(E=30e9, strength=3e6, kappa=3e-3)


def demo_problem(*, seed=2, size=(0.004, 0.008), radii=(0.2e-3, 0.35e-3), kappa_known=True,
                 loading_rate=None):
    """A small calibration problem with a known answer (used by ``jdem demo`` and
    notebooks/calibration.ipynb): a ~100-disc bonded specimen (4 mm x 8 mm) in
    the quasi-static UCS test, the target curve simulated with ``DEMO_TRUE`` and
    a start with E 40 % high and the strength 30 % low (and kappa 50 % high
    unless ``kappa_known``).  Returns ``(setup, params, target curve dict
    (strain, stress), true values, start values)``."""
    spec = generate("rectangle", size, *radii, seed=seed, target_coordination=4.5)
    setup = lab.UCS.setup(spec, rock_params(2, kappa=DEMO_TRUE["kappa"]), max_strain=1.2e-3,
                          stiffness_margin=2.0, loading_rate=loading_rate)
    params = setup.params
    hist, setup = lab.checked_curve(setup, material(params, DEMO_TRUE))
    curve = dict(strain=hist["axial_strain"], stress=hist["axial_stress"])
    start = dict(E=1.4 * DEMO_TRUE["E"], strength=0.7 * DEMO_TRUE["strength"])
    if not kappa_known:
        start["kappa"] = 1.5 * DEMO_TRUE["kappa"]
    true = {k: DEMO_TRUE[k] for k in start}
    return setup, params, curve, true, start
