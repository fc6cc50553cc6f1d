#!/usr/bin/env python
"""Strain-energy ratio lambda vs mean coordination number N-bar (002 §1.4, Fig. 8-9).

    python experiments/coordination_study.py --small     # ~2 cm block, ~450 discs per specimen
    python experiments/coordination_study.py             # the seed's 10 cm block (hours)
    python experiments/coordination_study.py --targets 4.8 --spreads 0   # one 10 cm block

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
from the faces).

Every specimen is loaded four ways: with steel plates bonded to its faces (002
Fig 7: ``jdem.specimen.add_plates``, two rows of discs, E = 200 GPa, bonded to
every rock disc within a mean radius of the face) or between rigid platens (a
random packing touches them at a few discs, and the seating of the others adds
energy near the platens), each with the seed's circular bending section (002
eq 5) and with the unit-thickness slab (``Config.bond_section``).

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
import functools
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
from jdem.specimen import add_plates, embed, generate, specimen_for_coordination  # noqa: E402
from jdem.specimen.bonding import gap_for_coordination, near_pairs  # noqa: E402

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


LOADINGS = ("plates", "rigid")
SECTIONS = ("circular", "slab")
MARKERS = {("plates", "circular"): "o", ("plates", "slab"): "s",
           ("rigid", "circular"): "^", ("rigid", "slab"): "v"}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--small", action="store_true", help="2 cm x 2 cm blocks (~450 discs)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--targets", type=float, nargs="+", default=None,
                    help="N-bar targets (default: 3.6 to 5.6 by 0.4)")
    ap.add_argument("--spreads", type=int, nargs="+", default=None,
                    help="which radius spreads to run, by index (default: all)")
    ap.add_argument("--max-gap", type=float, default=0.5,
                    help="largest bonding gap tolerance / mean radius (default 0.5); more "
                         "reaches a higher N-bar, like the seed's embedding")
    ap.add_argument("--vary", choices=("gap", "size", "porosity", "embedding"), default="gap",
                    help="how N-bar is varied: the bonding gap tolerance to reach each "
                         "target (default); the disc size at a fixed gap of 0.2 mean radius "
                         "(the particle count, the seed's case 1); the packing's porosity at "
                         "that gap (looser packings); the embedding at that gap (every "
                         "radius grown at fixed centres, jdem.specimen.embed: denser than "
                         "touching discs, as the seed's blocks)")
    ap.add_argument("--loadings", nargs="+", choices=LOADINGS, default=list(LOADINGS))
    ap.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    args = ap.parse_args(argv)
    small = args.small or os.environ.get("JDEM_SMALL") == "1"
    setup = dict(SMALL if small else FULL)
    if args.targets:
        setup["targets"] = tuple(args.targets)
    if args.spreads:
        setup["spreads"] = tuple(setup["spreads"][i] for i in args.spreads)
    out = pathlib.Path(args.out or ("results/coordination_study" + ("_small" if small else "")))
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    params = {loading: rock_params(2, E=30e9, nu=0.3, T0=1e9, c0=1e9, kappa=1e-2,
                                   local_damping=0.8,
                                   plate_youngs=200e9 if loading == "plates" else None)
              for loading in LOADINGS}
    print(f"  damping: {DAMPING}")
    rows, failed = [], []
    for s_i, r_lo, r_hi, target, make in specimen_jobs(args, setup):
        t1 = time.time()
        try:
            sp = make()
        except InputError as e:
            failed.append(dict(spread=[r_lo, r_hi], target=target, error=str(e)))
            print(f"  r in [{r_lo * 1e3:g}, {r_hi * 1e3:g}] mm, target {target}: "
                  f"not reached ({e})")
            continue
        specimens = {"plates": add_plates(sp), "rigid": sp}
        for loading in args.loadings:
            for section in args.sections:
                t2 = time.time()
                res = coordination_energy_ratio(specimens[loading], params[loading],
                                                stress=STRESS, damping=DAMPING,
                                                bond_section=section)
                row = dict(spread=s_i, r_min=r_lo, r_max=r_hi, target=target,
                           way=args.vary, loading=loading, section=section,
                           n_bar=float(sp.coordination), n_particles=res["n_particles"],
                           area_fraction=float(sp.info.get("area_fraction", 1.0 - sp.porosity)),
                           n_bonds=res["n_bonds"], porosity=float(sp.porosity),
                           gap_tolerance=float(sp.info["gap_tolerance"]), lam=res["lam"],
                           lam_core=res["lam_core"], L_p=res["L_p"], L_e=res["L_e"],
                           L_p_loading=res["L_p_loading"], E_macro=res["E_macro"],
                           converged=bool(res["converged"]), steps=res["steps"],
                           seconds=time.time() - t2)
                rows.append(row)
                print(f"  r in [{r_lo * 1e3:g}, {r_hi * 1e3:g}] mm: N-bar "
                      f"{row['n_bar']:.2f} ({n_rock(sp)} discs, area fraction "
                      f"{row['area_fraction']:.3f}), {loading:6s} {section:8s}: lambda "
                      f"{row['lam']:.3f}, bulk {row['lam_core']:.3f}  "
                      f"({row['seconds']:.0f} s)", flush=True)
        print(f"    specimen done in {time.time() - t1:.0f} s", flush=True)
    if not rows:
        print("no specimen reached its target")
        return 1
    fits = {}
    if len({r["n_bar"] for r in rows}) < 2:
        print("one N-bar only: figures without a fit")
    else:
        for key in [k for k in MARKERS if k[0] in args.loadings and k[1] in args.sections]:
            sel = [r for r in rows if (r["loading"], r["section"]) == key]
            n_bar = np.array([r["n_bar"] for r in sel])
            fits[key] = dict(lam=power_fit(n_bar, [r["lam"] for r in sel]),
                             core=power_fit(n_bar, [r["lam_core"] for r in sel]))
    n5 = lambda f: f[0] * 5.0 ** f[1]
    wall = time.time() - t0

    all_n = np.array([r["n_bar"] for r in rows])
    xs = np.linspace(min(all_n.min(), 3.5) * 0.97, max(all_n.max(), 5.8) * 1.03, 100)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), sharey=True)
    for ax, what, title in ((axes[0], "lam", "whole block"),
                            (axes[1], "lam_core", "bulk (> 0.2 H from the faces)")):
        for c, key in enumerate(MARKERS):
            sel = [r for r in rows if (r["loading"], r["section"]) == key]
            if not sel:
                continue
            f = fits[key]["lam" if what == "lam" else "core"] if fits else None
            ax.plot([r["n_bar"] for r in sel], [r[what] for r in sel], MARKERS[key],
                    color=f"C{c}", mfc="none" if key[1] == "slab" else None,
                    label=f"{key[0]}, {key[1]}" + (f": {f[0]:.3g} N̄^{f[1]:.2f}" if f else ""))
            if f:
                ax.plot(xs, f[0] * xs ** f[1], "-", color=f"C{c}", lw=0.8)
        ax.plot(xs, SEED_A * xs ** SEED_B, "k--", lw=1.2, label="002 eq 17: 60.5 N̄^-2.54")
        ax.axhline(1.0, color="gray", lw=0.6)
        ax.set_xlabel("mean coordination number N̄")
        ax.set_title(f"λ = L_p / L_e, {title}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0].set_ylabel("λ")
    fig.suptitle("strain-energy ratio vs coordination (002 Fig. 9), "
                 f"{setup['size'][0] * 100:g} cm block, 1 MPa", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "lambda_vs_coordination.png", dpi=130)
    plt.close(fig)

    fit_table = {f"{k[0]}_{k[1]}": dict(a=v["lam"][0], b=v["lam"][1], r=v["lam"][2],
                                        lam_at_5=n5(v["lam"]), core_a=v["core"][0],
                                        core_b=v["core"][1], core_lam_at_5=n5(v["core"]))
                 for k, v in fits.items()}
    summary = dict(small=small, size=list(setup["size"]), stress=STRESS, max_gap=args.max_gap,
                   damping=str(DAMPING), rows=rows, failed=failed, fits=fit_table,
                   seed_fit=dict(a=SEED_A, b=SEED_B, lam_at_5=SEED_A * 5.0 ** SEED_B),
                   wall_s=wall)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    hist = {k: np.asarray([r[k] for r in rows]) for k in
            ("n_bar", "lam", "lam_core", "L_p", "L_e", "L_p_loading", "E_macro",
             "n_particles", "n_bonds", "porosity", "area_fraction", "gap_tolerance", "r_min",
             "r_max",
             "steps")}
    hist["target"] = np.asarray([str(r["target"]) for r in rows], dtype="S24")
    hist["loading"] = np.asarray([r["loading"] for r in rows], dtype="S8")
    hist["section"] = np.asarray([r["section"] for r in rows], dtype="S8")
    jdem.io.save_run(out / "coordination_study.h5", history=hist,
                     attrs={"what": "002 §1.4 lambda vs N-bar", "wall_s": wall,
                            "stress": STRESS, "damping": str(DAMPING),
                            "fits": json.dumps(fit_table)})
    print()
    for key, v in fits.items():
        f, fc = v["lam"], v["core"]
        print(f"  {key[0]:6s} {key[1]:8s} lambda = {f[0]:.3g} N^{f[1]:.2f} (r = {f[2]:.3f}), "
              f"lambda(5) = {n5(f):.3f}; bulk {fc[0]:.3g} N^{fc[1]:.2f}, "
              f"lambda(5) = {n5(fc):.3f}")
    print(f"  seed            lambda = 60.5 N^-2.54; lambda(5) = {SEED_A * 5.0 ** SEED_B:.3f}")
    print(f"  wall time {wall:.0f} s -> {out}")
    return 0


def specimen_jobs(args, setup):
    """``(spread index, r_min, r_max, target, make)`` per specimen; ``make()``
    builds it.  ``--vary gap``: each N-bar target of each radius spread, by the
    gap tolerance (up to ``--max-gap`` mean radii).  ``--vary size``: the first
    spread scaled to mean radii ``SIZE_SCALES`` x its own (the particle count
    changes, the area fraction does not), bonded at a gap of ``FIXED_GAP`` mean
    radius.  ``--vary porosity``: the first spread packed at ``POROSITIES``,
    bonded at that gap.  ``--vary embedding``: the first spread's densest packing
    with every radius grown by ``EMBEDDINGS`` at fixed centres
    (:func:`jdem.specimen.embed`), bonded at that gap of the grown mean radius;
    with ``--targets``, grown by the last of ``EMBEDDINGS`` and bonded at the gap
    (up to ``--max-gap`` grown mean radii) that brings N-bar to each target."""
    jobs = []
    if args.vary == "gap":
        for s_i, (r_lo, r_hi) in enumerate(setup["spreads"]):
            for target in setup["targets"]:
                make = (lambda t=target, lo=r_lo, hi=r_hi, k=s_i: specimen_for_coordination(
                    t, "rectangle", setup["size"], lo, hi, seed=args.seed + k,
                    max_gap_tolerance=args.max_gap * 0.5 * (lo + hi)))
                jobs.append((s_i, r_lo, r_hi, target, make))
        return jobs
    r_lo, r_hi = setup["spreads"][0]
    if args.vary == "size":
        for scale in SIZE_SCALES:
            lo, hi = r_lo * scale, r_hi * scale
            make = (lambda lo=lo, hi=hi: generate(
                "rectangle", setup["size"], lo, hi, seed=args.seed,
                gap_tolerance=FIXED_GAP * 0.5 * (lo + hi)))
            jobs.append((0, lo, hi, f"mean radius x {scale:g}", make))
    elif args.vary == "embedding":
        @functools.cache
        def packing():                     # one packing for every scale
            return generate("rectangle", setup["size"], r_lo, r_hi, seed=args.seed,
                            gap_tolerance=FIXED_GAP * 0.5 * (r_lo + r_hi))

        def embedded(scale):
            return embed(packing(), scale)

        if args.targets:       # the highest embedding, the gap chosen for each target
            def embedded_for(target, scale=EMBEDDINGS[-1]):
                pos = np.asarray(packing().particles.pos, np.float64)
                rad = scale * np.asarray(packing().particles.radius, np.float64)
                max_gap = args.max_gap * float(rad.mean())
                gap, _, _, _ = gap_for_coordination(target, *near_pairs(pos, rad, max_gap),
                                                    rad.size, "keep", max_gap)
                return embed(packing(), scale, gap_tolerance=gap)

            for target in args.targets:
                s = EMBEDDINGS[-1]
                jobs.append((0, r_lo * s, r_hi * s, target,
                             lambda t=target: embedded_for(t)))
            return jobs
        for scale in EMBEDDINGS:
            jobs.append((0, r_lo * scale, r_hi * scale, f"radii x {scale:g} (embedding)",
                         lambda scale=scale: embedded(scale)))
    else:
        for phi in POROSITIES:
            make = (lambda phi=phi: generate(
                "rectangle", setup["size"], r_lo, r_hi, seed=args.seed, target_porosity=phi,
                gap_tolerance=FIXED_GAP * 0.5 * (r_lo + r_hi)))
            jobs.append((0, r_lo, r_hi, f"porosity {phi:g}", make))
    return jobs


SIZE_SCALES = (2.0, 1.4, 1.0, 0.7)   # mean radius 1.45, 1.0, 0.73, 0.5 mm at 10 cm
POROSITIES = (0.19, 0.21, 0.23)
EMBEDDINGS = (1.0, 1.05, 1.10, 1.15, 1.20)   # area fraction ~0.83 -> 1.19 (seed: 0.83-1.17)
FIXED_GAP = 0.2                      # bonding gap / mean radius for --vary size, porosity


def n_rock(specimen):
    return int(np.sum(np.asarray(specimen.particles.valid)))


if __name__ == "__main__":
    sys.exit(main())
