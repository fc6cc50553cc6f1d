#!/usr/bin/env python
"""Strain-energy ratio lambda vs mean coordination number N-bar (002 §1.4, Fig. 8-9).

    python experiments/coordination_study.py --small     # ~2 cm block, ~450 discs per specimen
    python experiments/coordination_study.py             # the seed's 10 cm block (hours)

A 2D block between a fixed bottom platen and a top platen servo-controlled to
1 MPa (free sides), E = 30 GPa, nu = 0.3, rho = 2500 kg/m^3 (002 §1.4), purely
elastic bonds (strengths 1 GPa, so that nothing yields).  At rest,

    lambda = L_p / L_e,   L_p = bond strain energy (002 eq 16),
    L_e = (1 - nu^2) sigma^2 V / (2E)   (plane strain: the seed's FE energy,
          0.151 J for 10 cm x 10 cm, is the plane-strain value 0.1517 J).

Different N-bar come from ``jdem.specimen.specimen_for_coordination`` (the
packing's density and the bonding gap tolerance; the seed varied particle
number, radius, arrangement, size spread and embedding), here for two radius
spreads.  ``jdem.lab.energy.coordination_energy_ratio`` gives lambda for the
whole block and ``lambda_core`` for the bulk only (bonds farther than 0.2 H
from the platens): a random packing touches a flat platen at a few discs, and
on a small block the seating of the others adds energy near the platens.

Damping: the seed's local non-viscous damping, alpha = 0.8 (000 eq 3-19,
``jdem.lab.local(0.8)``, 002 §1.4), passed explicitly (the lab tests' default
is the smooth damping ``jdem.lab.smooth()``).

Fits lambda = a N-bar^b (least squares in log-log) to both and compares with
the seed's lambda = 60.5 N-bar^-2.54 (002 eq 17; lambda = 1 at N-bar = 5.04).
Writes ``lambda_vs_coordination.png``, ``coordination_study.h5`` (every
specimen's figures; ``jdem.io.save_run``) and ``summary.json`` to ``--out``.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jdem.io  # noqa: E402
from jdem import InputError  # noqa: E402
from jdem import lab  # noqa: E402
from jdem.lab.energy import coordination_energy_ratio  # noqa: E402
from jdem.materials import rock_params  # noqa: E402
from jdem.specimen import specimen_for_coordination  # noqa: E402

SEED_A, SEED_B = 60.5, -2.54
FULL = dict(size=(0.10, 0.10), spreads=((0.6e-3, 0.85e-3), (0.45e-3, 1.0e-3)),
            targets=(3.6, 4.0, 4.4, 4.8, 5.2, 5.6))
SMALL = dict(size=(0.02, 0.02), spreads=((0.4e-3, 0.6e-3), (0.3e-3, 0.7e-3)),
             targets=(3.6, 4.0, 4.4, 4.8, 5.2, 5.6))
STRESS = 1e6
DAMPING = lab.local(0.8)    # the seed's local damping, not the lab default smooth()


def power_fit(n_bar, lam):
    """(a, b, r) of lambda = a N^b by least squares on log lambda vs log N;
    r = the correlation coefficient of the logs."""
    x, y = np.log(np.asarray(n_bar)), np.log(np.asarray(lam))
    b, log_a = np.polyfit(x, y, 1)
    r = float(np.corrcoef(x, y)[0, 1]) if len(x) > 2 else float("nan")
    return float(np.exp(log_a)), float(b), r


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--small", action="store_true", help="2 cm x 2 cm blocks (~450 discs)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    small = args.small or os.environ.get("JDEM_SMALL") == "1"
    setup = SMALL if small else FULL
    out = pathlib.Path(args.out or ("results/coordination_study" + ("_small" if small else "")))
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    params = rock_params(2, E=30e9, nu=0.3, T0=1e9, c0=1e9, kappa=1e-2, local_damping=0.8)
    print(f"  damping: {DAMPING}")
    rows, failed = [], []
    for s_i, (r_lo, r_hi) in enumerate(setup["spreads"]):
        for target in setup["targets"]:
            t1 = time.time()
            try:
                sp = specimen_for_coordination(target, "rectangle", setup["size"], r_lo, r_hi,
                                               seed=args.seed + s_i)
            except InputError as e:
                failed.append(dict(spread=[r_lo, r_hi], target=target, error=str(e)))
                print(f"  r in [{r_lo * 1e3:g}, {r_hi * 1e3:g}] mm, target N-bar {target}: "
                      f"not reached ({e})")
                continue
            res = coordination_energy_ratio(sp, params, stress=STRESS, damping=DAMPING)
            row = dict(spread=s_i, r_min=r_lo, r_max=r_hi, target=target,
                       n_bar=float(sp.coordination), n_particles=res["n_particles"],
                       n_bonds=res["n_bonds"], porosity=float(sp.porosity),
                       gap_tolerance=float(sp.info["gap_tolerance"]), lam=res["lam"],
                       lam_core=res["lam_core"], L_p=res["L_p"], L_e=res["L_e"],
                       E_macro=res["E_macro"], converged=bool(res["converged"]),
                       steps=res["steps"], seconds=time.time() - t1)
            rows.append(row)
            print(f"  r in [{r_lo * 1e3:g}, {r_hi * 1e3:g}] mm: N-bar {row['n_bar']:.2f} "
                  f"({row['n_particles']} discs, porosity {row['porosity']:.3f}): lambda "
                  f"{row['lam']:.3f}, bulk {row['lam_core']:.3f}, E_macro "
                  f"{row['E_macro'] / 1e9:.1f} GPa  ({row['seconds']:.0f} s)")
    if len(rows) < 2:
        print("too few specimens for a fit")
        return 1
    n_bar = np.array([r["n_bar"] for r in rows])
    lam = np.array([r["lam"] for r in rows])
    lam_core = np.array([r["lam_core"] for r in rows])
    fit = power_fit(n_bar, lam)
    fit_core = power_fit(n_bar, lam_core)
    n5 = lambda f: f[0] * 5.0 ** f[1]
    wall = time.time() - t0

    fig, ax = plt.subplots(figsize=(6, 4.4))
    xs = np.linspace(min(n_bar.min(), 3.5) * 0.97, max(n_bar.max(), 5.8) * 1.03, 100)
    for s_i in range(len(setup["spreads"])):
        sel = np.array([r["spread"] == s_i for r in rows])
        if sel.any():
            lo, hi = setup["spreads"][s_i]
            ax.plot(n_bar[sel], lam[sel], "o", color=f"C{s_i}",
                    label=f"λ, r ∈ [{lo * 1e3:g}, {hi * 1e3:g}] mm")
            ax.plot(n_bar[sel], lam_core[sel], "^", mfc="none", color=f"C{s_i}",
                    label="λ bulk (> 0.2 H from the platens)")
    ax.plot(xs, fit[0] * xs ** fit[1], "k-", lw=1,
            label=f"fit λ = {fit[0]:.3g} N̄^{fit[1]:.2f}")
    ax.plot(xs, fit_core[0] * xs ** fit_core[1], "k:", lw=1,
            label=f"fit bulk λ = {fit_core[0]:.3g} N̄^{fit_core[1]:.2f}")
    ax.plot(xs, SEED_A * xs ** SEED_B, "r--", lw=1, label="002 eq 17: 60.5 N̄^-2.54")
    ax.axhline(1.0, color="gray", lw=0.6)
    ax.set_xlabel("mean coordination number N̄")
    ax.set_ylabel("λ = L_p / L_e")
    ax.set_title("strain-energy ratio vs coordination (002 Fig. 9)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "lambda_vs_coordination.png", dpi=130)
    plt.close(fig)

    summary = dict(small=small, size=list(setup["size"]), stress=STRESS,
                   damping=str(DAMPING), rows=rows,
                   failed=failed, fit=dict(a=fit[0], b=fit[1], r=fit[2], lam_at_5=n5(fit)),
                   fit_core=dict(a=fit_core[0], b=fit_core[1], r=fit_core[2],
                                 lam_at_5=n5(fit_core)),
                   seed_fit=dict(a=SEED_A, b=SEED_B, lam_at_5=SEED_A * 5.0 ** SEED_B),
                   wall_s=wall)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    hist = {k: np.asarray([r[k] for r in rows]) for k in
            ("n_bar", "lam", "lam_core", "L_p", "L_e", "E_macro", "n_particles", "n_bonds",
             "porosity", "gap_tolerance", "target", "r_min", "r_max", "steps")}
    jdem.io.save_run(out / "coordination_study.h5", history=hist,
                     attrs={"what": "002 §1.4 lambda vs N-bar", "fit_a": fit[0], "fit_b": fit[1],
                            "fit_core_a": fit_core[0], "fit_core_b": fit_core[1],
                            "wall_s": wall, "stress": STRESS, "damping": str(DAMPING)})
    print(f"\n  fit      lambda = {fit[0]:.3g} N^{fit[1]:.2f} (r = {fit[2]:.3f}); "
          f"lambda(5) = {n5(fit):.3f}")
    print(f"  bulk fit lambda = {fit_core[0]:.3g} N^{fit_core[1]:.2f} (r = {fit_core[2]:.3f}); "
          f"lambda(5) = {n5(fit_core):.3f}")
    print(f"  seed     lambda = 60.5 N^-2.54; lambda(5) = {SEED_A * 5.0 ** SEED_B:.3f}")
    print(f"  wall time {wall:.0f} s -> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
