#!/usr/bin/env python
"""The reduced UCS stage runs (``experiments/ucs_stages.py``) side by side: peak
stress, critical strain and fracture degree at the peak against the loading rate,
per boundary (rigid platens, bonded plates, free plates) and damping, beside the
seed's figures (002 §2.2, Fig 11, 14).

    python experiments/ucs_rate_summary.py                  # the committed runs
    python experiments/ucs_rate_summary.py DIR [DIR ...]    # result folders of ucs_stages.py

The seed loads 1 nm a step (002 §2.1) and does not give its time step.  With the
textbook's step (000 eq 3-26, 3-27: T_min / 10 from the stiffest single bond on the
lightest disc) that is a loading rate (platen speed / sqrt(E / rho)) of 3.9e-6 on
its discs; with jdem's step (every bond of a disc counted, jdem.timestep) 1.5e-5.
The plot marks that range.

Writes ``experiments/results/ucs_stages_rate/``: ``summary.md`` (the table) and
``summary.png`` (peak and critical strain against the rate).
"""
from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

RESULTS = pathlib.Path(__file__).parent / "results"
OUT = RESULTS / "ucs_stages_rate"
DEFAULT_DIRS = ([RESULTS / "ucs_stages", RESULTS / "ucs_stages_plates"]
                + sorted((RESULTS / "ucs_stages_damping").glob("*/"))
                + sorted(p for p in OUT.glob("*/") if (p / "ucs_stages.json").exists()))
#: 002 §2.2, Fig 11, 14: kappa -> (peak [Pa], critical strain, fracture degree at the peak)
SEED = {0.0: (6.54e6, 232e-6, 0.015), 2.4e-2: (20.1e6, 861e-6, 0.00073)}
SEED_RATE = (3.9e-6, 1.5e-5)       # the seed's 1 nm step as a loading rate (docstring)


def load(dirs):
    runs = []
    for d in dirs:
        js = json.loads((pathlib.Path(d) / "ucs_stages.json").read_text())
        for r in js["rows"]:
            n_peak = r["n_tension_at_peak"] + r["n_shear_at_peak"]
            runs.append(dict(folder=pathlib.Path(d).relative_to(RESULTS) if pathlib.Path(d)
                             .is_relative_to(RESULTS) else pathlib.Path(d),
                             boundary=js["boundary"]
                             + ("" if js.get("section", "circular") == "circular"
                                else ", slab section")
                             + (f", radii x {js['embed']:g} (area fraction "
                                f"{js['area_fraction']:.3f})" if js.get("embed") else ""),
                             damping=js["damping"],
                             rate=js["loading_rate"], kappa=r["kappa"],
                             peak=r["peak_stress"], strain=r["peak_strain"],
                             fd_peak=n_peak / js["n_bonds"], first_break=r["first_break_stress"],
                             residual=r["residual_stress"]))
    return runs


def table(runs):
    rows = ["| boundary | damping | loading rate | κ % | peak MPa (seed) | critical strain 1e-6 "
            "(seed) | fracture degree at peak % (seed) | first break MPa | folder |",
            "|---|---|---|---|---|---|---|---|---|"]
    key = lambda r: (r["boundary"], r["damping"], -r["rate"], r["kappa"])
    # (run key, format of a value, of the seed's) per column that has a seed figure
    columns = (("peak", lambda v: f"{v / 1e6:.2f}", lambda v: f"{v / 1e6:.2f}"),
               ("strain", lambda v: f"{v * 1e6:.0f}", lambda v: f"{v * 1e6:.0f}"),
               ("fd_peak", lambda v: f"{100 * v:.2f}", lambda v: f"{100 * v:.3g}"))
    for r in sorted(runs, key=key):
        seed = SEED.get(r["kappa"])
        cells = [ours(r[k]) + (f" ({theirs(seed[n])})" if seed else "")
                 for n, (k, ours, theirs) in enumerate(columns)]
        rows.append(f"| {r['boundary']} | {r['damping']} | {r['rate']:.3g} | "
                    f"{100 * r['kappa']:g} | {' | '.join(cells)} | "
                    f"{r['first_break'] / 1e6:.2f} | {r['folder']} |")
    return "\n".join(rows)


def plot(runs, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    configs = sorted({(r["boundary"], r["damping"]) for r in runs})
    for c, (boundary, damping) in enumerate(configs):
        for kappa, marker in ((0.0, "o"), (2.4e-2, "s")):
            sel = sorted((r for r in runs if (r["boundary"], r["damping"]) == (boundary, damping)
                          and r["kappa"] == kappa), key=lambda r: r["rate"])
            if not sel:
                continue
            rate = [r["rate"] for r in sel]
            label = f"{boundary}, {damping}" if kappa == 0.0 else None
            axes[0].plot(rate, [r["peak"] / 1e6 for r in sel], marker=marker, color=f"C{c}",
                         label=label)
            axes[1].plot(rate, [r["strain"] * 1e6 for r in sel], marker=marker, color=f"C{c}")
    for kappa, (peak, strain, _) in SEED.items():
        axes[0].axhline(peak / 1e6, color="k", ls=":", lw=1)
        axes[1].axhline(strain * 1e6, color="k", ls=":", lw=1)
    for ax in axes:
        ax.axvspan(*SEED_RATE, color="0.9", zorder=0)
        ax.axvline(4e-6, color="0.5", lw=0.8, ls="--")
        ax.set_xscale("log")
        ax.set_xlabel("loading rate (platen speed / bar wave speed)")
    axes[0].set_ylabel("peak stress [MPa]  (o: κ = 0, s: κ = 2.4 %)")
    axes[1].set_ylabel("critical strain [1e-6]")
    axes[0].set_title("dotted: the seed (002 Fig 11); grey: its 1 nm step", fontsize=9)
    axes[1].set_title("dashed: jdem's certified default rate 4e-6", fontsize=9)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="*", type=pathlib.Path, default=DEFAULT_DIRS)
    ap.add_argument("--out", type=pathlib.Path, default=OUT)
    a = ap.parse_args(argv)
    runs = load(a.dirs)
    a.out.mkdir(parents=True, exist_ok=True)
    md = table(runs)
    (a.out / "summary.md").write_text("# Reduced UCS study against the loading rate "
                                      "(`python experiments/ucs_rate_summary.py`)\n\n"
                                      + md + "\n")
    plot(runs, a.out / "summary.png")
    print(md)
    print(f"-> {a.out / 'summary.md'}, {a.out / 'summary.png'}")


if __name__ == "__main__":
    main()
