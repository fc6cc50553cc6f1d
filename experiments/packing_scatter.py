#!/usr/bin/env python
"""How much do packings of the same statistics differ in the differentiable UCS test?

    python experiments/packing_scatter.py                                  # ~100 discs, 8 packings
    python experiments/packing_scatter.py --size 0.007 0.014               # ~330 discs
    python experiments/packing_scatter.py --platen-step 1.25e-9 --ramp-transits 11
    python experiments/packing_scatter.py --out results/packing_scatter

Calibration on one packing recovers the parameters of another packing only as
closely as the two packings agree.  This study runs the calibration's UCS test
(:data:`jdem.lab.UCS` with ``stiffness_margin=2`` and the lab tests' default
smooth damping, run as the pure :func:`jdem.lab.checked_curve`; the set-up of
tests/test_calibrate.py: a 4 mm x 8 mm rectangle, r in [0.2, 0.35] mm, N-bar
4.5, E = 30 GPa, T0 = c0 = 3 MPa, kappa = 0.3 %) with the same parameters on
``--packings`` packings (seeds 0, 1, ...) as one vmapped call, a record every
50 steps, and reports per packing the peak stress, the strain at
the peak and the slope of the curve over four windows of the pre-peak curve
(5-20, 20-40, 40-60, 60-80 % of the peak; the calibration's modulus term uses
10-40 %), with their relative standard deviation over the packings.

``--platen-step`` and ``--ramp-transits`` set the loading (defaults: 5 nm per
step and a ramp of 2.2 wave transits through the specimen, about 8 records of
50 steps on the default 4 mm x 8 mm specimen, where a transit takes ~180 steps:
the set-up of the former differentiable test); a slower step shows how much of
the curve is the loading rate.  ``--ramp-transits 11`` is about the former
40-record ramp.

Writes under ``--out``: ``packing_scatter.png`` (the curves), ``packing_scatter.h5``
(the curves and the per-packing figures; reopen with ``h5py``),
``packing_scatter.json`` (the same as text) and ``packing_scatter.md`` (the table).
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
from jdem.materials import material, rock_params  # noqa: E402
from jdem.specimen import generate  # noqa: E402

TRUE = dict(E=30e9, strength=3e6, kappa=3e-3)
WINDOWS = ((0.05, 0.2), (0.2, 0.4), (0.4, 0.6), (0.6, 0.8))
RECORD_EVERY = 50      # steps per record (one point of the curve)


def slopes(strain, stress):
    """Least-squares slopes [Pa] of the pre-peak curve over ``WINDOWS`` (fractions
    of the peak); NaN where a window holds fewer than two records."""
    k = int(np.argmax(stress))
    e, s = strain[:k + 1], stress[:k + 1]
    out = []
    for lo, hi in WINDOWS:
        sel = (s >= lo * stress[k]) & (s <= hi * stress[k])
        out.append(float(np.polyfit(e[sel], s[sel], 1)[0]) if sel.sum() >= 2 else float("nan"))
    return out


def rel_std(a):
    a = np.asarray(a, float)
    return float(np.nanstd(a, ddof=1) / np.nanmean(a))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=float, nargs=2, default=(0.004, 0.008), metavar=("W", "H"))
    ap.add_argument("--radii", type=float, nargs=2, default=(0.2e-3, 0.35e-3))
    ap.add_argument("--coordination", type=float, default=4.5)
    ap.add_argument("--packings", type=int, default=8)
    ap.add_argument("--platen-step", type=float, default=5e-9, help="[m per step]")
    ap.add_argument("--ramp-transits", type=float, default=2.2,
                    help="wave transits over which the platen speeds up")
    ap.add_argument("--max-strain", type=float, default=2.2e-3)
    ap.add_argument("--out", default="results/packing_scatter")
    a = ap.parse_args(argv)
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    specs = [generate("rectangle", tuple(a.size), *a.radii, seed=s,
                      target_coordination=a.coordination) for s in range(a.packings)]
    t_gen = time.perf_counter() - t0
    setup = lab.UCS.setup(specs, rock_params(2, kappa=TRUE["kappa"]), platen_step=a.platen_step,
                          max_strain=a.max_strain, ramp_transits=a.ramp_transits,
                          record_every=RECORD_EVERY, stiffness_margin=2.0)
    params = setup.params
    print(f"{setup}, ramp {setup.plan.ramp_records} records", flush=True)
    t0 = time.perf_counter()   # one parameter set, broadcast to every packing
    hist, setup = lab.checked_curve(setup, material(params, TRUE))
    t_run = time.perf_counter() - t0
    curve = dict(strain=hist["axial_strain"], stress=hist["axial_stress"])

    rows = []
    for m, sp in enumerate(specs):
        e, s = np.asarray(curve["strain"][m]), np.asarray(curve["stress"][m])
        k = int(np.argmax(s))
        rows.append(dict(seed=m, discs=int(np.sum(np.asarray(sp.particles.valid))),
                         coordination=float(sp.coordination), porosity=float(sp.porosity),
                         peak_stress=float(s[k]), peak_strain=float(e[k]),
                         slopes=slopes(e, s), final_over_peak=float(s[-1] / s[k])))
    peak = [r["peak_stress"] for r in rows]
    summary = dict(peak_stress=rel_std(peak), peak_strain=rel_std([r["peak_strain"] for r in rows]),
                   **{f"slope_{int(lo * 100)}_{int(hi * 100)}": rel_std([r["slopes"][w] for r in rows])
                      for w, (lo, hi) in enumerate(WINDOWS)})
    info = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="minutes"),
                size=list(a.size), radii=list(a.radii), coordination=a.coordination,
                platen_step=a.platen_step, ramp_transits=a.ramp_transits,
                ramp_records=int(setup.plan.ramp_records), max_strain=a.max_strain,
                damping=str(setup.plan.damping),
                dt=float(params.dt), steps=int(setup.plan.n_records * setup.plan.record_every),
                true=TRUE, generation_s=t_gen, run_s=t_run, rows=rows, rel_std=summary,
                strain=np.asarray(curve["strain"]).tolist(), stress=np.asarray(curve["stress"]).tolist())
    (out / "packing_scatter.json").write_text(json.dumps(info, indent=1))
    with h5py.File(out / "packing_scatter.h5", "w") as f:
        f["strain"], f["stress"] = np.asarray(curve["strain"]), np.asarray(curve["stress"])
        for key in ("seed", "discs", "coordination", "porosity", "peak_stress", "peak_strain",
                    "slopes", "final_over_peak"):
            f[key] = np.asarray([r[key] for r in rows])
        f["slope_windows"] = np.asarray(WINDOWS)
        f.attrs.update({k: v for k, v in info.items() if isinstance(v, (int, float, str))})
    fig, ax = plt.subplots(figsize=(6, 4))
    for m in range(a.packings):
        ax.plot(np.asarray(curve["strain"][m]) * 100, np.asarray(curve["stress"][m]) / 1e6,
                lw=1, label=f"seed {m}")
    ax.set_xlabel("axial strain [%]")
    ax.set_ylabel("axial stress [MPa]")
    ax.set_title(f"{a.packings} packings, {a.size[0] * 1e3:g} x {a.size[1] * 1e3:g} mm, "
                 f"platen step {a.platen_step:g} m", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "packing_scatter.png", dpi=120)
    plt.close(fig)

    head = (f"# Packing scatter of the differentiable UCS test\n\n"
            f"`python experiments/packing_scatter.py --size {a.size[0]} {a.size[1]} "
            f"--platen-step {a.platen_step} --ramp-transits {a.ramp_transits} --packings {a.packings}` "
            f"({info['date']}; {info['steps']} steps of {info['dt']:.3g} s, ramp "
            f"{info['ramp_records']} records, damping {info['damping']}; generation "
            f"{t_gen:.0f} s, run {t_run:.0f} s)\n\n"
            "| seed | discs | N-bar | peak MPa | peak strain 1e-6 | slope 5-20 % GPa | 20-40 % | "
            "40-60 % | 60-80 % |\n|---|---|---|---|---|---|---|---|---|\n")
    lines = [f"| {r['seed']} | {r['discs']} | {r['coordination']:.2f} | {r['peak_stress'] / 1e6:.2f} | "
             f"{r['peak_strain'] * 1e6:.0f} | " + " | ".join(f"{x / 1e9:.1f}" for x in r["slopes"]) + " |"
             for r in rows]
    lines.append("| rel. std | | | " + f"{summary['peak_stress']:.1%} | {summary['peak_strain']:.1%} | "
                 + " | ".join(f"{summary[k]:.1%}" for k in summary if k.startswith("slope")) + " |")
    text = head + "\n".join(lines) + "\n"
    (out / "packing_scatter.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
