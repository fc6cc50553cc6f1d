"""Calibration targets and their residuals: what a fit compares the model with.

Two kinds of target, both in SI units:

* :class:`Target`: a laboratory stress-strain curve (strain [-], stress [Pa];
  :func:`load_target` reads arrays, a dict or a CSV file and rejects a column in
  percent or MPa).  Its residuals (:func:`curve_residuals`) are the simulated
  stress interpolated onto the target strains, minus the target, over the
  target's peak (or over its stated ``stress_sigma``), each weighted by
  1/sqrt(points) so the curve counts as one; then the relative peak-stress error
  and the relative error of the pre-peak slope.
* :class:`Scalar`: one measured figure with its uncertainty, e.g. the UCS of a
  series of specimens (``Scalar("peak_stress", 200e6, 10e6)``), a Brazilian
  strength (``Scalar("tensile_strength", 9e6, 1e6)``), Young's modulus or
  Poisson's ratio (``Scalar("poisson_ratio", 0.26, 0.02)``).  Its residual
  (:func:`scalar_residuals`) is (simulated - value) / sigma.

:func:`curve_loss` is the sum of squares of :func:`curve_residuals`: the mean
square misfit of the curve plus the two key-figure terms, one definition used by
the solvers and the reports.
"""
from __future__ import annotations

import csv
import pathlib
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem.lab.summary import MODULUS_WINDOW, fit_modulus
from jdem.validate import InputError, read_text_file


class Target(NamedTuple):
    """A target curve and its key figures (NumPy; strain ascending).

    strain, stress    (K,) [-], [Pa]
    peak_stress, peak_strain
    modulus           least-squares slope over 10 %..40 % of the peak, pre-peak [Pa]
    modulus_window    (lo, hi) strains of that fit
    stress_sigma      stated uncertainty of each stress point [Pa], or None (the
                      residuals are then relative to the peak stress)
    lateral_strain    (K,) or None: the lateral strain at the same points, compression
                      positive (negative as the specimen bulges), as in the lab tests'
                      histories; it makes Poisson's ratio identifiable.  NaN where
                      there is no reading (a gauge that failed at the peak): those
                      points carry no lateral residual.  Past the peak the simulated
                      lateral strain is the extent of a breaking specimen, not a
                      gauge reading, so a target usually stops it at the peak.
    """

    strain: np.ndarray
    stress: np.ndarray
    peak_stress: float
    peak_strain: float
    modulus: float
    modulus_window: tuple
    stress_sigma: float | None = None
    lateral_strain: np.ndarray | None = None


class LossWeights(NamedTuple):
    """Weights of the three parts of a curve's misfit (each is dimensionless)."""

    pre_peak: float = 1.0
    post_peak: float = 1.0
    peak: float = 1.0
    modulus: float = 1.0
    lateral: float = 1.0


#: scalar quantities a :class:`Scalar` may name, and the history entry each is read from
SCALAR_QUANTITIES = {
    "peak_stress": "axial_stress",          # UCS or the peak of a biaxial / tension test [Pa]
    "youngs_modulus": "axial_stress",       # slope over 10 %..40 % of the peak [Pa]
    "poisson_ratio": "lateral_strain",      # -d(lateral strain)/d(axial strain), same window
    "tensile_strength": "tensile_strength_indirect",   # Brazilian 2 P / (pi D t) [Pa]
}


class Scalar(NamedTuple):
    """One measured figure: ``quantity`` (a key of :data:`SCALAR_QUANTITIES`),
    ``value`` and its standard uncertainty ``sigma`` (both in SI units)."""

    quantity: str
    value: float
    sigma: float


def check_scalar(t: Scalar) -> Scalar:
    if t.quantity not in SCALAR_QUANTITIES:
        raise InputError(f"scalar target quantity {t.quantity!r} is not one of "
                         f"{sorted(SCALAR_QUANTITIES)}")
    for name in ("value", "sigma"):
        v = getattr(t, name)
        if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
            raise InputError(f"scalar target {t.quantity}.{name} must be a positive number, "
                             f"got {v!r}")
    if t.quantity == "poisson_ratio":
        if not t.value < 0.5:
            raise InputError(f"scalar target poisson_ratio = {t.value!r} must be below 0.5")
    elif t.quantity == "youngs_modulus" and t.value < 1e6:
        raise InputError(f"scalar target youngs_modulus = {t.value!r} Pa: moduli are in Pa "
                         f"(this looks like GPa: multiply by 1e9)")
    elif t.value < 1e4:
        raise InputError(f"scalar target {t.quantity} = {t.value!r} Pa: stresses are in Pa "
                         f"(this looks like MPa: multiply by 1e6)")
    return Scalar(t.quantity, float(t.value), float(t.sigma))


# ----------------------------------------------------------------------------- reading curves
#: largest strain a target may reach unless ``allow_large_strain``: rock specimens fail
#: well below 5 %, so a larger value is almost always a column in percent
MAX_TARGET_STRAIN = 0.05


def load_target(source, *, strain_column=0, stress_column=1, lateral_column=None,
                stress_sigma=None, allow_large_strain=False) -> Target:
    """A :class:`Target` from ``(strain, stress)`` arrays, a dict with ``strain``
    and ``stress`` (e.g. a simulated curve or history; ``axial_strain`` /
    ``axial_stress`` also work; ``lateral_strain`` is taken when present), or a
    CSV file of two columns (strain, stress in Pa; a header line is allowed) or
    three (``lateral_column=2``: the lateral strain, compression positive;
    ``lateral_column="auto"``: the column after strain and stress when the first
    row of numbers has one).  Malformed input raises ``InputError``, and so
    does a strain column in percent (strain above :data:`MAX_TARGET_STRAIN`) or
    a stress column in MPa (peak below 1e4 Pa)."""
    if isinstance(source, Target):
        return source
    lateral = None
    if isinstance(source, (str, pathlib.Path)):
        cols = _read_csv(pathlib.Path(source), strain_column, stress_column, lateral_column)
        strain, stress = cols[0], cols[1]
        lateral = cols[2] if len(cols) == 3 else None
    elif isinstance(source, dict):
        key_e = "strain" if "strain" in source else "axial_strain"
        key_s = "stress" if "stress" in source else "axial_stress"
        if key_e not in source or key_s not in source:
            raise InputError(f"target dict needs 'strain' and 'stress', got keys {sorted(source)}")
        strain, stress = source[key_e], source[key_s]
        lateral = source.get("lateral_strain")
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
    if lateral is not None:
        lateral = np.asarray(lateral, np.float64).ravel()
        read = ~np.isnan(lateral)
        if lateral.shape != strain.shape or np.any(np.isinf(lateral)) or np.sum(read) < 3:
            raise InputError(f"target lateral_strain must be {strain.size} values (NaN where "
                             f"there is no reading, at least 3 readings), got {lateral.size} "
                             f"with {int(np.sum(read))} readings and "
                             f"{int(np.sum(np.isinf(lateral)))} infinite")
        if float(np.max(np.abs(lateral[read]))) > MAX_TARGET_STRAIN and not allow_large_strain:
            raise InputError(f"target lateral strain reaches "
                             f"{float(np.max(np.abs(lateral[read])))!r}: strain is "
                             f"dimensionless; divide a percent column by 100")
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
    if float(np.max(np.abs(strain))) > MAX_TARGET_STRAIN and not allow_large_strain:
        raise InputError(f"target strain reaches {float(np.max(np.abs(strain)))!r}: strain is "
                         f"dimensionless (0.003, not 0.3 %); divide a percent column by 100 "
                         f"(or pass allow_large_strain=True for a strain above "
                         f"{MAX_TARGET_STRAIN})")
    if peak < 1e4:
        raise InputError(f"target peak stress is {peak!r} Pa: stress must be in Pa "
                         f"(this looks like MPa: multiply by 1e6)")
    if stress_sigma is not None and not (np.isfinite(stress_sigma) and stress_sigma > 0):
        raise InputError(f"stress_sigma must be a positive number of Pa, got {stress_sigma!r}")
    modulus, window = fit_modulus(strain, stress, min_points=2)
    if not np.isfinite(modulus):
        modulus, window = peak / max(float(strain[k]), 1e-300), (0.0, float(strain[k]))
    return Target(strain, stress, peak, float(strain[k]), modulus, window,
                  None if stress_sigma is None else float(stress_sigma), lateral)


def _read_csv(path, ce, cs, cl=None):
    text = read_text_file(path, "target file", "CSV")
    rows = []
    header = False
    for n, row in enumerate(csv.reader(text.splitlines())):
        if not row or all(not c.strip() for c in row) or row[0].lstrip().startswith("#"):
            continue
        if cl == "auto":   # decided by the first row of numbers
            try:
                float(row[ce]), float(row[cs])
            except (ValueError, IndexError):
                pass
            else:
                cl = max(ce, cs) + 1 if len(row) > max(ce, cs) + 1 else None
        cl_row = None if cl == "auto" else cl
        cols = (ce, cs) if cl_row is None else (ce, cs, cl_row)
        try:
            rows.append(tuple(float(row[c]) for c in (ce, cs))
                        + (() if cl_row is None else (_reading(row[cl_row]),)))
        except ValueError:
            # only the first line may be a header, and a header holds no number
            # in these columns (a first row with a typo is an error, not a header)
            if rows or header or any(_is_number(row[c]) for c in cols if c < len(row)):
                raise InputError(f"{path}: line {n + 1} is not {len(cols)} numbers: "
                                 f"{row!r}") from None
            header = True
        except IndexError:
            raise InputError(f"{path}: line {n + 1} has {len(row)} column(s), need "
                             f"{max(cols) + 1}: {row!r}") from None
    if not rows:
        raise InputError(f"{path} holds no (strain, stress) rows")
    a = np.asarray(rows)
    return tuple(a[:, c] for c in range(a.shape[1]))


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _reading(cell: str) -> float:
    """A lateral-strain cell: a number, or empty for "no reading" (NaN)."""
    return float(cell) if cell.strip() else float("nan")


# ----------------------------------------------------------------------------- residuals
def _window_slope(strain, stress, lo, hi):
    """Least-squares slope of ``stress`` over ``lo <= strain <= hi`` (traced)."""
    sel = (strain >= lo) & (strain <= hi)
    n = jnp.maximum(jnp.sum(sel), 1)
    em = jnp.sum(jnp.where(sel, strain, 0.0)) / n
    sm = jnp.sum(jnp.where(sel, stress, 0.0)) / n
    return (jnp.sum(jnp.where(sel, (strain - em) * (stress - sm), 0.0))
            / jnp.maximum(jnp.sum(jnp.where(sel, (strain - em) ** 2, 0.0)), 1e-300))


def curve_residuals(strain, stress, target: Target, weights: LossWeights = LossWeights(),
                    lateral=None):
    """Residuals (K + 2,) of one simulated curve ``(strain, stress)`` (R,) against
    ``target``: K interpolated stress differences, then the peak and the modulus;
    with a target lateral strain, K more: the simulated ``lateral`` (R,) strain
    minus the target's over its largest magnitude, weighted as the stresses (points
    without a reading, NaN, carry none).

    The simulated stress is interpolated (linearly) onto the target strains; a
    target point outside the simulated range gets residual 0.  Point i carries
    sqrt(w_i / sum w) with w = ``pre_peak`` up to the target's peak strain and
    ``post_peak`` after it, over the peak stress (or ``target.stress_sigma``).
    Then sqrt(``peak``) x (relative peak-stress error) and sqrt(``modulus``) x
    (relative error of the slope over the target's 10 %..40 % window).
    Differentiable in ``stress``; use ``jax.vmap`` for several curves."""
    et = jnp.asarray(target.strain)
    st = jnp.asarray(target.stress)
    inside = (et >= strain[0]) & (et <= strain[-1])
    sim = jnp.interp(et, strain, stress)
    w = jnp.where(et <= target.peak_strain, weights.pre_peak, weights.post_peak) * inside
    scale = target.peak_stress if target.stress_sigma is None else target.stress_sigma
    points = jnp.sqrt(w / jnp.maximum(jnp.sum(w), 1e-300)) * (sim - st) / scale
    peak = jnp.sqrt(weights.peak) * (jnp.max(stress) / target.peak_stress - 1.0)
    slope = _window_slope(strain, stress, *target.modulus_window)
    modulus = jnp.sqrt(weights.modulus) * (slope / target.modulus - 1.0)
    parts = [points, peak[None], modulus[None]]
    if target.lateral_strain is not None:
        if lateral is None:
            raise InputError("the target has a lateral strain column but the test records "
                             "none")
        # points with a reading; the target may arrive traced (a solver passes it as
        # an argument of its compiled step), so no host conversions here
        lt_all = jnp.asarray(target.lateral_strain)
        read = ~jnp.isnan(lt_all)
        lt = jnp.where(read, lt_all, 0.0)
        scale_l = jnp.maximum(jnp.max(jnp.abs(lt)), 1e-12)
        sim_l = jnp.interp(et, strain, lateral)
        wl = w * read
        parts.append(jnp.sqrt(weights.lateral * wl / jnp.maximum(jnp.sum(wl), 1e-300))
                     * (sim_l - lt) / scale_l)
    return jnp.concatenate(parts)


def curve_loss(strain, stress, target: Target, weights: LossWeights = LossWeights(),
               lateral=None):
    """Sum of squares of :func:`curve_residuals`: the weighted mean-square stress
    misfit over the peak squared, plus ``peak`` x (relative peak error)^2 and
    ``modulus`` x (relative slope error)^2."""
    return jnp.sum(curve_residuals(strain, stress, target, weights, lateral) ** 2)


def simulated_scalar(history: dict, quantity: str):
    """The simulated value (traced) of a :data:`SCALAR_QUANTITIES` entry from one
    member's history."""
    if quantity == "peak_stress":
        return jnp.max(history["axial_stress"])
    if quantity == "tensile_strength":
        if "tensile_strength_indirect" not in history:
            raise InputError("a tensile_strength target needs a Brazilian test "
                             "(lab.BRAZILIAN) set-up")
        return jnp.max(history["tensile_strength_indirect"])
    if quantity in ("youngs_modulus", "poisson_ratio"):
        stress, strain = history["axial_stress"], history["axial_strain"]
        k = jnp.argmax(stress)
        peak = jax.lax.stop_gradient(stress[k])
        lo_f, hi_f = MODULUS_WINDOW
        pre = jnp.arange(stress.shape[0]) <= k
        lo = jax.lax.stop_gradient(
            jnp.min(jnp.where(pre & (stress >= lo_f * peak), strain, jnp.inf)))
        hi = jax.lax.stop_gradient(
            jnp.max(jnp.where(pre & (stress <= hi_f * peak), strain, -jnp.inf)))
        if quantity == "youngs_modulus":
            return _window_slope(strain, stress, lo, hi)
        if "lateral_strain" not in history:
            raise InputError("a poisson_ratio target needs a test that records lateral strain")
        return -_window_slope(strain, history["lateral_strain"], lo, hi)
    raise InputError(f"unknown scalar quantity {quantity!r}")


def scalar_residuals(history: dict, targets) -> jnp.ndarray:
    """(len(targets),) z-scores (simulated - value) / sigma of :class:`Scalar`
    targets against one member's history."""
    return jnp.stack([(simulated_scalar(history, t.quantity) - t.value) / t.sigma
                      for t in targets])
