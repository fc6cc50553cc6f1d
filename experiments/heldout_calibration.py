"""Calibration on packings the target was not made on (the issue's held-out check).

The target is the UCS curve of one packing of ~1,050 discs (2D, 1.25 cm x 2.5 cm,
radii 0.2-0.35 mm, ``--target-seed``) with known micro-parameters (E 30 GPa,
strength 3 MPa, kappa 3e-3).  E, strength and kappa are fitted to it on an
ensemble of ``--members`` other packings of the same statistics (seeds 0, 1, ...),
one vmapped run per iteration, from E +40 %, strength -30 %, kappa +50 %
(Levenberg-Marquardt, forward-mode Jacobian).  The check: the true values lie
inside the reported 95 % intervals, E within 5 % and strength within 8 %.

The loading rate.  The issue asks for the certified rate (4e-6, the default); a
fit there costs ~1.7 h on a 2-core CPU (experiments/calibration_benchmark.py
--ensemble 4).  ``--loading-rate`` (default 3.2e-5, the rate of the suite's
calibration tests, 8x the certified one) runs target and fit at one rate, so
the packing scatter, not the rate, is what the check measures; on a GPU pass
``--loading-rate 4e-6``.  The certificate is not required at a faster rate.

    python experiments/heldout_calibration.py [--members 4] [--loading-rate 3.2e-5]
        [--steps 15] [--size 0.0125 0.025] [--post-peak 1] [--jacobian auto]
        [--out experiments/results/heldout_calibration]

Writes ``heldout_calibration.md`` and ``.json`` (values, intervals, errors,
iterations, wall time) and the calibration's own HDF5 result (``calibration.h5``,
:func:`jdem.calibrate.load_calibration` reopens it).
"""
from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import platform
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)   # set-ups built in float64, run in float32
import numpy as np  # noqa: E402

from jdem import calibrate as cb  # noqa: E402
from jdem import lab  # noqa: E402
from jdem.lab.platen import DEFAULT_LOADING_RATE  # noqa: E402
from jdem.materials import material, rock_params  # noqa: E402
from jdem.specimen import generate  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
TRUE = dict(E=30e9, strength=3e6, kappa=3e-3)
START = dict(E=1.4 * TRUE["E"], strength=0.7 * TRUE["strength"], kappa=1.5 * TRUE["kappa"])
TOLERANCE = dict(E=0.05, strength=0.08)          # the issue's; kappa: inside its interval


def packing(seed, size):
    return generate("rectangle", tuple(size), 0.2e-3, 0.35e-3, seed=seed, target_coordination=4.5)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--members", type=int, default=4)
    ap.add_argument("--target-seed", type=int, default=10)
    ap.add_argument("--loading-rate", type=float, default=3.2e-5)
    ap.add_argument("--steps", type=int, default=15)
    ap.add_argument("--size", type=float, nargs=2, default=(0.0125, 0.025))
    ap.add_argument("--max-strain", type=float, default=1.2e-3)
    ap.add_argument("--post-peak", type=float, default=1.0,
                    help="weight of the post-peak curve (LossWeights.post_peak; 0 fits the "
                         "curve up to the peak and the peak, as the README demo does)")
    ap.add_argument("--jacobian", default="auto",
                    help="calibrate's jacobian: auto (forward mode), forward, reverse or "
                         "finite-difference (central differences, for the post-peak curve)")
    ap.add_argument("--out", type=pathlib.Path, default=HERE / "results" / "heldout_calibration")
    a = ap.parse_args(argv)
    if a.target_seed in range(a.members):
        ap.error(f"--target-seed {a.target_seed} is one of the ensemble's seeds 0..{a.members - 1}")
    a.out.mkdir(parents=True, exist_ok=True)
    params = rock_params(2, kappa=TRUE["kappa"])
    kw = dict(max_strain=a.max_strain, loading_rate=a.loading_rate, stiffness_margin=2.0)
    t0 = time.time()
    target_spec = packing(a.target_seed, a.size)
    members = [packing(s, a.size) for s in range(a.members)]
    n_target = int(target_spec.info["n_particles"])
    n_members = [int(m.info["n_particles"]) for m in members]
    print(f"target: packing {a.target_seed}, {n_target} discs; ensemble: {n_members} discs; "
          f"rate {a.loading_rate:g}", flush=True)
    target_setup = lab.UCS.setup(target_spec, params, **kw)
    hist, _ = lab.checked_curve(target_setup, material(target_setup.params, TRUE))
    target = dict(strain=np.asarray(hist["axial_strain"]), stress=np.asarray(hist["axial_stress"]))
    ensemble = lab.UCS.setup(members, params, **kw)
    # the set-up's own params (its time step and damping), the fitted values replaced
    res = cb.calibrate(ensemble, target, START, steps=a.steps,
                       weights=cb.LossWeights(post_peak=a.post_peak), jacobian=a.jacobian,
                       out=a.out / "calibration.h5",
                       require_quasi_static=a.loading_rate <= DEFAULT_LOADING_RATE)
    wall = time.time() - t0
    print(cb.report(res, TRUE), flush=True)
    rows = {}
    for n in START:
        lo, hi = res.intervals[n]
        rows[n] = dict(true=TRUE[n], start=START[n], fitted=res.values[n],
                       error=res.values[n] / TRUE[n] - 1.0, interval=[lo, hi],
                       std_error=res.std_errors[n],
                       packing_std_error=res.packing_std_errors.get(n, float("nan")),
                       inside=bool(lo <= TRUE[n] <= hi))
    passed = (all(r["inside"] for r in rows.values())
              and all(abs(rows[n]["error"]) < tol for n, tol in TOLERANCE.items()))
    out = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="minutes"),
               machine=f"{platform.machine()} {platform.platform()}",
               command="python experiments/heldout_calibration.py "
                       + " ".join(argv if argv is not None else sys.argv[1:]),
               target_seed=a.target_seed, target_discs=n_target, member_discs=n_members,
               loading_rate=a.loading_rate, post_peak_weight=a.post_peak,
               jacobian=res.jacobian,
               iterations=res.steps, stop=res.stop, loss=res.loss, wall_s=wall, rows=rows, check_passed=passed)
    (a.out / "heldout_calibration.json").write_text(json.dumps(out, indent=1))
    md = ["# Calibration on packings the target was not made on", "",
          f"{out['date']}, {out['machine']}, float32; `{out['command']}`", "",
          f"Target: packing {a.target_seed} ({n_target} discs) at E 30 GPa, strength 3 MPa, "
          f"kappa 3e-3; fitted on packings 0-{a.members - 1} ({n_members} discs) as one "
          f"ensemble; loading rate {a.loading_rate:g} for both; post-peak weight "
          f"{a.post_peak:g}; {res.jacobian} Jacobian; {res.steps} iterations "
          f"({res.stop}), loss {res.loss:.3g}, {wall / 60:.1f} min in all.", "",
          "| parameter | true | start | fitted | error | standard error (packings) | "
          "95 % interval | truth inside |",
          "|---|---|---|---|---|---|---|---|"]
    for n, r in rows.items():
        md.append(f"| {n} | {r['true']:.4g} | {r['start']:.4g} | {r['fitted']:.4g} | "
                  f"{r['error'] * 100:+.2f} % | {r['std_error']:.3g} ({r['packing_std_error']:.3g}) | "
                  f"{r['interval'][0]:.4g} .. {r['interval'][1]:.4g} | "
                  f"{'yes' if r['inside'] else 'no'} |")
    md += ["", f"Check (truth inside every interval, E within 5 %, strength within 8 %): "
               f"{'passed' if passed else 'not passed'}."]
    (a.out / "heldout_calibration.md").write_text("\n".join(md) + "\n")
    print("\n".join(md[-1:]), f"-> {a.out}", sep="\n")


if __name__ == "__main__":
    main()
