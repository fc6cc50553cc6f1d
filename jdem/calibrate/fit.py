""":func:`calibrate`: the fit of named micro-parameters to one or several
targets (see :mod:`jdem.calibrate`)."""
from __future__ import annotations

import pathlib
import time
import warnings

import jax.numpy as jnp
import numpy as np

from jdem import lab
from jdem.calibrate.problem import make_terms, member_blocks, n_data, peakless, residual_problem
from jdem.calibrate.result import (CalibrationResult, fitted_curves, load_calibration,
                                   merge_curves, partial_result, save_calibration, uncertainty)
from jdem.calibrate.solvers import FD_STEP, adam, jacobian_at, least_squares
from jdem.calibrate.transform import bounds_for, to_internal, to_value
from jdem.materials import check_names, material
from jdem.targets import LossWeights
from jdem.validate import InputError

#: forward-mode Jacobians up to this many fitted parameters, reverse mode beyond
FORWARD_MODE_MAX = 8
METHODS = ("lm", "gauss_newton", "adam")
JACOBIANS = ("forward", "reverse", "finite-difference")


def check_time_step(params, terms):
    """Raise :class:`InputError` when ``params`` carries another time step than a
    set-up's own: the set-up chose its step for stability at its stiffness
    margin, and a run with another (``rock_params``' placeholder 1e-8 s, say) can
    stay finite while its forward-mode derivatives grow without bound."""
    dt = np.asarray(params.dt, np.float64)
    for i, t in enumerate(terms):
        own = np.asarray(t.setup.params.dt, np.float64)
        if dt.shape not in ((), own.shape) or not np.allclose(dt, own, rtol=1e-6, atol=0.0):
            raise InputError(
                f"params.dt = {dt.tolist()!r} s, but set-up {i} ({t.setup.plan.test.name}) "
                f"runs at {own.tolist()!r} s, the step it chose for stability: pass its own "
                f"params (setup.params) or leave params out")


def calibrate(setup, target, start: dict, *, params=None, bounds=None, method="lm",
              jacobian="auto", steps=30, rtol=1e-4, atol=1e-8, learning_rate=0.1,
              weights=LossWeights(), tol=1e-8, patience=None, min_improvement=1e-3,
              progress=True, out=None, checkpoint=None, resume=None,
              require_quasi_static=True, extrapolate_rate=False,
              rate_factor=2.0, fd_step=FD_STEP) -> CalibrationResult:
    """Fit the named parameters of ``start`` to ``target``.

    setup          a :class:`jdem.lab.Setup` (e.g. ``jdem.lab.UCS.setup(specimen,
                   params)``: one packing or an ensemble), or a list of them
    target         anything :func:`jdem.targets.load_target` takes (a curve), a
                   :class:`~jdem.targets.Scalar` or tuple of them; a list, one per set-up
    start          name -> starting value (names from ``PARAMETERS``)
    params         the other parameters; default each set-up's own ``params``
                   (another time step than the set-up's is refused: :func:`check_time_step`)
    bounds         name -> (lo, hi); default ``DEFAULT_BOUNDS`` or start / 5 .. start x 5
    method         "lm" (Levenberg-Marquardt), "gauss_newton" or "adam"
    jacobian       "forward", "reverse" or "auto" (forward for <= 8 parameters), or
                   "finite-difference": central differences over ``fd_step`` in the
                   internal coordinate (2k + 1 runs per iteration), for a curve past the
                   peak of a large specimen, where the exact derivative through the
                   break cascade is too large to steer by
                   (:func:`jdem.calibrate.solvers.finite_difference_jacobian`)
    steps          at most this many iterations
    rtol, atol     the least-squares solvers' tolerances (on u and on the loss)
    learning_rate  Adam's step in u (cosine decay to 5 % over ``steps``)
    tol, patience  stop when the loss falls below ``tol`` (``stop`` "converged"),
                   or has not improved by a fraction ``min_improvement`` for
                   ``patience`` accepted iterations (default 3 for the least-squares
                   solvers, 20 for Adam; ``stop`` "stalled", ``converged`` False)
    out            HDF5 path for the result (:func:`save_calibration`)
    checkpoint     HDF5 path written after every iteration (default: next to
                   ``out``); ``resume``: such a file to continue from
    require_quasi_static  certify each set-up at the start values first
                   (:func:`jdem.lab.certify`) and refuse one that is not
    extrapolate_rate  fit the quasi-static estimate instead of the run at the
                   set-up's rate: every set-up also runs ``rate_factor`` times
                   slower and each residual is extrapolated to rate zero
                   (:func:`jdem.lab.extrapolated_history`).  Costs 1 +
                   ``rate_factor`` times the run per iteration
                   (experiments/quasi_static_calibration.py measures what it buys)
    """
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}, got {method!r}")
    if patience is None:
        patience = 20 if method == "adam" else 3
    check_names(start)
    if jacobian not in JACOBIANS + ("auto",):
        raise InputError(f"jacobian must be one of {JACOBIANS} or 'auto', got {jacobian!r}")
    if not (isinstance(fd_step, (int, float)) and 0 < fd_step < 1):
        raise InputError(f"fd_step must be a number in (0, 1) (internal coordinate), "
                         f"got {fd_step!r}")
    if not (isinstance(rate_factor, (int, float)) and rate_factor > 1):
        raise InputError(f"rate_factor must be a number above 1, got {rate_factor!r}")
    terms = make_terms(setup, target, weights, extrapolate_rate=extrapolate_rate,
                       factor=rate_factor)
    names = list(start)
    k = len(names)
    if jacobian == "auto":
        jacobian = "forward" if k <= FORWARD_MODE_MAX else "reverse"
    lims = {n: bounds_for(n, float(start[n]), bounds) for n in names}
    plist = [t.setup.params if params is None else params for t in terms]
    if params is not None:
        check_time_step(params, terms)
    history = {"loss": [], **{n: [] for n in names}}
    done = 0
    values0 = {n: float(start[n]) for n in names}
    if resume is not None:
        back = load_calibration(resume)
        if sorted(back["values"]) != sorted(names):
            raise InputError(f"resume file {resume} fits {sorted(back['values'])}, not "
                             f"{sorted(names)}")
        history = {kk: list(v) for kk, v in back["history"].items()}
        done = back["steps"]
        values0 = {n: back["values"][n] for n in names}
    if require_quasi_static:
        for i, t in enumerate(terms):
            cert = lab.certify(t.setup, material(plist[i], start))
            if not cert.quasi_static:
                raise InputError(f"set-up {i} ({t.setup.plan.test.name}) is not quasi-static: "
                                 f"{cert}; lower loading_rate, or pass "
                                 f"require_quasi_static=False")
    if checkpoint is None and out is not None:
        checkpoint = pathlib.Path(out).with_suffix(".checkpoint.h5")
    t0 = time.time()
    curves0 = fitted_curves(terms, plist, {n: float(start[n]) for n in names})
    terms = [c[1] for c in curves0]
    u = jnp.asarray([to_internal(values0[n], *lims[n]) for n in names])
    n_points = sum(n_data(t) for t in terms)

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, initial=min(done, steps), unit="it",
                   desc=f"calibrate ({method}, {jacobian} Jacobian)", leave=False)
    diverged, stop = [], "steps"
    best = (min(history["loss"]) if history["loss"] else np.inf, dict(values0))

    def record(u_now, loss, ok):
        nonlocal best
        vals = {n: float(to_value(float(u_now[i]), *lims[n])) for i, n in enumerate(names)}
        history["loss"].append(float(loss))
        for n in names:
            history[n].append(vals[n])
        for ti, flags in enumerate(ok):
            for m in np.flatnonzero(~np.asarray(flags)):
                diverged.append((len(history["loss"]) - 1, ti, int(m)))
        if float(loss) < best[0]:
            best = (float(loss), vals)
        if checkpoint is not None:
            save_calibration(checkpoint, partial_result(best, start, history, terms, plist,
                                                        method, jacobian, time.time() - t0))
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{float(loss):.3g}")

    try:
        stepper = adam if method == "adam" else least_squares
        stop, why_stopped, terms = stepper(
            terms, plist, u, names, lims, record, history, steps - done, method=method,
            jacobian=jacobian, rtol=rtol, atol=atol, learning_rate=learning_rate, tol=tol,
            patience=patience, min_improvement=min_improvement, fd_step=fd_step)
    finally:
        if bar is not None:
            bar.close()
    # uncertainty and curves at the best point
    ub = jnp.asarray([to_internal(best[1][n], *lims[n]) for n in names])
    fn, args = residual_problem(names, lims, terms, plist)
    r, J, aux = jacobian_at(fn, ub, args, jacobian, step=fd_step, with_aux=True)
    blocks = member_blocks(terms, aux["ok"], aux["members"])
    unc = uncertainty(J, r, np.asarray(ub), names, lims, n_points, blocks)
    curves1 = fitted_curves(terms, plist, best[1])
    doubts = peakless(terms, [h for h, _ in curves1])
    if stop == "stalled":
        doubts = [f"the fit stalled after {len(history['loss'])} iterations (loss "
                  f"{best[0]:.3g}): {why_stopped}"] + doubts
    for msg in doubts:
        warnings.warn(msg, stacklevel=2)
    curves = merge_curves(terms, curves0, curves1)
    fitted = material(plist[0], best[1])
    res = CalibrationResult(values=best[1], loss=best[0], start=dict(start),
                            history={kk: np.asarray(v) for kk, v in history.items()},
                            steps=len(history["loss"]), converged=stop == "converged",
                            stop=stop, params=fitted,
                            curves=curves, wall_time=time.time() - t0, method=method,
                            jacobian=jacobian, std_errors=unc.std,
                            packing_std_errors=unc.packing_std, intervals=unc.intervals,
                            correlation=unc.correlation,
                            poorly_determined=unc.poorly_determined, diverged=diverged,
                            warnings=doubts)
    if out is not None:
        save_calibration(out, res)
    return res
