"""The demonstration problem of ``jdem demo`` and notebooks/calibration.ipynb:
a small calibration with a known answer."""
from __future__ import annotations

from jdem import lab
from jdem.materials import material, rock_params
from jdem.specimen import generate

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
