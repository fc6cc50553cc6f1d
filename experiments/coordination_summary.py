#!/usr/bin/env python
"""lambda against N-bar from every way of varying N-bar, on one figure (002 §1.4, Fig 9).

    python experiments/coordination_summary.py

Reads the ``summary.json`` that ``experiments/coordination_study.py`` wrote for
the 10 cm block (loaded through bonded steel plates, the seed's circular
section): the bonding gap (``coordination_study_10cm``), the disc size
(``_size``), the porosity (``_porosity``) and the embedding (``_embedding`` and
``_embedding_high``).  Fits lambda = a N-bar^b per way (least squares in
log-log, :func:`coordination_study.power_fit`) and over all points, beside the
seed's lambda = 60.5 N-bar^-2.54 (002 eq 17).  Writes
``experiments/results/coordination_summary/``: ``lambda_all_ways.png`` and
``lambda_all_ways.md`` (the fits and every point).  Runs in seconds (no
simulation).
"""
from __future__ import annotations

import json
import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from coordination_study import SEED_A, SEED_B, power_fit  # noqa: E402

RESULTS = pathlib.Path(__file__).parent / "results"
WAYS = {"bonding gap": ["coordination_study_10cm"],
        "disc size": ["coordination_study_10cm_size"],
        "porosity": ["coordination_study_10cm_porosity"],
        "embedding": ["coordination_study_10cm_embedding",
                      "coordination_study_10cm_embedding_high"]}
OUT = RESULTS / "coordination_summary"


def load_points(folders):
    """(N-bar, lambda, area fraction) of the plated, circular-section rows."""
    pts = []
    for name in folders:
        for r in json.loads((RESULTS / name / "summary.json").read_text())["rows"]:
            if r["loading"] == "plates" and r["section"] == "circular":
                pts.append((r["n_bar"], r["lam"], r.get("area_fraction", 1.0 - r["porosity"])))
    return np.asarray(pts)


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    points = {way: load_points(folders) for way, folders in WAYS.items()}
    every = np.concatenate(list(points.values()))
    fits = {way: power_fit(p[:, 0], p[:, 1]) for way, p in points.items()}
    fits["all"] = power_fit(every[:, 0], every[:, 1])
    xs = np.linspace(3.8, 7.2, 100)
    fig, ax = plt.subplots(figsize=(6.4, 4.6))
    for k, (way, p) in enumerate(points.items()):
        a, b, _ = fits[way]
        ax.plot(p[:, 0], p[:, 1], "osv^"[k], color=f"C{k}", mfc="none",
                label=f"{way}: {a:.3g} N̄^{b:.2f}")
    a, b, r = fits["all"]
    ax.plot(xs, a * xs ** b, "-", color="gray", lw=1, label=f"all: {a:.3g} N̄^{b:.2f}")
    ax.plot(xs, SEED_A * xs ** SEED_B, "k--", lw=1.2, label="002 eq 17: 60.5 N̄^-2.54")
    ax.axhline(1.0, color="gray", lw=0.5)
    ax.set_xlabel("mean coordination number N̄")
    ax.set_ylabel("λ = L_p / L_e")
    ax.set_title("10 cm block through bonded steel plates, circular section", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "lambda_all_ways.png", dpi=130)
    plt.close(fig)

    lines = ["# λ against N̄, every way of varying N̄ (10 cm, plates, circular section)", "",
             "Command: `python experiments/coordination_summary.py` (reads the studies' "
             "summary.json files).", "",
             "| way | points | N̄ range | fit | r | λ(5) | N̄ at λ = 1 |",
             "|---|---|---|---|---|---|---|"]
    for way in list(WAYS) + ["all"]:
        p = every if way == "all" else points[way]
        a, b, r = fits[way]
        lines.append(f"| {way} | {len(p)} | {p[:, 0].min():.2f}-{p[:, 0].max():.2f} | "
                     f"{a:.3g} N̄^{b:.2f} | {r:.3f} | {a * 5.0 ** b:.3f} | "
                     f"{(1.0 / a) ** (1.0 / b):.2f} |")
    lines.append(f"| seed (002 eq 17) | | | {SEED_A} N̄^{SEED_B} | 0.967 | "
                 f"{SEED_A * 5.0 ** SEED_B:.3f} | {(1.0 / SEED_A) ** (1.0 / SEED_B):.2f} |")
    lines += ["", "| way | N̄ | area fraction | λ | seed's law | λ / law |", "|---|---|---|---|---|---|"]
    for way, p in points.items():
        for n, lam, frac in sorted(p.tolist()):
            law = SEED_A * n ** SEED_B
            lines.append(f"| {way} | {n:.2f} | {frac:.3f} | {lam:.3f} | {law:.3f} | "
                         f"{lam / law:.2f} |")
    (OUT / "lambda_all_ways.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[4:4 + len(WAYS) + 3]))
    print(f"-> {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
