#!/usr/bin/env python
"""Where does a Brazilian disc start to break, and does that change with its size?

    python experiments/brazilian_size.py --small              # D = 12, 20 mm (minutes on a CPU)
    python experiments/brazilian_size.py                      # D = 12, 30, 60, 100 mm (use a GPU)
    python experiments/brazilian_size.py --diameters 0.012 0.04 --out results/brazil
    python experiments/brazilian_size.py --diameters 0.012 --platen-stiffness 0.003 --max-strain 0.03

Elasticity puts the largest tensile stress of a disc under diametral line loads
uniformly along the loaded diameter, and the crack of a rock disc starts at the
centre.  The test suite's disc (D = 12 mm, r in [0.2, 0.35] mm, 384 discs)
breaks first along the loaded diameter but away from the centre (the suite's
check that it starts at the centre, ``test_brazilian_failure_starts_at_the_centre``,
was a strict xfail; ``tests/test_lab.py::test_brazilian_reports_the_onset_location``
now reports the onset instead).  This study repeats that test (same radii,
N-bar = 5, T0 = 3 MPa, c0 = 10 MPa, kappa = 0, 1.5 nm platen step) on larger
discs, so the ratio D / d grows, and reports for the first tenth of the broken
bonds: their distance from the centre r / R, the share with r < 0.4 R (the
centre-start check asked for >= 80 %) and the
share in the band |x - x_c| < R / 3 around the loaded diameter; also the indirect
tensile strength sigma_t = 2 P / (pi D) at the peak.

The loading can be varied to see what moves the first breaks:
``--platen-stiffness`` (platen / rock stiffness, 10 by default: a rigid steel
platen; below 1 a soft cushion that spreads the load over more boundary discs, as
the cardboard strips of the lab test do), ``--flat-angle`` (cut two flat loading
faces of that angle, ``jdem.specimen.flatten_disc``), ``--kappa`` (fracture
strain, 0 by default: brittle bonds) and ``--c0`` (cohesion).  A soft platen needs
a larger ``--max-strain``: most of the platen travel goes into the cushion.

The test is ``jdem.lab.BRAZILIAN`` run by ``jdem.lab.run`` (a record every 50
steps, stopped once the load fell below 30 % of its peak) with the seed's local
damping, alpha = 0.8 (``jdem.lab.local(0.8)``, 002 §2.1), passed explicitly: the
lab tests' default is the smooth damping ``jdem.lab.smooth()``.  The platen
speeds up over the lab tests' default ramp (10 wave transits, half a cosine).

Writes ``first_breaks.png`` (broken bonds of each disc coloured by when they broke,
the first tenth ringed), ``brazilian_size.json`` (the table) and
``brazilian_size.h5`` (one group per diameter: the history and the broken bonds'
points, modes and steps; reopen with ``h5py``).
"""
from __future__ import annotations

import argparse
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

from jdem import InputError  # noqa: E402
from jdem import lab  # noqa: E402
from jdem.materials import rock_params  # noqa: E402
from jdem.specimen import flatten_disc, generate  # noqa: E402

RADII = (0.2e-3, 0.35e-3)   # [m], as in tests/test_lab.py
N_BAR = 5.0
STEP = 1.5e-9               # [m per step]
FULL = (0.012, 0.03, 0.06, 0.10)
SMALL = (0.012, 0.02)
RECORD_EVERY = 50           # steps per record
STOP_RATIO = 0.3            # stop once the load fell below 30 % of its peak
DAMPING = lab.local(0.8)    # the seed's local damping (002 §2.1), not the lab default smooth()


def first_break_stats(disc, state, hist):
    """Distances of the first tenth of the broken bonds from the centre, and shares."""
    big_r = disc.info["radius"]
    centre = np.asarray(disc.info["centre"])          # generate("disc") records both
    fp = lab.failure_pattern(state)
    n = len(fp["step"])
    first = lab.first_breaks(fp)
    r = np.linalg.norm(fp["point"][first] - centre, axis=1) / big_r
    band = np.abs(fp["point"][:, 0] - centre[0]) < big_r / 3
    k = int(np.argmax(hist["load"]))
    return dict(n_broken=int(n), n_first=int(len(first)), r_over_R=r.tolist(),
                median_r_over_R=float(np.median(r)), share_first_within_0_4R=float(np.mean(r < 0.4)),
                share_first_in_band=float(np.mean(band[first])), share_all_in_band=float(band.mean()),
                share_first_tension=float(np.mean(fp["mode"][first] == 1)),
                sigma_t=float(hist["tensile_strength_indirect"][k]),
                strain_at_peak=float(hist["axial_strain"][k])), fp, first, centre, big_r


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--small", action="store_true", help=f"diameters {SMALL} m")
    ap.add_argument("--diameters", type=float, nargs="+", help="disc diameters [m]")
    ap.add_argument("--max-strain", type=float, default=0.004)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--platen-stiffness", type=float, default=10.0,
                    help="platen / rock contact stiffness ratio (default 10: rigid)")
    ap.add_argument("--flat-angle", type=float, default=0.0,
                    help="angle [deg] of two flat loading faces (default 0: round disc)")
    ap.add_argument("--kappa", type=float, default=0.0, help="fracture strain (default 0)")
    ap.add_argument("--c0", type=float, default=10e6, help="bond cohesion [Pa] (default 10 MPa)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    diameters = args.diameters or (SMALL if args.small else FULL)
    out = pathlib.Path(args.out or ("results/brazilian_size" + ("_small" if args.small else "")))
    out.mkdir(parents=True, exist_ok=True)
    params = rock_params(2, kappa=args.kappa, c0=args.c0,
                         platen_stiffness=args.platen_stiffness)
    loading = dict(platen_stiffness=args.platen_stiffness, flat_angle_deg=args.flat_angle,
                   kappa=args.kappa, c0=args.c0, max_strain=args.max_strain)
    print("loading: " + ", ".join(f"{k} {v:g}" for k, v in loading.items())
          + f"; damping {DAMPING}", flush=True)
    rows, panels = [], []
    with h5py.File(out / "brazilian_size.h5", "w") as h5:
        for d in diameters:
            t0 = time.time()
            try:
                disc = generate("disc", d, *RADII, seed=args.seed, target_coordination=N_BAR,
                                progress=d > 0.03)
            except InputError as err:  # small discs: too few contacts for N-bar 5
                print(f"D = {d * 1e3:g} mm skipped: {err}", flush=True)
                continue
            t_gen = time.time() - t0
            specimen = flatten_disc(disc, args.flat_angle) if args.flat_angle > 0 else disc
            test = lab.BRAZILIAN.setup(specimen, params, platen_step=STEP,
                                       max_strain=args.max_strain, record_every=RECORD_EVERY,
                                       damping=DAMPING)
            res = lab.run(test, progress=True, stop_stress_ratio=STOP_RATIO)
            hist, state = res.history, res.state
            t_run = time.time() - t0 - t_gen
            stats, fp, first, centre, big_r = first_break_stats(disc, state, hist)
            n_loaded = int(np.sum(np.asarray(specimen[0].valid)))   # after any flats are cut
            stats.update(loading, damping=str(DAMPING), diameter=d,
                         n_discs=int(disc.info["n_particles"]),
                         n_discs_loaded=n_loaded,
                         d_over_mean_diameter=d / sum(RADII), generation_s=t_gen, run_s=t_run,
                         steps=int(np.max(np.asarray(state.step))))
            rows.append(stats)
            panels.append((d, fp, first, centre, big_r))
            g = h5.create_group(f"D_{d * 1e3:g}mm")
            for key, v in hist.items():
                g.create_dataset(key, data=np.asarray(v))
            for key in ("point", "mode", "step"):
                g.create_dataset(f"broken_{key}", data=np.asarray(fp[key]))
            g.attrs.update({k: v for k, v in stats.items() if not isinstance(v, list)})
            print(f"D = {d * 1e3:g} mm: {stats['n_discs']} discs, {stats['steps']} steps "
                  f"({t_gen:.0f} s + {t_run:.0f} s); sigma_t {stats['sigma_t'] / 1e6:.2f} MPa; "
                  f"first {stats['n_first']} breaks: median r/R {stats['median_r_over_R']:.2f}, "
                  f"{100 * stats['share_first_within_0_4R']:.0f} % within 0.4 R, "
                  f"{100 * stats['share_first_in_band']:.0f} % in the band", flush=True)

    fig, axes = plt.subplots(1, len(panels), figsize=(max(4 * len(panels), 6), 5.2),
                             squeeze=False)
    for ax, (d, fp, first, centre, big_r) in zip(axes[0], panels):
        p = (fp["point"] - centre) / big_r
        sc = ax.scatter(p[:, 0], p[:, 1], c=fp["step"], s=3, cmap="viridis")
        ax.scatter(p[first, 0], p[first, 1], s=30, facecolors="none", edgecolors="r", lw=0.8)
        ax.add_patch(plt.Circle((0, 0), 1.0, fill=False, color="0.5"))
        ax.add_patch(plt.Circle((0, 0), 0.4, fill=False, color="r", ls="--", lw=0.8))
        ax.set_aspect("equal")
        ax.set_xlim(-1.05, 1.05)
        ax.set_ylim(-1.05, 1.05)
        ax.set_title(f"D = {d * 1e3:g} mm ({len(fp['step'])} broken)", fontsize=10)
        ax.set_xlabel("x / R")
        fig.colorbar(sc, ax=ax, shrink=0.7, label="step of breaking")
    axes[0][0].set_ylabel("y / R")
    fig.suptitle("Brazilian test: broken bonds\nfirst tenth ringed red; r = 0.4 R dashed\n"
                 f"platen stiffness {args.platen_stiffness:g}, flat {args.flat_angle:g} deg, "
                 f"kappa {args.kappa:g}, c0 {args.c0 / 1e6:g} MPa", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "first_breaks.png", dpi=130)
    (out / "brazilian_size.json").write_text(json.dumps(rows, indent=1))
    print(f"\n{'D mm':>6} {'discs':>7} {'D/d':>5} {'sigma_t MPa':>11} {'median r/R':>10} "
          f"{'<0.4R %':>8} {'band %':>7}")
    for s in rows:
        print(f"{s['diameter'] * 1e3:6g} {s['n_discs']:7d} {s['d_over_mean_diameter']:5.0f} "
              f"{s['sigma_t'] / 1e6:11.2f} {s['median_r_over_R']:10.2f} "
              f"{100 * s['share_first_within_0_4R']:8.0f} {100 * s['share_first_in_band']:7.0f}")
    print(f"-> {out}/first_breaks.png, brazilian_size.json, brazilian_size.h5")
    return rows


if __name__ == "__main__":
    main()
