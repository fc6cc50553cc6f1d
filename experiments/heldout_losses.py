"""The held-out check's losses, split: at the truth and at each fit, the mean
over members of each member's squared misfit to the target (what an ensemble
calibration minimised until 2026-12-08) and its two parts, the misfit of the
members' mean residuals (what it minimises since) and the spread of the members
about that mean (since then left to the intervals).

    python experiments/heldout_losses.py [--out experiments/results/heldout_calibration]

Reads the fitted values of the runs ``post_peak_0``, ``post_peak_1_fd`` (fits of the
mean of the members' losses) and ``mean_post_peak_0``, ``mean_post_peak_1_fd`` (fits of
the members' mean), those present, written by experiments/heldout_calibration.py under
``--out``; writes ``losses.md``/``.json``
there.  Same target, ensemble and loading rate as that script's defaults.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import heldout_calibration as hc  # noqa: E402

from jdem import calibrate as cb  # noqa: E402
from jdem import lab  # noqa: E402
from jdem.materials import material, rock_params  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=pathlib.Path, default=hc.HERE / "results" / "heldout_calibration")
    a = ap.parse_args(argv)
    kw = dict(max_strain=1.2e-3, loading_rate=3.2e-5, stiffness_margin=2.0)
    size = (0.0125, 0.025)
    params = rock_params(2, kappa=hc.TRUE["kappa"])
    ts = lab.UCS.setup(hc.packing(10, size), params, **kw)
    hist, _ = lab.checked_curve(ts, material(ts.params, hc.TRUE))
    target = cb.load_target(dict(strain=np.asarray(hist["axial_strain"]),
                                 stress=np.asarray(hist["axial_stress"])))
    ens = lab.UCS.setup([hc.packing(s, size) for s in range(4)], params, **kw)
    points = {"truth": hc.TRUE, "start": hc.START}
    for run in ("post_peak_0", "post_peak_1_fd", "mean_post_peak_0", "mean_post_peak_1_fd"):
        path = a.out / run / "heldout_calibration.json"
        if path.exists():
            rows = json.loads(path.read_text())["rows"]
            points[run] = {n: r["fitted"] for n, r in rows.items()}
    curve = jax.jit(lambda p: lab.curve(ens, p).history)
    out = {}
    md = ["# The held-out check's losses, split into the mean misfit and the members' spread",
          "", "`python experiments/heldout_losses.py`; target packing 10, ensemble packings 0-3, "
          "rate 3.2e-5, float32 runs.", "",
          "| point | post-peak weight | mean of the members' losses | misfit of the mean | spread "
          "about the mean | member peaks [MPa] |", "|---|---|---|---|---|---|"]
    for name, values in points.items():
        h = curve(material(ens.params, values))
        peaks = np.asarray(h["axial_stress"]).max(axis=1) / 1e6
        for w in (1.0, 0.0):
            weights = cb.LossWeights(post_peak=w)
            r = np.asarray(jax.vmap(lambda e, s: cb.curve_residuals(e, s, target, weights))(
                h["axial_strain"], h["axial_stress"]))
            mean = r.mean(axis=0)
            row = dict(loss=float(np.mean(np.sum(r ** 2, axis=1))),
                       mean_misfit=float(np.sum(mean ** 2)),
                       spread=float(np.mean(np.sum((r - mean) ** 2, axis=1))),
                       peaks_MPa=peaks.round(3).tolist())
            out[f"{name}/post_peak_{w:g}"] = row
            md.append(f"| {name} | {w:g} | {row['loss']:.4g} | {row['mean_misfit']:.4g} | "
                      f"{row['spread']:.4g} | {', '.join(f'{p:.2f}' for p in peaks)} |")
            print(md[-1], flush=True)
    md += ["", f"Target peak {target.peak_stress / 1e6:.3f} MPa."]
    (a.out / "losses.json").write_text(json.dumps(out, indent=1))
    (a.out / "losses.md").write_text("\n".join(md) + "\n")


if __name__ == "__main__":
    main()
