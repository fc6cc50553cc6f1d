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
    packing_std_errors  name -> the part of it from the ensemble's packing-to-packing
                  spread (:func:`packing_covariance`; empty without an ensemble)
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
    packing_std_errors: dict = {}


class Uncertainty(NamedTuple):
    """What :func:`uncertainty` returns: name -> standard error (``std``, the unit
    of the value), name -> (lo, hi) 95 % interval, the (k, k) correlation matrix,
    name -> why the data do not determine it, and name -> the part of the
    standard error that comes from the packing-to-packing spread of the
    ensemble (``packing_std``; empty without an ensemble)."""

    std: dict
    intervals: dict
    correlation: np.ndarray
    poorly_determined: dict
    packing_std: dict


class MemberBlock(NamedTuple):
    """One ensemble term in the residual vector: its ``size`` residuals (the
    members' mean, :func:`jdem.calibrate.problem.term_residuals`) from ``start``;
    ``members`` (K, size) each member's residuals and ``ok`` (K,) the members
    that ran without diverging."""

    start: int
    size: int
    members: np.ndarray
    ok: np.ndarray


def packing_covariance(Jp, blocks, a_inv):
    """(k, k) covariance of the fitted parameters from the packing-to-packing
    spread of the ensemble(s), and its degrees of freedom (members - 1).

    The fit matches the ensemble's mean residuals to the target, so its
    sensitivity to the target y is d theta / d y = A^-1 J^T (J the Jacobian of
    the mean residuals, A = J^T J).  A target from a packing outside the ensemble
    differs from the ensemble's mean by a packing deviation, which the members
    sample: d_m = r_m - mean(r).  Member m therefore shifts the fit by
    A^-1 J^T d_m, and the covariance is (1 + 1/K) times the sample covariance of
    these shifts over the K members (the 1/K for the ensemble's own mean, itself
    a sample of K packings).  Blocks with the same member count are taken as
    built on the same packings, in order (member m of each is packing m: their
    shifts add); blocks with different counts as independent.  Diverged members
    (``ok`` False) are left out.  Returns ``(zeros, inf)`` without an ensemble
    of at least 2 good members."""
    k = Jp.shape[1]
    by_count = {}
    for b in blocks:
        by_count.setdefault(len(b.ok), []).append(b)
    cov = np.zeros((k, k))
    dof = np.inf
    for count, group in by_count.items():
        good = np.ones(count, bool)
        for b in group:
            good &= np.asarray(b.ok, bool)
        kk = int(good.sum())
        if kk < 2:
            continue
        shifts = np.zeros((kk, k))
        for b in group:
            rm = np.asarray(b.members, np.float64)[good]
            dev = rm - rm.mean(axis=0)
            shifts += dev @ Jp[b.start:b.start + b.size] @ a_inv.T
        shifts -= shifts.mean(axis=0)
        cov += (1.0 + 1.0 / kk) * shifts.T @ shifts / (kk - 1)
        dof = min(dof, kk - 1)
    return cov, dof


def uncertainty(J, r, u, names, lims, n_fit, blocks=()) -> Uncertainty:
    """Standard errors, 95 % intervals and correlations at ``u``.

    J (n, k) = dr/du; converted to d r / d ln(value) (log-space parameters) or
    d r / d value (linear ones).  The covariance is the Gauss-Newton one,
    s^2 (J^T J)^-1 with s^2 = RSS / (n - k) (n the residuals that carry data),
    plus, for ensemble terms (``blocks``, :class:`MemberBlock`), the covariance
    from the packing-to-packing spread (:func:`packing_covariance`): a fit to one
    specimen's curve moves by that much with the specimen.  The sum is
    conservative, since the misfit at the optimum already holds some of the
    spread.  The curve points are correlated, so the Gauss-Newton part alone is
    a lower bound; the packing part is estimated from K members only, so the
    interval takes Student's t quantile with the Welch-Satterthwaite degrees of
    freedom of the two parts (3.18 instead of 1.96 when 4 members dominate)."""
    from scipy import stats

    k = len(names)
    scale = np.array([dscale_du(float(u[i]), *lims[n]) for i, n in enumerate(names)])
    Jp = np.asarray(J, np.float64) / scale[None, :]
    rss = float(np.sum(np.asarray(r, np.float64) ** 2))
    dof_fit = max(n_fit - k, 1)
    s2 = rss / dof_fit
    jtj = Jp.T @ Jp
    why = {}
    norms = np.sqrt(np.diag(jtj))
    for i, n in enumerate(names):
        if not norms[i] > 0:
            why[n] = "the residuals do not depend on it"
    try:
        a_inv = np.linalg.pinv(jtj, rcond=1e-12)
    except np.linalg.LinAlgError:
        a_inv = np.full((k, k), np.nan)
    cov_fit = s2 * a_inv
    cov_pack, dof_pack = packing_covariance(Jp, blocks, a_inv)
    cov = cov_fit + cov_pack
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    sd_pack = np.sqrt(np.clip(np.diag(cov_pack), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    values = {n: float(to_value(float(u[i]), *lims[n])) for i, n in enumerate(names)}
    std, intervals, packing = {}, {}, {}
    for i, n in enumerate(names):
        v1, v2 = max(float(cov_fit[i, i]), 0.0), float(sd_pack[i]) ** 2
        den = v1 ** 2 / dof_fit + (v2 ** 2 / dof_pack if v2 > 0 else 0.0)
        dof = (v1 + v2) ** 2 / den if den > 0 else float(dof_fit)   # Welch-Satterthwaite
        q = float(stats.t.ppf(0.975, dof)) if np.isfinite(dof) and dof > 0 else 1.96
        v = values[n]
        if log_space(lims[n][0]):
            std[n] = v * float(sd[i])
            intervals[n] = (v * math.exp(-q * sd[i]), v * math.exp(q * sd[i]))
            if blocks:
                packing[n] = v * float(sd_pack[i])
            if n not in why and sd[i] > 0.25:
                why[n] = f"relative standard error {100 * sd[i]:.0f} % (> 25 %)"
        else:
            std[n] = float(sd[i])
            intervals[n] = (v - q * sd[i], v + q * sd[i])
            if blocks:
                packing[n] = float(sd_pack[i])
            if n not in why and q * sd[i] > 0.5 * (lims[n][1] - lims[n][0]):
                why[n] = "its 95 % interval spans more than half its bounds"
    for i in range(k):
        for j in range(i + 1, k):
            if abs(corr[i, j]) > 0.98:
                for n in (names[i], names[j]):
                    why.setdefault(n, f"correlation {corr[i, j]:+.3f} between {names[i]} "
                                      f"and {names[j]}: only a combination is determined")
    return Uncertainty(std, intervals, corr, why, packing)


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
    attribute groups ``fit``, ``start``, ``stderr``, ``stderr_packing``, ``ci95`` (lo, hi) and
    ``undetermined`` (name -> why), and root attributes ``loss``, ``steps``,
    ``converged``, ``stop``, ``wall_time``, ``method``, ``jacobian``, ``names``,
    ``diverged``, ``warnings``."""
    history = {"iterations": dict(res.history), "curves": dict(res.curves)}
    if np.size(res.correlation):
        history["correlation"] = np.asarray(res.correlation)
    attrs = {"fit": dict(res.values), "start": dict(res.start),
             "stderr": dict(res.std_errors),
             "stderr_packing": dict(res.packing_std_errors),
             "ci95": {k: list(v) for k, v in res.intervals.items()},
             "undetermined": dict(res.poorly_determined)}
    attrs.update(loss=res.loss, steps=res.steps, converged=res.converged, stop=res.stop,
                 wall_time=res.wall_time, method=res.method, jacobian=res.jacobian,
                 names=list(res.values), diverged=[list(d) for d in res.diverged],
                 warnings=list(res.warnings))
    return io.save_run(path, params=res.params, history=history, attrs=attrs)


def load_calibration(path) -> dict:
    """``{values, start, loss, steps, converged, stop, history, curves, params, method,
    jacobian, std_errors, packing_std_errors, intervals, correlation, poorly_determined,
    warnings}`` from
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
                packing_std_errors={k: float(v)
                                    for k, v in (a.get("stderr_packing") or {}).items()},
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
        pack = res.packing_std_errors.get(n)
        spread = "" if pack is None else f", packings {pack:.2g}"
        line = (f"  {n:9s} {v:.5g} +- {se:.2g}{spread}  (95 %: {lo:.4g} .. {hi:.4g}; "
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
