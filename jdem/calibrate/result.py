"""What a calibration returns and writes: :class:`CalibrationResult`, the
Gauss-Newton uncertainty at the optimum, the start and fitted curves, the HDF5
file (:func:`save_calibration`, :func:`load_calibration`) and a text report."""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from jdem import io, lab
from jdem.calibrate.transform import dscale_du, log_space, to_value
from jdem.materials import material
from jdem.state import Params
from jdem.targets import Target

class CalibrationResult(NamedTuple):
    """values        fitted parameters (name -> float), the best iterate
    loss          its sum of squared residuals
    start         the starting values
    history       ``loss`` (S,) and ``<name>`` (S,) per iteration (the accepted point)
    steps         iterations; ``converged``: the solver's tolerance (or ``tol``) was met
    stop          why it stopped: "converged", "stalled" (no progress: ``converged``
                  False, and a warning) or "steps" (the iteration budget spent)
    params        ``Params`` with the fitted values
    curves        ``target_strain``, ``target_stress``, ``strain``, ``start_stress``,
                  ``fit_stress`` of the first curve target (members x records for
                  an ensemble); further terms prefixed ``term<k>_``
    wall_time     seconds
    method, jacobian   the solver and the Jacobian mode ("forward" / "reverse")
    std_errors    name -> standard error (same unit as the value)
    intervals     name -> (lo, hi) 95 % interval
    correlation   (k, k) correlation matrix of the fitted parameters (names order)
    poorly_determined  name -> why the data do not determine it
    diverged      list of (iteration, term, member) of ensemble members that diverged
    warnings      what makes the fit doubtful, e.g. a test whose fitted curve has no
                  peak before its end (:func:`peakless`)"""

    values: dict
    loss: float
    start: dict
    history: dict
    steps: int
    converged: bool
    params: Params
    curves: dict
    wall_time: float
    method: str = "lm"
    jacobian: str = "forward"
    std_errors: dict = {}
    intervals: dict = {}
    correlation: np.ndarray = np.zeros((0, 0))
    poorly_determined: dict = {}
    diverged: list = []
    warnings: list = []
    stop: str = ""


def uncertainty(J, r, u, names, lims, n_fit):
    """Gauss-Newton standard errors, 95 % intervals and correlations at ``u``.

    J (n, k) = dr/du; converted to d r / d ln(value) (log-space parameters) or
    d r / d value (linear ones).  Covariance s^2 (J^T J)^-1 with s^2 = RSS / (n - k),
    n the residuals that carry data.  The curve points are correlated, so these
    intervals are a lower bound on the true uncertainty."""
    k = len(names)
    scale = np.array([dscale_du(float(u[i]), *lims[n]) for i, n in enumerate(names)])
    Jp = np.asarray(J) / scale[None, :]
    rss = float(np.sum(np.asarray(r) ** 2))
    dof = max(n_fit - k, 1)
    s2 = rss / dof
    jtj = Jp.T @ Jp
    why = {}
    norms = np.sqrt(np.diag(jtj))
    for i, n in enumerate(names):
        if not norms[i] > 0:
            why[n] = "the residuals do not depend on it"
    try:
        cov = s2 * np.linalg.pinv(jtj, rcond=1e-12)
    except np.linalg.LinAlgError:
        cov = np.full((k, k), np.nan)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    values = {n: float(to_value(float(u[i]), *lims[n])) for i, n in enumerate(names)}
    std, intervals = {}, {}
    for i, n in enumerate(names):
        v = values[n]
        if log_space(lims[n][0]):
            std[n] = v * float(sd[i])
            intervals[n] = (v * math.exp(-1.96 * sd[i]), v * math.exp(1.96 * sd[i]))
            if n not in why and sd[i] > 0.25:
                why[n] = f"relative standard error {100 * sd[i]:.0f} % (> 25 %)"
        else:
            std[n] = float(sd[i])
            intervals[n] = (v - 1.96 * sd[i], v + 1.96 * sd[i])
            if n not in why and 1.96 * sd[i] > 0.5 * (lims[n][1] - lims[n][0]):
                why[n] = "its 95 % interval spans more than half its bounds"
    for i in range(k):
        for j in range(i + 1, k):
            if abs(corr[i, j]) > 0.98:
                for n in (names[i], names[j]):
                    why.setdefault(n, f"correlation {corr[i, j]:+.3f} between {names[i]} "
                                      f"and {names[j]}: only a combination is determined")
    return std, intervals, corr, why


# ----------------------------------------------------------------------------- curves, files
def fitted_curves(terms, plist, values):
    """[(history as NumPy, the term with its set-ups grown as needed)] per term
    at ``values``: the run at the set-up's rate, or for a term with a slowed
    set-up the rate-extrapolated curve (:func:`jdem.lab.extrapolated_history`)."""
    out = []
    for t, p in zip(terms, plist):
        prm = material(p, values)
        hist, setup = lab.checked_curve(t.setup, prm)
        if t.slow is not None:
            hist_slow, slow = lab.checked_curve(t.slow, prm)
            hist = {k: np.asarray(v) for k, v in
                    lab.extrapolated_history(hist, hist_slow, t.factor).items()}
            t = t._replace(slow=slow)
        out.append((hist, t._replace(setup=setup)))
    return out


def merge_curves(terms, start, fit):
    """The ``curves`` of a :class:`CalibrationResult` from the start and fitted
    histories of every term (later terms prefixed ``term<k>_``)."""
    out = {}
    for k, (t, (h0, _), (h1, _)) in enumerate(zip(terms, start, fit)):
        pre = "" if k == 0 else f"term{k}_"
        if isinstance(t.target, Target):
            out[pre + "target_strain"] = t.target.strain
            out[pre + "target_stress"] = t.target.stress
        out[pre + "strain"] = h0["axial_strain"]
        out[pre + "start_stress"] = h0["axial_stress"]
        out[pre + "fit_stress"] = h1["axial_stress"]
    return out


def partial_result(best, start, history, terms, plist, method, jacobian, wall):
    """The :class:`CalibrationResult` of a fit in progress (the checkpoint):
    the best point so far, no curves and no uncertainty."""
    return CalibrationResult(values=best[1], loss=best[0], start=dict(start),
                             history={k: np.asarray(v) for k, v in history.items()},
                             steps=len(history["loss"]), converged=False,
                             params=material(plist[0], best[1]), curves={}, wall_time=wall,
                             method=method, jacobian=jacobian)


def save_calibration(path, res: CalibrationResult):
    """Write a :class:`CalibrationResult` to HDF5 (:func:`jdem.io.save_run`):
    the fitted ``params``; history groups ``iterations`` (``loss`` and each
    parameter per iteration) and ``curves``, the dataset ``correlation``;
    attribute groups ``fit``, ``start``, ``stderr``, ``ci95`` (lo, hi) and
    ``undetermined`` (name -> why), and root attributes ``loss``, ``steps``,
    ``converged``, ``stop``, ``wall_time``, ``method``, ``jacobian``, ``names``,
    ``diverged``, ``warnings``."""
    history = {"iterations": dict(res.history), "curves": dict(res.curves)}
    if np.size(res.correlation):
        history["correlation"] = np.asarray(res.correlation)
    attrs = {"fit": dict(res.values), "start": dict(res.start),
             "stderr": dict(res.std_errors),
             "ci95": {k: list(v) for k, v in res.intervals.items()},
             "undetermined": dict(res.poorly_determined)}
    attrs.update(loss=res.loss, steps=res.steps, converged=res.converged, stop=res.stop,
                 wall_time=res.wall_time, method=res.method, jacobian=res.jacobian,
                 names=list(res.values), diverged=[list(d) for d in res.diverged],
                 warnings=list(res.warnings))
    return io.save_run(path, params=res.params, history=history, attrs=attrs)


def load_calibration(path) -> dict:
    """``{values, start, loss, steps, converged, stop, history, curves, params, method,
    jacobian, std_errors, intervals, correlation, poorly_determined, warnings}`` from
    :func:`save_calibration` (or a checkpoint); files of format version 1 (flat
    names with ``fit_`` / ``iter_`` ... prefixes) load too."""
    rd = io.load_run(path)
    a = dict(rd.attrs or {})
    hist = dict(rd.history or {})
    if not isinstance(a.get("fit"), dict):      # format version 1
        for group, pre in (("fit", "fit_"), ("start", "start_"), ("stderr", "stderr_"),
                           ("ci95", "ci95_"), ("undetermined", "undetermined_")):
            a[group] = {k[len(pre):]: v for k, v in a.items()
                        if isinstance(k, str) and k.startswith(pre)}
        hist = dict(iterations={k[5:]: v for k, v in hist.items() if k.startswith("iter_")},
                    curves={k: v for k, v in hist.items()
                            if not k.startswith("iter_") and k != "correlation"},
                    **({"correlation": hist["correlation"]} if "correlation" in hist else {}))
    names = list(a.get("names", list(a["fit"])))
    return dict(values={n: float(a["fit"][n]) for n in names},
                start={k: float(v) for k, v in a["start"].items()},
                loss=float(a["loss"]), steps=int(a["steps"]), converged=bool(a["converged"]),
                stop=str(a.get("stop", "")),
                method=a.get("method"), jacobian=a.get("jacobian"),
                warnings=list(a.get("warnings", [])),
                std_errors={k: float(v) for k, v in a["stderr"].items()},
                intervals={k: tuple(v) for k, v in a["ci95"].items()},
                poorly_determined=dict(a["undetermined"]),
                correlation=np.asarray(hist.get("correlation", np.zeros((0, 0)))),
                history={k: np.asarray(v) for k, v in hist["iterations"].items()},
                curves={k: np.asarray(v) for k, v in hist["curves"].items()},
                params=rd.params)


def report(res: CalibrationResult, true_values=None) -> str:
    """A few lines: each fitted value with its standard error and 95 % interval,
    and the parameters the data leave undetermined."""
    lines = [f"{res.method}, {res.jacobian}-mode Jacobian: loss {res.loss:.3g} after "
             f"{res.steps} iterations ({res.wall_time:.0f} s)"
             + (f", {res.stop}" if res.stop else "")]
    for n, v in res.values.items():
        se = res.std_errors.get(n, float("nan"))
        lo, hi = res.intervals.get(n, (float("nan"), float("nan")))
        line = (f"  {n:9s} {v:.5g} +- {se:.2g}  (95 %: {lo:.4g} .. {hi:.4g}; "
                f"start {res.start[n]:.4g})")
        if true_values and n in true_values:
            line += f"  true {true_values[n]:.4g} ({100 * (v / true_values[n] - 1):+.2f} %)"
        lines.append(line)
    for n, why in res.poorly_determined.items():
        lines.append(f"  not determined: {n}: {why}")
    for msg in res.warnings:
        lines.append(f"  warning: {msg}")
    if res.diverged:
        lines.append(f"  {len(res.diverged)} ensemble member run(s) diverged (iteration, "
                     f"term, member): {res.diverged[:5]}")
    return "\n".join(lines)
