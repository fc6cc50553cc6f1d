"""The quasi-static certificate: run a test at its rate and slower, compare.

Citations ("000 §3.2") refer to the documents listed in REFERENCES.md.

Dynamic relaxation (000 §2.3, §3.2) seeks the static response; a curve that
still changes when the loading is slowed describes the loading rate and the
damping, not the rock.  :func:`certify` runs the set-up at its loading rate
and at ``1 / factor`` of it (the same specimen, damping and strain range; the
ramp lasts as many wave transits) and compares the peak stress and the modulus
(:func:`jdem.lab.summary.fit_modulus`).  Calibration refuses a set-up that
does not pass unless told otherwise.

Near the quasi-static limit a figure of the curve moves linearly with the
loading rate (measured: experiments/results/rate_convergence), so the two runs
also give the limit itself: :func:`rate_extrapolated` is the first-order
(Richardson) extrapolation to rate zero, :func:`extrapolated_curve` applies
it to a whole curve (matched at the same fraction of the peak strain), and calibration can fit it
(``jdem.calibrate.calibrate(..., extrapolate_rate=True)``).
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jdem.lab import core
from jdem.lab.summary import (QUASI_STATIC_TOLERANCE, Certificate, peak_summary,
                              rate_extrapolated)


def slowed(setup: core.Setup, factor: float = 2.0) -> core.Setup:
    """The same test with the loading ``factor`` times slower: the drive velocities
    divided by ``factor``, the loading records and the ramp multiplied by it
    (the preload, if any, unchanged)."""
    plan = setup.plan
    pre = plan.preload_records
    n_load = plan.n_records - pre
    frame = setup.frame._replace(velocity=setup.frame.velocity / factor)
    options = tuple((k, v / factor if k == "loading_rate" else v) for k, v in plan.options)
    plan = plan.replace(n_records=pre + int(math.ceil(n_load * factor)),
                        ramp_records=int(math.ceil(plan.ramp_records * factor)),
                        options=options)
    return setup.replace(frame=frame, plan=plan)


#: per-record entries a quasi-static estimate extrapolates (the rest come from the run at the rate)
EXTRAPOLATED = ("axial_stress", "lateral_strain", "tensile_strength_indirect")


def peak_strain(strain, stress):
    """The strain at the peak of one curve (R,): the vertex of the parabola
    through the largest record and its two neighbours (the largest record's
    strain where the three do not bend down).  Moves continuously with the
    curve, so it can be differentiated."""
    k = jnp.clip(jnp.argmax(stress), 1, stress.shape[0] - 2)
    e0, e1, e2 = strain[k - 1], strain[k], strain[k + 1]
    s0, s1, s2 = stress[k - 1], stress[k], stress[k + 1]
    d01, d12 = (s1 - s0) / (e1 - e0), (s2 - s1) / (e2 - e1)
    curv = (d12 - d01) / (e2 - e0)                       # half the second derivative
    bends = curv < 0
    vertex = 0.5 * (e0 + e1) - d01 / (2.0 * jnp.where(bends, curv, -1.0))
    return jnp.where(bends, jnp.clip(vertex, e0, e2), e1)


def extrapolated_curve(at_rate: dict, slower: dict, factor: float = 2.0) -> dict:
    """The quasi-static estimate of one curve (unbatched, records on axis 0; JAX
    or NumPy) from the runs at a rate and ``factor`` times slower.

    The peak moves with the rate (to a larger strain at a higher rate), so the
    curves are matched at the same fraction xi = strain / peak strain
    (:func:`peak_strain`), not at the same strain: the record of the run at
    the rate with fraction xi is paired with the slower curve interpolated at
    xi, and strain is xi times the extrapolated peak strain.  Up to the peak
    (xi <= 1) every entry of ``EXTRAPOLATED`` goes through
    :func:`rate_extrapolated`: a linear-elastic stretch stays linear with the
    extrapolated slope, and the peak is the extrapolation of the two peaks.
    Past the peak the two runs soften by discrete drops at different xi, so a
    pointwise extrapolation there amplifies each drop (measured: +28 % above
    the peak); instead the slower run's post-peak curve is scaled by the
    extrapolated-over-slower ratio of the entry at the peak (continuous at xi =
    1; exact where the rate scales the curve).
    Returns ``at_rate`` with those entries replaced and its own ``axial_strain``
    and ``axial_stress`` kept as ``axial_strain_at_rate`` and
    ``axial_stress_at_rate``.  Differentiable; ``jax.vmap`` it over members."""
    strain, slow_strain = at_rate["axial_strain"], slower["axial_strain"]
    tiny = 1e-300 if jnp.asarray(strain).dtype == jnp.float64 else 1e-30
    pf = jnp.maximum(peak_strain(strain, at_rate["axial_stress"]), tiny)
    ps = jnp.maximum(peak_strain(slow_strain, slower["axial_stress"]), tiny)
    xi = strain / pf
    out = dict(at_rate)
    out["axial_strain_at_rate"] = strain
    out["axial_stress_at_rate"] = at_rate["axial_stress"]
    out["axial_strain"] = xi * rate_extrapolated(pf, ps, factor)
    for key in EXTRAPOLATED:
        if key in at_rate and key in slower:
            slow_at_xi = jnp.interp(xi * ps, slow_strain, slower[key])
            at_peak = jnp.interp(pf, strain, at_rate[key])
            slow_at_peak = jnp.interp(ps, slow_strain, slower[key])
            ok = jnp.abs(slow_at_peak) > tiny
            ratio = jnp.where(ok, rate_extrapolated(at_peak, slow_at_peak, factor)
                              / jnp.where(ok, slow_at_peak, 1.0), 1.0)
            out[key] = jnp.where(xi <= 1.0, rate_extrapolated(at_rate[key], slow_at_xi, factor),
                                 ratio * slow_at_xi)
    return out


def extrapolated_history(at_rate: dict, slower: dict, factor: float = 2.0) -> dict:
    """:func:`extrapolated_curve` of two histories of one test (pure
    :func:`curve` histories or NumPy ones, at a rate and :func:`slowed` by
    ``factor``), member by member when batched (members x records).  A member
    that failed in either run keeps the run's ``first_bad_step`` (and
    ``member_first_bad_step``) of the run where it failed.  Traceable: the pure
    residuals of a calibration use it (``extrapolate_rate``)."""
    batched = jnp.ndim(at_rate["axial_strain"]) == 2

    def per_record(h):
        n = jnp.shape(h["axial_strain"])[-1]
        return {k: v for k, v in h.items()
                if jnp.ndim(v) == (2 if batched else 1) and jnp.shape(v)[-1] == n
                and jnp.issubdtype(jnp.asarray(v).dtype, jnp.floating)}

    def extrap(f, s):
        return extrapolated_curve(f, s, factor)

    out = {**at_rate, **(jax.vmap(extrap) if batched else extrap)(per_record(at_rate),
                                                                   per_record(slower))}
    for key in ("first_bad_step", "member_first_bad_step"):
        if key in at_rate and key in slower:
            out[key] = jnp.where(jnp.asarray(at_rate[key]) >= 0, at_rate[key], slower[key])
    return out


def quasi_static_history(setup: core.Setup, params=None, *, factor: float = 2.0) -> dict:
    """:func:`extrapolated_history` of ``setup`` run as a pure curve
    (:func:`jdem.lab.checked_curve`) at its rate and ``factor`` times slower;
    NumPy out."""
    fast, _ = core.checked_curve(setup, params)
    slow, _ = core.checked_curve(slowed(setup, factor), params)
    return {k: np.asarray(v) for k, v in extrapolated_history(fast, slow, factor).items()}


def certify(setup: core.Setup, params=None, *, factor=2.0, tolerance=QUASI_STATIC_TOLERANCE,
            progress=False) -> Certificate:
    """Run ``setup`` and its :func:`slowed` copy (host loop) and compare peak
    stress and modulus.  Returns a :class:`jdem.lab.summary.Certificate`
    (``quasi_static`` when both changed by less than ``tolerance``)."""
    fast = core.run(setup, params, progress=progress, warn_dynamic=False)
    slow = core.run(slowed(setup, factor), params, progress=progress, warn_dynamic=False)
    s_fast, s_slow = peak_summary(fast.history), peak_summary(slow.history)
    peak = np.asarray(s_fast["peak_stress"]) / np.asarray(s_slow["peak_stress"]) - 1.0
    mod = np.asarray(s_fast["youngs_modulus"]) / np.asarray(s_slow["youngs_modulus"]) - 1.0
    ok = bool(np.all(np.abs(peak) < tolerance) and np.all(np.abs(mod) < tolerance))
    rate = float(setup.plan.option("loading_rate", float("nan")))
    return Certificate(peak_change=peak, modulus_change=mod,
                       kinetic_ratio=np.asarray(s_fast["kinetic_ratio"]), quasi_static=ok,
                       tolerance=float(tolerance), loading_rate=rate, summary=s_fast,
                       slow_summary=s_slow, factor=float(factor))
