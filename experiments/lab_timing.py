"""Time one UCS curve of the calibration demo's packing through the lab layer,
as the pure function (:func:`jdem.lab.curve`) and as the host loop
(:func:`jdem.lab.run`), first call (compile included) and second call.

    python experiments/lab_timing.py [--platen-step 1.25e-9] [--damping smooth|local]

Prints the figures; the same test is run both ways, so the two peaks agree.
"""
from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jdem import lab  # noqa: E402
from jdem.materials import material, rock_params  # noqa: E402
from jdem.specimen import generate  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--platen-step", type=float, default=None,
                    help="platen step [m]; default: the quasi-static loading rate")
    ap.add_argument("--damping", choices=("smooth", "local"), default="smooth")
    a = ap.parse_args(argv)
    spec = generate("rectangle", (0.004, 0.008), 0.2e-3, 0.35e-3, seed=2, target_coordination=4.5)
    params = material(rock_params(2, kappa=3e-3), dict(E=30e9, strength=3e6))
    damping = lab.smooth() if a.damping == "smooth" else lab.local(0.8)
    kw = dict(platen_step=a.platen_step) if a.platen_step else {}
    setup = lab.UCS.setup(spec, params, max_strain=1.2e-3, damping=damping, **kw)
    steps = setup.plan.n_records * setup.plan.record_every
    for name, fn in (("pure (lab.curve)", lambda: lab.checked_curve(setup)[0]),
                     ("host (lab.run)", lambda: lab.run(setup, progress=False).history)):
        times = []
        for _ in range(2):
            t = time.perf_counter()
            hist = fn()
            times.append(time.perf_counter() - t)
        print(f"{name}: {steps} steps ({setup.plan.n_records} records), damping {damping}, "
              f"first call {times[0]:.2f} s, second {times[1]:.2f} s, peak "
              f"{float(np.max(hist['axial_stress'])) / 1e6:.3f} MPa")


if __name__ == "__main__":
    main()
