#!/usr/bin/env python
"""External-source bar with a viscoelastic boundary (001 §3.1, Fig 14).

    python experiments/viscoelastic_bar.py            # radii 2-3 m (about 2,000 discs)
    python experiments/viscoelastic_bar.py --small    # radii 4-6 m (500 discs)
    python experiments/viscoelastic_bar.py --out DIR

The 1000 m x 50 m bar of 001 Fig 1 (y fixed on every disc), a random packing
with radius ratio 1.5 (Pattern B; the seed's radii are 0.2-0.3 m, these are
scaled up), rho = 2500 kg/m^3, c_P = 1000 m/s.  The P pulse of 001 eq 12
(M = 0.5 m/s, T = 0.5 s) enters through a viscous input boundary on the left
(001 eq 6); the right end is a viscoelastic boundary (001 eq 17) with
K_n from eq 14: E = E_c = rho c_P^2 / 2, nu = 0, L = 1000 m, alpha_n = 2.5.
The calibration factors come from the ratio iteration (001 Fig 5): first the
right end as an absorbing viscous boundary with a velocity-driven left end,
then the left input boundary.  The record is 20 s long.

Writes viscoelastic_bar.png and viscoelastic_bar.h5 to
experiments/results/viscoelastic_bar/ (or --out) and prints the peak and
permanent (end of record) displacement at P1..P5.
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

L, H, RHO, CP = 1000.0, 50.0, 2500.0, 1000.0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--small", action="store_true", help="radii 4-6 m instead of 2-3 m")
    ap.add_argument("--out", default=None, help="output directory")
    ap.add_argument("--t-end", type=float, default=20.0, help="record length [s]")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out or pathlib.Path(__file__).parent / "results" / "viscoelastic_bar")
    out.mkdir(parents=True, exist_ok=True)
    r_min = 4.0 if args.small else 2.0
    t0 = time.perf_counter()
    parts, bonds, porosity = waves.random_packing(L, H, r_min, 1.5 * r_min, seed=1, fix_rotation=True)
    print(f"packing: {int(np.sum(np.asarray(parts.valid)))} discs, porosity {porosity:.3f}")
    driven = waves.bar_model(parts, bonds, length=L, height=H, dt_factor=0.9)
    right = waves.calibrate_ratio(driven)
    print(f"right beta_2P = {right.beta:.4f} after {len(right.history)} runs")
    k = waves.viscoelastic_stiffness(waves.contact_modulus(CP, RHO), 0.0, L, 2.5)
    model = waves.bar_model(parts, bonds, length=L, height=H, dt_factor=0.9, input="viscous",
                         beta_right=right.beta, k_right=k, t_end=args.t_end)
    left = waves.calibrate_ratio(waves.bar_model(parts, bonds, length=L, height=H, dt_factor=0.9,
                                           input="viscous", beta_right=right.beta),
                              boundary="left")
    print(f"left (input) beta_2P = {left.beta:.4f} after {len(left.history)} runs")
    h = waves.run_bar(model, waves.with_betas(model, beta_left=left.beta))
    wall = time.perf_counter() - t0
    d = h["disp"][:, :, 0]
    peak = np.abs(d).max(axis=0)
    permanent = np.abs(d[-1]) / peak
    for j in range(5):
        print(f"P{j + 1}: peak displacement {peak[j] * 1e3:.1f} mm, at {h['time'][-1]:.1f} s "
              f"{d[-1, j] * 1e3:.2f} mm ({permanent[j]:.2%} of the peak)")
    i10 = int(np.searchsorted(h["time"], 10.0))
    print("at 10 s: " + ", ".join(f"{v:.2%}" for v in np.abs(d[min(i10, len(d) - 1)]) / peak))
    print(f"wall time {wall:.0f} s")
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for j in range(5):
        axes[0].plot(h["time"], d[:, j] * 1e3, label=f"P{j + 1} (x = {model.monitor_x[j]:.0f} m)")
        axes[1].plot(h["time"], h["vel"][:, j, 0], label=f"P{j + 1}")
    axes[0].set_ylabel("x displacement [mm]")
    axes[1].set_ylabel("x velocity [m/s]")
    axes[1].set_xlabel("time [s]")
    axes[0].legend(fontsize=8)
    axes[0].set_title("Viscous input left, viscoelastic right (001 §3.1, alpha_n = 2.5)")
    fig.tight_layout()
    fig.savefig(out / "viscoelastic_bar.png", dpi=120)
    jdem.io.save_run(out / "viscoelastic_bar.h5", history=dict(
        time=h["time"], vel=h["vel"], disp=h["disp"], monitor_x=model.monitor_x,
        right_iterations=np.array([[r["beta"], r["m_out"]] for r in right.history]),
        left_iterations=np.array([[r["beta"], r["m_out"]] for r in left.history])),
        attrs=dict(beta_right=right.beta, beta_left=left.beta, k_n=k, r_min=r_min,
                   porosity=porosity, t_end=float(h["time"][-1]), wall_time_s=wall))
    print(f"wrote {out / 'viscoelastic_bar.png'} and {out / 'viscoelastic_bar.h5'}")


if __name__ == "__main__":
    main()
