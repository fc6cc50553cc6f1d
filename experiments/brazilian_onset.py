#!/usr/bin/env python
"""Which bonds of a Brazilian disc are nearest to breaking just before the first break?

    python experiments/brazilian_onset.py                       # the suite's disc, D = 12 mm
    python experiments/brazilian_onset.py --diameter 0.02 --out results/brazilian_onset_20mm

The test suite's Brazilian disc (D = 12 mm, r in [0.2, 0.35] mm, N-bar 5,
T0 = 3 MPa, c0 = 10 MPa, kappa = 0, flat rigid platens, 1.5 nm per step) breaks
first along the loaded diameter but mostly away from the centre (the suite's
check that it starts at the centre, ``test_brazilian_failure_starts_at_the_centre``,
was a strict xfail; ``tests/test_lab.py::test_brazilian_reports_the_onset_location``
now reports the onset instead).  This study runs the test once to find the step of the first break,
runs it again to ``--fraction`` of the axial strain (platen travel) at that step
(no bond broken yet), and tabulates the tensile force of the intact bonds
against where they sit:

* in the band |x - x_c| < 0.2 R around the loaded diameter, the bonds within
  30 deg of horizontal (the ones the splitting tension pulls), by |y - y_c| / R:
  mean, standard deviation and largest tensile normal force;
* every bond, by distance from the centre r / R: the mean, 99th percentile and
  largest tensile utilisation F_n / (T0 A), A = 2 min(r_i, r_j) x 1 m (the
  linked bar's area, 002 eq 1), which is 1 where a bond yields in tension.

The test is ``jdem.lab.BRAZILIAN`` run by ``jdem.lab.run`` (a record every 50
steps; the first run stops once the load fell below 30 % of its peak) with the
seed's local damping, alpha = 0.8 (``jdem.lab.local(0.8)``, 002 §2.1), passed
explicitly: the lab tests' default is the smooth damping ``jdem.lab.smooth()``.
The platen speeds up over the lab tests' default ramp (10 wave transits), so the
strain at the first break is read from the first run's history rather than
taken proportional to its step.

Writes under ``--out``: ``brazilian_onset.png`` (the intact bonds coloured by
their tensile utilisation just before the first break, the first tenth of the
breaks ringed), ``brazilian_onset.h5`` (per bond: contact point, utilisation;
the first breaks; reopen with ``h5py``), ``brazilian_onset.json`` and ``.md``
(the tables).
"""
from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)
import h5py  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jdem import lab  # noqa: E402
from jdem.lab.pattern import bond_points  # noqa: E402
from jdem.materials import rock_params  # noqa: E402
from jdem.specimen import generate  # noqa: E402

RADII = (0.2e-3, 0.35e-3)   # [m], as in tests/test_lab.py
N_BAR = 5.0
STEP = 1.5e-9               # [m per step]
BINS = ((0.0, 0.2), (0.2, 0.4), (0.4, 0.6), (0.6, 0.8), (0.8, 1.01))
RECORD_EVERY = 50           # steps per record
STOP_RATIO = 0.3            # the first run stops once the load fell below 30 % of its peak
DAMPING = lab.local(0.8)    # the seed's local damping (002 §2.1), not the lab default smooth()


def brazilian(disc, params, max_strain, stop_stress_ratio):
    """The Brazilian test of this study; returns ``(history, final state)``."""
    test = lab.BRAZILIAN.setup(disc, params, platen_step=STEP, max_strain=max_strain,
                               record_every=RECORD_EVERY, damping=DAMPING)
    res = lab.run(test, stop_stress_ratio=stop_stress_ratio, progress=False)
    return res.history, res.state


def bond_table(state, centre, big_r, tensile_strength):
    """Tensile force of the intact bonds by position (see the module docstring).
    Returns the two tables and, per intact bond, its contact point relative to
    the centre (K, 2) [m] and its utilisation (K,)."""
    point, n, half = bond_points(state)   # the points failure_pattern uses
    b = state.bonds
    keep = np.asarray(b.valid) & ~np.asarray(b.broken)
    rel, n = point[keep] - centre, n[keep]
    tension = -np.asarray(b.normal_force)[keep]       # normal_force > 0 is compression
    util = tension / (tensile_strength * 2.0 * half[keep])
    along = (np.abs(rel[:, 0]) < 0.2 * big_r) & (np.abs(n[:, 0]) > np.cos(np.deg2rad(30.0)))
    y = np.abs(rel[:, 1]) / big_r
    r = np.linalg.norm(rel, axis=1) / big_r
    rows_d, rows_r = [], []
    for lo, hi in BINS:
        m = along & (y >= lo) & (y < hi)
        rows_d.append(dict(lo=lo, hi=min(hi, 1.0), n=int(m.sum()),
                           mean=float(tension[m].mean()) if m.any() else None,
                           std=float(tension[m].std()) if m.any() else None,
                           max=float(tension[m].max()) if m.any() else None))
        m = (r >= lo) & (r < hi)
        rows_r.append(dict(lo=lo, hi=min(hi, 1.0), n=int(m.sum()),
                           mean=float(util[m].mean()) if m.any() else None,
                           p99=float(np.percentile(util[m], 99)) if m.any() else None,
                           max=float(util[m].max()) if m.any() else None))
    return rows_d, rows_r, rel, util


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--diameter", type=float, default=0.012)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--fraction", type=float, default=0.8,
                    help="load to this fraction of the axial strain at the first break")
    ap.add_argument("--out", default="results/brazilian_onset")
    a = ap.parse_args(argv)
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    disc = generate("disc", a.diameter, *RADII, seed=a.seed, target_coordination=N_BAR)
    params = rock_params(2, kappa=0.0, c0=10e6)
    big_r = float(disc.info["radius"])
    centre = np.asarray(disc.info["centre"])
    print(f"damping: {DAMPING}", flush=True)
    hist, state = brazilian(disc, params, 0.004, STOP_RATIO)
    fp = lab.failure_pattern(state)
    if len(fp["index"]) == 0:
        raise SystemExit("no bond broke: raise the platen travel")
    first = lab.first_breaks(fp)
    r_first = np.linalg.norm(fp["point"][first] - centre, axis=1) / big_r
    step1 = int(np.min(fp["step"]))
    load = np.asarray(hist["load"])
    # the axial strain when the first bond broke (the ramp makes it non-proportional to the step)
    strain1 = float(np.interp(step1 + 1, np.asarray(hist["step"], np.float64),
                              np.asarray(hist["axial_strain"])))
    pre_strain = a.fraction * strain1
    hist2, pre = brazilian(disc, params, pre_strain, None)
    n_broken = int(np.sum(np.asarray(pre.bonds.broken) & np.asarray(pre.bonds.valid)))
    rows_d, rows_r, points, util = bond_table(pre, centre, big_r,
                                              float(params.bond_tensile))
    info = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="minutes"),
                diameter=a.diameter, seed=a.seed, damping=str(DAMPING),
                first_break_strain=strain1, pre_strain=pre_strain,
                discs=int(np.sum(np.asarray(disc.particles.valid))), first_break_step=step1,
                first_tenth_r_over_R=np.sort(r_first).tolist(),
                pre_state_step=int(pre.step), pre_load_over_peak=float(hist2["load"][-1] / load.max()),
                pre_broken=n_broken, diameter_band=rows_d, by_radius=rows_r,
                wall_s=time.perf_counter() - t0)
    (out / "brazilian_onset.json").write_text(json.dumps(info, indent=1))
    first_points = fp["point"][first] - centre
    with h5py.File(out / "brazilian_onset.h5", "w") as f:
        f["bond_point"], f["bond_utilisation"] = points, util
        f["first_break_point"] = first_points
        f["load"], f["axial_strain"] = load, np.asarray(hist["axial_strain"])
        f.attrs.update({k: v for k, v in info.items() if isinstance(v, (int, float, str))})
    fig, ax = plt.subplots(figsize=(5.5, 5))
    order = np.argsort(util)
    sc = ax.scatter(points[order, 0] / big_r, points[order, 1] / big_r, c=util[order], s=8,
                    cmap="coolwarm", vmin=-1, vmax=1)
    ax.scatter(first_points[:, 0] / big_r, first_points[:, 1] / big_r, s=70, facecolors="none",
               edgecolors="k", label="first tenth of the breaks")
    ax.add_patch(plt.Circle((0, 0), 1.0, fill=False, color="0.5"))
    ax.add_patch(plt.Circle((0, 0), 0.4, fill=False, color="0.5", ls="--"))
    fig.colorbar(sc, ax=ax, label="F_n / (T0 A), tension > 0")
    ax.set_aspect("equal")
    ax.set_xlabel("x / R")
    ax.set_ylabel("y / R (load along y)")
    ax.set_title(f"D = {a.diameter * 1e3:g} mm at {info['pre_load_over_peak']:.0%} of the peak load",
                 fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "brazilian_onset.png", dpi=120)
    plt.close(fig)
    fmt = lambda v, f: "" if v is None else format(v, f)
    text = (f"# Brazilian disc just before the first break\n\n"
            f"`python experiments/brazilian_onset.py --diameter {a.diameter} --fraction {a.fraction}` "
            f"({info['date']}, {info['wall_s']:.0f} s; damping {DAMPING}): {info['discs']} discs; "
            f"the first bond "
            f"breaks at step {step1}; the first tenth of the breaks lie at r / R = "
            f"{', '.join(f'{v:.2f}' for v in np.sort(r_first))}.  State at step {int(pre.step)} "
            f"(load {info['pre_load_over_peak']:.0%} of the peak, {n_broken} bonds broken):\n\n"
            "Bonds within 30 deg of horizontal in the band |x - x_c| < 0.2 R, tensile F_n [N]:\n\n"
            "| \\|y\\| / R | bonds | mean | std | max |\n|---|---|---|---|---|\n"
            + "".join(f"| {r['lo']:.1f}-{r['hi']:.1f} | {r['n']} | {fmt(r['mean'], '.0f')} | "
                      f"{fmt(r['std'], '.0f')} | {fmt(r['max'], '.0f')} |\n" for r in rows_d)
            + "\nEvery intact bond, tensile utilisation F_n / (T0 A):\n\n"
            "| r / R | bonds | mean | 99th percentile | max |\n|---|---|---|---|---|\n"
            + "".join(f"| {r['lo']:.1f}-{r['hi']:.1f} | {r['n']} | {fmt(r['mean'], '.3f')} | "
                      f"{fmt(r['p99'], '.3f')} | {fmt(r['max'], '.3f')} |\n" for r in rows_r))
    (out / "brazilian_onset.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
