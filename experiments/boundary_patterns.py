#!/usr/bin/env python
"""Disc patterns at a viscous boundary (001 §2.3.1, Fig 10-12): Pattern A
(equal discs, square), Pattern B (random, radius ratio 1.5 and 2.0) and
Pattern C (random interior, equal discs along the boundaries).

    python experiments/boundary_patterns.py            # mean radius 2.5 m (about 2,000 discs)
    python experiments/boundary_patterns.py --small    # mean radius 5 m (about 500 discs)
    python experiments/boundary_patterns.py --out DIR

The 1000 m x 50 m P-wave bar of 001 Fig 1 (jdem.waves.bar_model: y fixed,
left end driven by the pulse of 001 eq 12, M = 0.5 m/s, T = 0.5 s; right end
viscous, 001 eq 4; no damping, unbreakable bonds, rotations fixed) on four
packings of one mean radius, as 001 Fig 10 (the seed: mean 0.5 m; here 5x or
10x larger, the pulse is still 500 m long):

* A: equal discs in a square arrangement;
* B 1.5 / B 2.0: radii uniform with r_max / r_min = 1.5 and 2.0;
* C: a B 1.5 interior between columns of equal discs at both ends
  (jdem.waves.edge_packing).  The seed's edge discs are 1.04 x the interior's
  mean radius; here they equal it, so that the 50 m height holds a whole
  number of them.

For each pattern with beta_2P = 1: the widths D of the right-boundary discs
along the boundary (001 Fig 11) and each disc's peak x velocity (001 Fig 12),
their mean and spread; then the ratio iteration (001 Fig 5) on the peak of the
boundary discs' mean velocity (P5, calibrate_ratio), and the largest |v_x| at P3 after the incident
pulse (jdem.waves.reflection; on a random packing this includes the medium's
own scattering, see experiments/pwave_bar.py) before and after it.

Writes boundary_patterns.png, boundary_patterns.h5 and results.md to
experiments/results/boundary_patterns/ (or --out) and prints the table.
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

L, H, RHO = 1000.0, 50.0, 2500.0
PATTERNS = ("A", "B 1.5", "B 2.0", "C")


def packing(name, r_mean, seed):
    """Particles, bonds and a one-line description of pattern ``name``."""
    if name == "A":
        pos, rad = waves.square_packing(int(L / (2 * r_mean)), int(H / (2 * r_mean)), r_mean)
        parts, bonds = waves.lattice(pos, rad, waves.square_density(RHO), fix_rotation=True)
        return parts, bonds, "square, equal discs"
    if name == "C":
        r_min = 2.0 * r_mean / 2.5
        parts, bonds, phi, _ = waves.edge_packing(L, H, r_min, 1.5 * r_min, r_mean, seed=seed,
                                                  fix_rotation=True)
        return parts, bonds, f"random interior (ratio 1.5), edge discs r = {r_mean:g} m, n = {phi:.3f}"
    ratio = float(name.split()[1])
    r_min = 2.0 * r_mean / (1.0 + ratio)
    parts, bonds, phi = waves.random_packing(L, H, r_min, ratio * r_min, seed=seed,
                                             fix_rotation=True)
    return parts, bonds, f"random, radii {r_min:.3g}-{ratio * r_min:.3g} m, n = {phi:.3f}"


def one_pattern(name, r_mean, seed, log=print):
    t0 = time.perf_counter()
    parts, bonds, desc = packing(name, r_mean, seed)
    model = waves.with_boundary_monitors(
        waves.bar_model(parts, bonds, length=L, height=H, dt_factor=0.9))
    right = model.conditions.boundaries[1]
    y = np.asarray(parts.pos)[right.index, 1]
    h1 = waves.run_bar(model)
    disc_peaks = np.max(h1["vel"][:, 5:, 0], axis=0)
    r1 = waves.reflection(h1, model)
    cal = waves.calibrate_ratio(model, beta0=1.0)
    hc = waves.run_bar(model, waves.with_betas(model, beta_right=cal.beta))
    rc = waves.reflection(hc, model)
    out = dict(
        name=name, description=desc, n=int(np.sum(np.asarray(parts.valid))),
        n_bonds=int(np.sum(np.asarray(bonds.valid))), n_boundary=len(right.index),
        sum_d=float(np.sum(right.width)), y=y, width=np.asarray(right.width),
        disc_peaks=disc_peaks, peak_mean=float(disc_peaks.mean()),
        peak_cv=float(disc_peaks.std() / disc_peaks.mean()),
        m_out=waves.peak(h1, 4), p3_beta1=r1["ratio"], beta=cal.beta, runs=len(cal.history),
        converged=cal.converged, p3_calibrated=rc["ratio"], time=h1["time"],
        p3_vel_beta1=h1["vel"][:, 2, 0], p3_vel_calibrated=hc["vel"][:, 2, 0],
        wall_s=time.perf_counter() - t0)
    log(f"{name:6s} {out['n']:5d} discs, {out['n_boundary']:3d} boundary discs (sum D "
        f"{out['sum_d']:.1f} m): disc peaks {disc_peaks.min():.4f}-{disc_peaks.max():.4f} m/s "
        f"(mean {out['peak_mean']:.4f}, CV {out['peak_cv']:.2%}); P5 {out['m_out']:.4f}; "
        f"P3 after the pulse {r1['ratio']:.2%}; ratio iteration beta = {cal.beta:.4f} "
        f"({out['runs']} runs), P3 then {rc['ratio']:.2%}  [{out['wall_s']:.0f} s]")
    return out


def figure(res, path):
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    for r in res:
        axes[0].plot(r["y"], r["width"] / 2, "o-", ms=3, label=r["name"])
        axes[1].plot(r["y"], r["disc_peaks"], "o-", ms=3,
                     label=f"{r['name']} (CV {r['peak_cv']:.1%})")
        axes[2].plot(r["time"], r["p3_vel_beta1"], lw=1, label=f"{r['name']}, beta = 1")
    axes[0].set(xlabel="y along the right boundary [m]", ylabel="radius [m]",
                title="Boundary disc radii (001 Fig 11)")
    axes[1].axhline(0.5, color="k", lw=0.8, ls=":")
    axes[1].set(xlabel="y along the right boundary [m]", ylabel="peak v_x [m/s]",
                title="Boundary disc peak velocity, beta = 1 (001 Fig 12)")
    axes[2].set(xlabel="time [s]", ylabel="v_x at P3 [m/s]", title="Middle of the bar (P3)")
    for ax in axes:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def note(res, args, wall):
    rows = "\n".join(
        f"| {r['name']} | {r['n']} | {r['n_boundary']} | {r['sum_d']:.1f} | "
        f"{r['disc_peaks'].min():.4f}-{r['disc_peaks'].max():.4f} | {r['peak_mean']:.4f} | "
        f"{r['peak_cv']:.2%} | {r['p3_beta1']:.2%} | {r['beta']:.4f} ({r['runs']}) | "
        f"{r['p3_calibrated']:.2%} |" for r in res)
    cmd = "python experiments/boundary_patterns.py" + (" --small" if args.small else "")
    return f"""# Disc patterns at a viscous boundary (001 §2.3.1, Fig 10-12) — results note

Command: `{cmd}` (wall time {wall:.0f} s).  1000 m x 50 m P bar, mean radius {args.r_mean:g} m,
seed {args.seed}, float64; packings: {"; ".join(f"{r['name']}: {r['description']}" for r in res)}.

| pattern | discs | boundary discs | sum D [m] | disc peaks, beta = 1 [m/s] | mean | CV | P3 after pulse, beta = 1 | ratio-iterated beta (runs) | P3 after pulse, calibrated |
| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |
{rows}

The input peak is 0.5 m/s.  "P3 after pulse" is the largest |v_x| in the middle of the bar
after the incident pulse over the incident peak (jdem.waves.reflection); on the random
packings it includes the medium's own scattering (experiments/results/pwave_bar).
"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--small", action="store_true", help="mean radius 5 m (about 500 discs)")
    ap.add_argument("--seed", type=int, default=1, help="packing seed")
    ap.add_argument("--out", default=None, help="output directory")
    args = ap.parse_args(argv)
    args.r_mean = 5.0 if args.small else 2.5
    out = pathlib.Path(args.out or pathlib.Path(__file__).parent / "results" / "boundary_patterns")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    res = [one_pattern(name, args.r_mean, args.seed) for name in PATTERNS]
    wall = time.perf_counter() - t0
    figure(res, out / "boundary_patterns.png")
    hist, attrs = {}, dict(r_mean=args.r_mean, seed=args.seed, wall_time_s=wall)
    for r in res:
        key = r["name"].replace(" ", "").replace(".", "")
        for field in ("y", "width", "disc_peaks", "time", "p3_vel_beta1", "p3_vel_calibrated"):
            hist[f"{key}_{field}"] = r[field]
        for field in ("n", "n_bonds", "n_boundary", "sum_d", "peak_mean", "peak_cv", "m_out",
                      "p3_beta1", "beta", "runs", "converged", "p3_calibrated"):
            attrs[f"{key}_{field}"] = r[field]
    jdem.io.save_run(out / "boundary_patterns.h5", history=hist, attrs=attrs)
    (out / "results.md").write_text(note(res, args, wall))
    print(f"wall time {wall:.0f} s; wrote {out}")


if __name__ == "__main__":
    main()
