"""Laboratory tests, each defined once (:mod:`jdem.lab.core`), run as a host
loop (:func:`run`) or as a pure function of ``Params`` (:func:`curve`).
Citations ("002 §1.3") refer to the documents listed in REFERENCES.md.

    from jdem import lab
    from jdem.materials import rock_params
    setup = lab.UCS.setup(specimen, rock_params(2))   # or lab.BIAXIAL, lab.BRAZILIAN, lab.TENSION
    result = lab.run(setup)                            # progress bar, checkpoints, early stop
    print(lab.peak_summary(result.history))
    print(lab.certify(setup))                          # is the curve quasi-static?

Modules: :mod:`~jdem.lab.core` (the test object, the two runners),
:mod:`~jdem.lab.platen` (UCS, biaxial / triaxial, Brazilian),
:mod:`~jdem.lab.tension` (direct tension between grips),
:mod:`~jdem.lab.damping` (the quasi-static damping), :mod:`~jdem.lab.summary`
and :mod:`~jdem.lab.certify` (key figures, the quasi-static certificate),
:mod:`~jdem.lab.pattern` (failure patterns), :mod:`~jdem.lab.checkpoint`,
:mod:`~jdem.lab.single_bond` (002 §1.3) and :mod:`~jdem.lab.energy` (002 §1.4).
"""
from jdem.lab.core import (LabResult, LabTest, Plan, Setup, checked_curve, curve,  # noqa: F401
                           grow, in_precision, run, stack_setups)
from jdem.lab.damping import Damping, local, smooth  # noqa: F401
from jdem.lab.platen import BIAXIAL, BRAZILIAN, TRIAXIAL, UCS, PlatenFrame  # noqa: F401
from jdem.lab.tension import TENSION  # noqa: F401
from jdem.lab.summary import (Certificate, curve_stages, fit_modulus,  # noqa: F401
                              kinetic_ratio, peak_summary, rate_extrapolated)
from jdem.lab.certify import (certify, extrapolated_curve, extrapolated_history,  # noqa: F401
                              peak_strain, quasi_static_history, slowed)
from jdem.lab.pattern import damage_map, failure_pattern, first_breaks  # noqa: F401

#: the tests by name (for the command line and configuration files)
TESTS = {t.name: t for t in (UCS, BIAXIAL, BRAZILIAN, TENSION)}
