#!/usr/bin/env python
"""Lamb problem (001 §3.2, Fig 15, 16): viscous and viscoelastic boundaries
against an extended fixed-boundary model.

    python experiments/lamb.py            # 2.5 m discs, extended model 500 m
    python experiments/lamb.py --small    # 5 m discs, extended model 300 m
    python experiments/lamb.py --out DIR

A 100 m x 100 m half model (symmetry axis on the left, a roller) of equal
discs in a square arrangement (rho = 2500 kg/m^3, c_P = 300 m/s, fixed
rotations, bond nu = 0) is loaded at the top left by F(t) = P0 f(t) of 001
eq 19 (P0 = 450 kN, T0 = 0.5 s; half of it on the half model).  The right and
bottom boundaries are viscous (001 eq 5, beta = 1) or viscoelastic (001 eq 17,
K from eq 14 with E = E_c = rho c_P^2 / 2 as in 001 §3.1, nu = 0, L = 100 m,
alpha_n = 1, alpha_s = 0.5).  The extended solution is the same lattice
500 m x 500 m (300 m with --small) with fixed right and bottom boundaries;
its own reflections reach the monitor after 2 L / c_P (3.3 s, 2 s), so the
comparison stops at 3 s (2 s).  Monitor: the surface disc 10 m from the load.

Writes lamb_displacement.png and lamb.h5 to experiments/results/lamb/ (or
--out) and prints the RMS difference from the extended model and the
permanent displacements.
"""
from __future__ import annotations

import argparse
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jdem.io  # noqa: E402
from jdem import waves  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--small", action="store_true", help="5 m discs, 300 m extended model")
    ap.add_argument("--out", default=None, help="output directory")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out or pathlib.Path(__file__).parent / "results" / "lamb")
    out.mkdir(parents=True, exist_ok=True)
    radius, extended, t_end = (2.5, 300.0, 2.0) if args.small else (1.25, 500.0, 3.0)
    runs = {}
    for kind, size in (("fixed", extended), ("viscous", 100.0), ("viscoelastic", 100.0)):
        t0 = time.perf_counter()
        model = waves.lamb_model(size, radius, boundary=kind, t_end=t_end)
        runs[kind] = waves.run_lamb(model)
        n = int(np.sum(np.asarray(model.state.particles.valid)))
        runs[kind]["wall"] = time.perf_counter() - t0
        print(f"  {kind:12s} {size:5.0f} m: {n} discs, {model.n_steps} steps, "
              f"{runs[kind]['wall']:.1f} s")
    ref = runs["fixed"]
    w = ref["time"] <= t_end
    end = np.nonzero(w)[0][-1]
    peak = np.abs(ref["uy"][w]).max()
    stats = {}
    for kind in ("viscous", "viscoelastic"):
        u = runs[kind]["uy"]
        rms = np.sqrt(np.mean((u[w] - ref["uy"][w]) ** 2)) / np.sqrt(np.mean(ref["uy"][w] ** 2))
        stats[kind] = dict(rms=rms, final=u[end], final_error=abs(u[end] - ref["uy"][end]) / peak)
        print(f"{kind}: RMS difference {rms:.3f}; displacement at {ref['time'][end]:.2f} s "
              f"{u[end] * 1e3:.3f} mm (extended {ref['uy'][end] * 1e3:.3f} mm, "
              f"peak {peak * 1e3:.3f} mm)")
    fig, ax = plt.subplots(figsize=(8, 4.5))
    ax.plot(ref["time"][w], ref["uy"][w] * 1e3, "k-", lw=2, label=f"extended {extended:.0f} m, fixed")
    ax.plot(runs["viscous"]["time"], runs["viscous"]["uy"] * 1e3, "b:",
            label=f"viscous (RMS diff {stats['viscous']['rms']:.1%})")
    ax.plot(runs["viscoelastic"]["time"], runs["viscoelastic"]["uy"] * 1e3, "r--",
            label=f"viscoelastic (RMS diff {stats['viscoelastic']['rms']:.1%})")
    ax.set_xlim(0, t_end)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("vertical displacement [mm]")
    ax.set_title(f"Lamb problem (001 §3.2): monitor 10 m from the load, discs D = {2 * radius:g} m")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "lamb_displacement.png", dpi=120)
    hist = {}
    for kind, r in runs.items():
        hist[f"{kind}_time"] = r["time"]
        hist[f"{kind}_uy"] = r["uy"]
    attrs = dict(disc_diameter=2 * radius, extended_size=extended, t_end=t_end,
                 rms_viscous=float(stats["viscous"]["rms"]),
                 rms_viscoelastic=float(stats["viscoelastic"]["rms"]),
                 wall_time_s=float(sum(r["wall"] for r in runs.values())))
    jdem.io.save_run(out / "lamb.h5", history=hist, attrs=attrs)
    print(f"wrote {out / 'lamb_displacement.png'} and {out / 'lamb.h5'}")


if __name__ == "__main__":
    main()
