"""Key figures of a lab-test history, and how far a curve is from quasi-static.

Citations ("000 §2.3") refer to the documents listed in REFERENCES.md.

* :func:`fit_modulus` -- the one secant-modulus fit: least-squares slope of
  stress against strain over the pre-peak records with 10 %..40 % of the peak.
* :func:`peak_summary` -- peak stress, critical strain, modulus, Poisson ratio,
  fracture degree, and the in-run quasi-static indicator.
* :func:`curve_stages` -- the four stages of a compression curve (002 Fig 10)
  and the broken bonds by mode at the peak and at the end.
* The quasi-static certificate (000 §2.3, §3.2: dynamic relaxation seeks the
  static solution; the curve should not depend on how fast it was reached):
  :func:`kinetic_ratio` is the cheap in-run indicator (kinetic over strain
  energy on the loading branch up to the peak), :func:`certify` the decisive
  check (the change of peak stress and modulus when the loading rate is halved),
  :func:`rate_extrapolated` the quasi-static limit estimated from the two runs.
"""
from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np

from jdem.batch import member

MODULUS_WINDOW = (0.1, 0.4)   #: fraction of the peak stress between which the modulus is fitted
QUASI_STATIC_TOLERANCE = 0.02  #: peak and modulus may change this much at half the rate
#: in-run indicator above which a run is reported as dynamic (see :func:`kinetic_ratio`)
KINETIC_RATIO_WARNING = 1e-2


def fit_modulus(strain, stress, *, window=MODULUS_WINDOW, min_points=3):
    """Least-squares slope [Pa] of ``stress`` vs ``strain`` (R,) over the records
    up to the peak whose stress lies in ``window`` x the peak (NaN if fewer than
    ``min_points`` records do).  Returns ``(modulus, (strain_lo, strain_hi))``."""
    strain = np.asarray(strain, np.float64)
    stress = np.asarray(stress, np.float64)
    k = int(np.argmax(stress))
    peak = float(stress[k])
    s, e = stress[:k + 1], strain[:k + 1]
    sel = (s >= window[0] * peak) & (s <= window[1] * peak)
    if sel.sum() < min_points:
        return float("nan"), (float("nan"), float("nan"))
    return float(np.polyfit(e[sel], s[sel], 1)[0]), (float(e[sel].min()), float(e[sel].max()))


def kinetic_ratio(history) -> float:
    """The in-run quasi-static indicator of one (unbatched) history: the largest
    kinetic / strain energy ratio (``kinetic_ratio`` records) on the loading
    branch, from 10 % of the peak stress up to the peak."""
    stress = np.asarray(history["axial_stress"], np.float64)
    ratio = np.asarray(history["kinetic_ratio"], np.float64)
    if not np.any(np.isfinite(stress)):
        return float("nan")
    k = int(np.nanargmax(stress))
    sel = stress[:k + 1] >= 0.1 * stress[k]
    return float(np.max(ratio[:k + 1][sel])) if sel.any() else float("nan")


def peak_summary(history: dict, *, window=MODULUS_WINDOW) -> dict:
    """Key figures of a compression (or tension) curve; a batched history gives
    arrays over its members.

    peak_stress              largest axial stress [Pa]
    critical_strain          axial strain at the peak (002 §2.2)
    youngs_modulus           :func:`fit_modulus` [Pa]
    poisson_ratio            -d(lateral strain)/d(axial strain) over the same records
    fracture_degree_at_peak, fracture_degree_end
    final_stress             axial stress of the last record
    peak_index, peak_step
    kinetic_ratio            :func:`kinetic_ratio`
    tensile_strength         Brazilian histories: 2 P_peak / (pi D t) [Pa]
    """
    stress = np.asarray(history["axial_stress"])
    if stress.ndim == 2:
        rows = [peak_summary(member(history, b), window=window) for b in range(stress.shape[0])]
        return {k: np.asarray([r[k] for r in rows]) for k in rows[0]}
    strain = np.asarray(history["axial_strain"])
    finite = np.isfinite(stress)
    if not finite.all():
        # a member set aside by the run (its records NaN from its failure on):
        # the figures of the records before it
        n_ok = int(np.argmin(finite))     # the first NaN record
        if n_ok == 0:
            return _nan_summary(history)
        history = {key: (np.asarray(v)[:n_ok] if np.ndim(v) and np.shape(v)[0] == stress.size
                         else v) for key, v in history.items()}
        stress, strain = stress[:n_ok], strain[:n_ok]
    k = int(np.argmax(stress))
    peak = float(stress[k])
    modulus, _ = fit_modulus(strain, stress, window=window)
    nu = float("nan")
    if "lateral_strain" in history:
        lat = np.asarray(history["lateral_strain"])
        s = stress[:k + 1]
        sel = (s >= window[0] * peak) & (s <= window[1] * peak)
        if sel.sum() >= 3:
            nu = float(-np.polyfit(strain[:k + 1][sel], lat[:k + 1][sel], 1)[0])
    fd = np.asarray(history["fracture_degree"])
    out = dict(peak_stress=peak, critical_strain=float(strain[k]), youngs_modulus=modulus,
               poisson_ratio=nu, fracture_degree_at_peak=float(fd[k]),
               fracture_degree_end=float(fd[-1]), final_stress=float(stress[-1]),
               peak_index=k, peak_step=int(np.asarray(history["step"])[k]),
               kinetic_ratio=kinetic_ratio(history))
    if "tensile_strength_indirect" in history:
        out["tensile_strength"] = float(np.max(history["tensile_strength_indirect"]))
    return out


def curve_stages(history: dict, *, linear_deviation=0.01, residual_rate=0.1,
                 window=MODULUS_WINDOW) -> dict:
    """The four stages of a uniaxial compression curve (002 §2.2, Fig 10, 15):
    linear rise (elastic, no break), non-linear rise (damage spreading), non-linear
    descent (the main fracture running through) and the slowly varying residual
    stage (sliding on the fracture).  One (unbatched) history; a batched one
    gives arrays over its members.

    linear_end_stress, linear_end_strain  the first record past the modulus window
        whose stress falls ``linear_deviation`` (1 %) below the line fitted there
        (:func:`fit_modulus`, with its intercept)
    first_break_stress, first_break_strain  the first record with a broken bond
    peak_stress, peak_strain
    rise_ratio  the non-linear rise over the linear one, (eps_peak - eps_lin) /
        eps_lin (002: about 0.2 at kappa = 0, above 2 at kappa = 2.4 %)
    residual_strain, residual_stress  the first record after the peak from which
        the stress falls, averaged over the next 5 % of the strain range, slower
        than ``residual_rate`` (10 %) of the steepest such fall, and the mean
        stress from there on; NaN while the curve is still falling at its end
    descent_modulus  the steepest fall of the descent [Pa] (negative)
    n_tension_at_peak, n_shear_at_peak, n_tension_end, n_shear_end  broken bonds
        by mode (002 Fig 12), where the history records them
    """
    stress = np.asarray(history["axial_stress"], np.float64)
    if stress.ndim == 2:
        rows = [curve_stages(member(history, b), linear_deviation=linear_deviation,
                             residual_rate=residual_rate, window=window)
                for b in range(stress.shape[0])]
        return {k: np.asarray([r[k] for r in rows]) for k in rows[0]}
    strain = np.asarray(history["axial_strain"], np.float64)
    ok = np.isfinite(stress)
    stress, strain = stress[ok], strain[ok]
    nan = float("nan")
    k = int(np.argmax(stress))
    peak = float(stress[k])
    out = dict(linear_end_stress=nan, linear_end_strain=nan, first_break_stress=nan,
               first_break_strain=nan, peak_stress=peak, peak_strain=float(strain[k]),
               rise_ratio=nan, residual_strain=nan, residual_stress=nan, descent_modulus=nan)
    s, e = stress[:k + 1], strain[:k + 1]
    sel = (s >= window[0] * peak) & (s <= window[1] * peak)
    if sel.sum() >= 3:
        slope, intercept = np.polyfit(e[sel], s[sel], 1)
        line = slope * e + intercept
        past = np.flatnonzero((e > e[sel].max()) & (s < (1.0 - linear_deviation) * line))
        j = int(past[0]) if past.size else k
        out.update(linear_end_stress=float(s[j]), linear_end_strain=float(e[j]))
        if e[j] > 0:
            out["rise_ratio"] = float((e[k] - e[j]) / e[j])
    broken = np.asarray(history.get("n_broken", np.zeros(ok.size)))[ok]
    first = np.flatnonzero(broken > 0)
    if first.size:
        out.update(first_break_stress=float(stress[first[0]]),
                   first_break_strain=float(strain[first[0]]))
    # the descent: the fall of the stress over a strain window of 5 % of the range
    span = 0.05 * (strain[-1] - strain[0])
    after = np.arange(k, stress.size)
    if span > 0 and after.size > 2:
        ahead = np.searchsorted(strain, strain[after] + span)
        full = ahead < stress.size
        if full.any():
            a, b = after[full], ahead[full]
            rate = (stress[b] - stress[a]) / (strain[b] - strain[a])
            steepest = float(np.min(rate))
            out["descent_modulus"] = steepest
            if steepest < 0:
                m = int(np.argmin(rate))
                slow = np.flatnonzero((np.arange(rate.size) > m) & (rate > residual_rate
                                                                    * steepest))
                if slow.size:
                    r = int(a[slow[0]])
                    out.update(residual_strain=float(strain[r]),
                               residual_stress=float(np.mean(stress[r:])))
    for mode in ("tension", "shear"):
        key = f"n_{mode}"
        if key in history:
            n = np.asarray(history[key])[ok]
            out[f"{key}_at_peak"], out[f"{key}_end"] = int(n[k]), int(n[-1])
    return out


def _nan_summary(history):
    out = dict(peak_stress=np.nan, critical_strain=np.nan, youngs_modulus=np.nan,
               poisson_ratio=np.nan, fracture_degree_at_peak=np.nan, fracture_degree_end=np.nan,
               final_stress=np.nan, peak_index=-1, peak_step=-1, kinetic_ratio=np.nan)
    if "tensile_strength_indirect" in history:
        out["tensile_strength"] = np.nan
    return out


def rate_extrapolated(at_rate, slower, factor: float = 2.0):
    """The first-order (Richardson) extrapolation to zero loading rate of a figure
    measured at a loading rate (``at_rate``) and at ``1 / factor`` of it
    (``slower``): ``(factor * slower - at_rate) / (factor - 1)``.

    If the figure is S(v) = S_0 + a v + O(v^2), this is S_0 + O(v^2).  Works
    on floats and on NumPy or JAX arrays of one shape (e.g. the residuals of a
    curve against a target, which are affine in the simulated curve)."""
    return (factor * slower - at_rate) / (factor - 1.0)


def warn_if_dynamic(history: dict, name: str = "lab test"):
    """Warn when a history's in-run indicator exceeds ``KINETIC_RATIO_WARNING``."""
    stress = np.asarray(history["axial_stress"])
    members = [member(history, b) for b in range(stress.shape[0])] if stress.ndim == 2 \
        else [history]
    worst = np.nanmax([kinetic_ratio(h) for h in members] + [-np.inf])
    if np.isfinite(worst) and worst > KINETIC_RATIO_WARNING:
        warnings.warn(f"{name}: kinetic / strain energy reached {worst:.3g} before the peak "
                      f"(> {KINETIC_RATIO_WARNING:g}): the curve is probably not quasi-static; "
                      f"lower loading_rate and check with jdem.lab.certify", stacklevel=3)
    return worst


class Certificate(NamedTuple):
    """How far a test is from the quasi-static limit (:func:`certify`).

    peak_change, modulus_change   relative change of the peak stress and of the
                                  modulus (:func:`fit_modulus`) from the test's rate
                                  to ``1 / factor`` of it (one value, or per member)
    kinetic_ratio                 the in-run indicator at the test's rate
    quasi_static                  both changes below ``tolerance`` (every member)
    loading_rate                  platen speed / wave speed of the test
    summary, slow_summary         :func:`peak_summary` at the rate and slower
    factor                        the slower run's rate is ``1 / factor`` of the test's

    ``peak_error``: the first-order estimate of how far the peak at the test's
    rate lies from the quasi-static limit, ``peak_change * factor / (factor -
    1)`` (twice the change for ``factor`` 2); ``quasi_static_peak``: the
    extrapolated limit itself (:func:`rate_extrapolated`).
    """

    peak_change: object
    modulus_change: object
    kinetic_ratio: object
    quasi_static: bool
    tolerance: float
    loading_rate: float
    summary: dict
    slow_summary: dict
    factor: float = 2.0

    @property
    def peak_error(self):
        return np.asarray(self.peak_change) * self.factor / (self.factor - 1.0)

    @property
    def quasi_static_peak(self):
        return rate_extrapolated(np.asarray(self.summary["peak_stress"]),
                                 np.asarray(self.slow_summary["peak_stress"]), self.factor)

    def __str__(self):
        pc = np.max(np.abs(self.peak_change))
        mc = np.max(np.abs(self.modulus_change))
        verdict = "quasi-static" if self.quasi_static else "NOT quasi-static"
        return (f"{verdict} at loading rate {self.loading_rate:.3g} (platen / wave speed): "
                f"peak {100 * pc:.2f} %, modulus {100 * mc:.2f} % from the half-rate run "
                f"(tolerance {100 * self.tolerance:g} %; estimated "
                f"{100 * np.max(np.abs(self.peak_error)):.2f} % from the quasi-static "
                f"peak), kinetic / strain energy "
                f"{np.max(self.kinetic_ratio):.2g}")
