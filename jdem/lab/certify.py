"""The quasi-static certificate: run a test at its rate and slower, compare.

Citations ("000 §3.2") refer to the documents listed in REFERENCES.md.

Dynamic relaxation (000 §2.3, §3.2) seeks the static response; a curve that
still changes when the loading is slowed describes the loading rate and the
damping, not the rock.  :func:`certify` runs the set-up at its loading rate
and at ``1 / factor`` of it (the same specimen, damping and strain range; the
ramp lasts as many wave transits) and compares the peak stress and the modulus
(:func:`jdem.lab.summary.fit_modulus`).  Calibration refuses a set-up that
does not pass unless told otherwise.
"""
from __future__ import annotations

import math

import numpy as np

from jdem.lab import core
from jdem.lab.summary import QUASI_STATIC_TOLERANCE, Certificate, peak_summary


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
                       slow_summary=s_slow)
