#!/usr/bin/env python
"""The reduced UCS study of tests/test_ucs_reduced.py on several packings,
against the seed's figures (002 §2.2-2.3).

    python experiments/ucs_seed_bands.py                 # packings 2, 3, 4, 5
    python experiments/ucs_seed_bands.py --seeds 2 3 --kappas 0 0.024

Each packing: a 1.8 cm x 3.6 cm rectangle, r in [0.2, 0.35] mm, N-bar 5, the
seed's material (E 30 GPa, nu 0.22, T0 = c0 = 3 MPa, phi 30 deg), local damping
0.8 and a 3 nm platen step (the seed's specimen is 5 cm x 10 cm with 13,097 discs
and a 1 nm step, 002 §2.1; the 3 nm step is a loading rate of 5.2e-5, 3-13 x the
seed's, whose kappa = 0 peak it doubles: experiments/results/ucs_stages_rate/).  All packings and fracture
strains run as one batch, stopping once every member fell below 60 % of its
peak.  The seed gives (002 §2.2, Fig 11, 14): kappa = 0: peak 6.54 MPa at a
critical strain of 232e-6, fracture degree 1.5 % at the peak and 19 % at the
end; kappa = 2.4 %: 20.1 MPa at 861e-6, 0.073 % and 2.4 %.

Writes ``experiments/results/ucs_seed_bands/``: ``ucs_seed_bands.md`` (per
packing and mean +- std over packings, beside the seed), ``.json``, ``.h5``
(curves and figures; reopen with ``jdem.io.load_run``) and ``.png`` (curves).
"""
from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jdem import io, lab  # noqa: E402
from jdem.materials import rock_params  # noqa: E402
from jdem.specimen import generate  # noqa: E402

SIZE = (0.018, 0.036)
RADII = (0.2e-3, 0.35e-3)
STEP = 3e-9
#: 002 §2.2-2.3 (Fig 11, 14): kappa -> figures
SEED = {0.0: dict(peak_stress=6.54e6, critical_strain=232e-6, fracture_degree_at_peak=0.015,
                  fracture_degree_end=0.19),
        0.024: dict(peak_stress=20.1e6, critical_strain=861e-6,
                    fracture_degree_at_peak=0.00073, fracture_degree_end=0.024)}
FIGURES = ("peak_stress", "critical_strain", "fracture_degree_at_peak", "fracture_degree_end",
           "youngs_modulus")
OUT = pathlib.Path(__file__).parent / "results" / "ucs_seed_bands"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[2, 3, 4, 5])
    ap.add_argument("--kappas", type=float, nargs="+", default=[0.0, 3e-3, 2.4e-2])
    ap.add_argument("--out", type=pathlib.Path, default=OUT)
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    specs = [generate("rectangle", SIZE, *RADII, seed=s, target_coordination=5.0)
             for s in a.seeds]
    n = [int(np.sum(np.asarray(sp.particles.valid))) for sp in specs]
    print(f"{len(specs)} packings of {n} discs, N-bar "
          f"{[round(float(sp.coordination), 2) for sp in specs]} ({time.time() - t0:.0f} s)",
          flush=True)
    members = [(s, k) for s in range(len(specs)) for k in a.kappas]
    setup = lab.UCS.setup([specs[s] for s, _ in members],
                          rock_params(2, kappa=[k for _, k in members]), platen_step=STEP,
                          max_strain=2e-3, damping=lab.local(0.8), record_every=50)
    t1 = time.time()
    res = lab.run(setup, stop_stress_ratio=0.6, progress=True, warn_dynamic=False)
    run_s = time.time() - t1
    s = lab.peak_summary(res.history)
    rows = [dict(seed=a.seeds[p], kappa=k, n_discs=n[p],
                 **{f: float(np.asarray(s[f])[m]) for f in FIGURES})
            for m, (p, k) in enumerate(members)]
    stats = {}
    for k in a.kappas:
        sel = [r for r in rows if r["kappa"] == k]
        stats[k] = {f: (float(np.mean([r[f] for r in sel])),
                        float(np.std([r[f] for r in sel], ddof=1)) if len(sel) > 1 else np.nan)
                    for f in FIGURES}
    out = dict(date=datetime.date.today().isoformat(), command="python experiments/"
               "ucs_seed_bands.py " + " ".join(argv if argv is not None else
                                                 __import__("sys").argv[1:]),
               n_discs=n, run_s=run_s, rows=rows,
               stats={str(k): v for k, v in stats.items()},
               seed={str(k): v for k, v in SEED.items()})
    (a.out / "ucs_seed_bands.json").write_text(json.dumps(out, indent=1))
    io.save_run(a.out / "ucs_seed_bands.h5",
                history={"axial_strain": res.history["axial_strain"],
                         "axial_stress": res.history["axial_stress"],
                         "fracture_degree": res.history["fracture_degree"]},
                attrs={"members": json.dumps(members), "seeds": a.seeds,
                       "kappas": list(a.kappas), "figures": {f: [r[f] for r in rows]
                                                             for f in FIGURES}})
    md = ["# The reduced UCS study on several packings, beside the seed (002 §2)", "",
          f"{out['date']}, `{out['command']}`, float64, 2-core CPU; {len(specs)} packings of "
          f"{min(n)}-{max(n)} discs, one batch of {len(members)} members, {run_s:.0f} s.", "",
          "| kappa | figure | mean | std over packings (rel.) | seed | (mean - seed) / seed "
          "| in mean +- 3 std? |", "|---|---|---|---|---|---|---|"]
    for k in a.kappas:
        for f in FIGURES:
            m, sd = stats[k][f]
            ref = SEED.get(k, {}).get(f)
            dev = "" if ref is None else f"{100 * (m - ref) / ref:+.0f} %"
            inside = "" if ref is None else ("yes" if abs(m - ref) <= 3 * sd else "no")
            md.append(f"| {k:g} | {f} | {m:.4g} | {sd:.3g} ({100 * sd / abs(m):.1f} %) | "
                      f"{'' if ref is None else f'{ref:.4g}'} | {dev} | {inside} |")
    md += ["", "Per packing:", "", "| seed | kappa | discs | " + " | ".join(FIGURES) + " |",
           "|" + "---|" * (3 + len(FIGURES))]
    for r in rows:
        md.append(f"| {r['seed']} | {r['kappa']:g} | {r['n_discs']} | "
                  + " | ".join(f"{r[f]:.4g}" for f in FIGURES) + " |")
    (a.out / "ucs_seed_bands.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for m, (p, k) in enumerate(members):
        ax.plot(res.history["axial_strain"][m] * 1e6, res.history["axial_stress"][m] / 1e6,
                color=f"C{a.kappas.index(k)}", lw=1, label=f"kappa {k:g}" if p == 0 else None)
    for k, ref in SEED.items():
        ax.plot(ref["critical_strain"] * 1e6, ref["peak_stress"] / 1e6, "k*", ms=10)
    ax.set(xlabel="axial strain [1e-6]", ylabel="axial stress [MPa]",
           title="reduced UCS study, several packings; stars: the seed's peaks")
    ax.legend()
    fig.savefig(a.out / "ucs_seed_bands.png", dpi=120, bbox_inches="tight")


if __name__ == "__main__":
    main()
