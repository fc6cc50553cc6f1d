#!/usr/bin/env python
"""Uniaxial compression vs fracture strain kappa (002 §2, Fig. 10-15).

    python experiments/ucs_fracture_strain.py --small            # ~500 discs, minutes
    python experiments/ucs_fracture_strain.py                    # the seed's specimen: 1.5 h on 2 CPU cores, 82 s on an H100
    python experiments/ucs_fracture_strain.py --small --platen-step 1e-9 --out results/ucs_kappa

The seed's test: a 5 cm x 10 cm 2D specimen of ~13,000 discs, r uniform in
[0.228, 0.422] mm, rho = 2500 kg/m^3, E = 30 GPa, nu = 0.22, T0 = c0 = 3 MPa,
phi = 30 deg, local damping 0.8, bottom platen fixed, top platen 1 nm per step,
kappa = eps_lim = gamma_lim in {0, 0.1, 0.3, 0.6, 1.2, 2.4} %.  Here the
specimen comes from ``jdem.specimen.generate`` (densest packing, bonding gap
chosen for N-bar = 5, the coordination at which 002 §1.4 finds lambda ~ 1; the
seed's "63,252 contacts" for 13,097 discs is 4.83 per disc) and the six kappas
run as ONE batched (vmapped) host run: ``jdem.lab.UCS.setup`` then
``jdem.lab.run``.

Damping: the seed's local non-viscous damping, alpha = 0.8 (000 eq 3-19,
``jdem.lab.local(0.8)``), passed explicitly: the lab tests' default is the
smooth damping ``jdem.lab.smooth()``, which is not what 002 §2.1 used.  The
platen speeds up over the lab tests' default ramp (10 wave transits through the
specimen, half a cosine) instead of starting at full speed.

``--small`` (explicit, for quick runs): a 1 cm x 2 cm specimen (~480 discs) of
the same radii and a 2 nm platen step (``--platen-step`` to change it).  The
number of wave transits through the specimen per unit of axial strain,
c dt / platen_step, does not depend on the specimen size, so 1 nm on the small
specimen is as quasi-static as 1 nm on the seed's.

Writes to ``--out`` (default results/ucs_fracture_strain[_small]):

* ``stress_strain.png``       the six stress-strain curves (Fig. 10)
* ``peak_vs_kappa.png``       peak stress and critical strain vs kappa (Fig. 11)
* ``fracture_degree_vs_kappa.png``  fracture degree at the peak and at the end (Fig. 14)
* ``stress_fd_vs_strain.png`` axial stress and fracture degree vs strain (Fig. 15)
* ``failure_patterns.png``    broken bonds at the end, tension red / shear black (Fig. 12)
* ``damage_at_peak.png``      combined damage chi (002 eq 10) at the peak (Fig. 13)
* ``ucs_fracture_strain.h5``  histories (batched), final state, params, config,
                              summary and timings (``jdem.io.save_run``)
* ``summary.json``            the table printed at the end, the wall time and the
                              estimate of the full run's time from the measured throughput
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
from matplotlib.collections import LineCollection  # noqa: E402

import jdem.io  # noqa: E402
from jdem import lab  # noqa: E402
from jdem.batch import member  # noqa: E402
from jdem.materials import rock_params  # noqa: E402
from jdem.specimen import generate  # noqa: E402

KAPPAS = (0.0, 1e-3, 3e-3, 6e-3, 1.2e-2, 2.4e-2)
#: the seed's figures (002 §2.2-2.3): kappa -> value
SEED_PEAK = {0.0: 6.54e6, 2.4e-2: 20.1e6}
SEED_CRIT = {0.0: 232e-6, 2.4e-2: 861e-6}
SEED_FD_PEAK = {0.0: 0.015, 2.4e-2: 0.00073}
SEED_FD_END = {0.0: 0.19, 2.4e-2: 0.024}

FULL = dict(size=(0.05, 0.10), radii=(0.228e-3, 0.422e-3), platen_step=1e-9, max_strain=3e-3,
            record_every=100)
SMALL = dict(size=(0.01, 0.02), radii=(0.228e-3, 0.422e-3), platen_step=2e-9, max_strain=3e-3,
             record_every=50)
MATERIAL = dict(E=30e9, nu=0.22, T0=3e6, c0=3e6, phi_deg=30.0, local_damping=0.8)
DENSITY = 2500.0
N_BAR = 5.0
STOP_RATIO = 0.25      # stop once every curve fell below 25 % of its peak
DAMPING = lab.local(0.8)   # the seed's local damping (002 §2.1), not the lab default smooth()


def _label(k):
    return f"κ = {k * 100:g} %"


def plot_curves(hist, kappas, path):
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for b, k in enumerate(kappas):
        ax.plot(hist["axial_strain"][b] * 1e6, hist["axial_stress"][b] / 1e6, lw=1.4,
                label=_label(k))
    ax.set_xlabel("axial strain [10⁻⁶]")
    ax.set_ylabel("axial stress [MPa]")
    ax.set_title("uniaxial compression vs fracture strain (002 Fig. 10)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_peak(summary, kappas, path):
    k = np.asarray(kappas) * 100
    fig, ax = plt.subplots(figsize=(6, 4.2))
    ax.plot(k, summary["peak_stress"] / 1e6, "o-", color="C0", label="peak stress (jdem)")
    ax.plot([x * 100 for x in SEED_PEAK], [v / 1e6 for v in SEED_PEAK.values()], "s",
            mfc="none", color="C0", label="peak stress (002)")
    ax.set_xlabel("fracture strain κ [%]")
    ax.set_ylabel("peak stress [MPa]", color="C0")
    ax2 = ax.twinx()
    ax2.plot(k, summary["critical_strain"] * 1e6, "^-", color="C3", label="critical strain (jdem)")
    ax2.plot([x * 100 for x in SEED_CRIT], [v * 1e6 for v in SEED_CRIT.values()], "D",
             mfc="none", color="C3", label="critical strain (002)")
    ax2.set_ylabel("critical strain [10⁻⁶]", color="C3")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=8, loc="lower right")
    ax.set_title("peak stress and critical strain (002 Fig. 11)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_fd(summary, kappas, path):
    k = np.asarray(kappas) * 100
    fig, ax = plt.subplots(figsize=(6, 4.2))
    ax.semilogy(k, summary["fracture_degree_at_peak"] * 100, "o-", label="at peak (jdem)")
    ax.semilogy(k, summary["fracture_degree_end"] * 100, "^-", label="at the end (jdem)")
    ax.semilogy([x * 100 for x in SEED_FD_PEAK], [v * 100 for v in SEED_FD_PEAK.values()], "s",
                mfc="none", color="C0", label="at peak (002)")
    ax.semilogy([x * 100 for x in SEED_FD_END], [v * 100 for v in SEED_FD_END.values()], "D",
                mfc="none", color="C1", label="at the end (002)")
    ax.set_xlabel("fracture strain κ [%]")
    ax.set_ylabel("fracture degree [%]")
    ax.set_title("fracture degree (002 Fig. 14)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_fig15(hist, kappas, path):
    picks = [b for b, k in enumerate(kappas) if k in (0.0, 3e-3)] or [0]
    fig, axes = plt.subplots(1, len(picks), figsize=(5.2 * len(picks), 3.8), squeeze=False)
    for ax, b in zip(axes[0], picks):
        e = hist["axial_strain"][b] * 1e6
        ax.plot(e, hist["axial_stress"][b] / 1e6, color="C0")
        ax.set_xlabel("axial strain [10⁻⁶]")
        ax.set_ylabel("axial stress [MPa]", color="C0")
        ax2 = ax.twinx()
        ax2.plot(e, hist["fracture_degree"][b] * 100, color="C3")
        ax2.set_ylabel("fracture degree [%]", color="C3")
        ax.set_title(_label(kappas[b]))
        ax.grid(alpha=0.3)
    fig.suptitle("axial stress and fracture degree vs strain (002 Fig. 15)")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _panels(n, box):
    lo, hi = np.asarray(box[0]), np.asarray(box[1])
    aspect = float((hi[1] - lo[1]) / (hi[0] - lo[0]))
    w = 2.0
    fig, axes = plt.subplots(1, n, figsize=(w * n + 1.0, w * aspect * 1.05 + 0.9), squeeze=False)
    fig.subplots_adjust(left=0.01, right=0.9, bottom=0.02, top=0.84, wspace=0.05)
    return fig, axes


def plot_failure(state, kappas, box, path):
    fig, axes = _panels(len(kappas), box)
    for b, ax in enumerate(axes[0]):
        fp = lab.failure_pattern(member(state, b))
        for mode, color in ((1, "red"), (2, "black")):
            seg = fp["segment"][fp["mode"] == mode] * 100
            ax.add_collection(LineCollection(seg, colors=color, linewidths=0.9))
        _frame(ax, box)
        nt, ns = int(np.sum(fp["mode"] == 1)), int(np.sum(fp["mode"] == 2))
        ax.set_title(f"{_label(kappas[b])}\n{nt} tension, {ns} shear", fontsize=8)
    fig.suptitle("broken bonds at the end: tension red, shear black (002 Fig. 12)", fontsize=9)
    fig.savefig(path, dpi=150)
    plt.close(fig)


def plot_damage(hist, kappas, box, path):
    fig, axes = _panels(len(kappas), box)
    sc = None
    for b, ax in enumerate(axes[0]):
        valid = hist["peak_valid"][b]
        pts = hist["peak_point"][b][valid] * 100
        chi = hist["peak_chi"][b][valid]
        zero = chi <= 1e-6
        ax.scatter(pts[zero, 0], pts[zero, 1], s=0.8, color="0.85", linewidths=0)
        order = np.argsort(chi[~zero])
        sc = ax.scatter(pts[~zero][order, 0], pts[~zero][order, 1], c=chi[~zero][order], s=7,
                        cmap="plasma_r", vmin=0, vmax=1, linewidths=0)
        _frame(ax, box)
        ax.set_title(f"{_label(kappas[b])}\nstep {int(hist['peak_step'][b])}", fontsize=8)
    cax = fig.add_axes([0.92, 0.15, 0.015, 0.6])
    fig.colorbar(sc, cax=cax, label="χ (grey: 0)")
    fig.suptitle("combined damage χ at the peak stress (002 Fig. 13)", fontsize=9)
    fig.savefig(path, dpi=150)
    plt.close(fig)


def _frame(ax, box):
    lo, hi = np.asarray(box[0]) * 100, np.asarray(box[1]) * 100
    ax.plot([lo[0], hi[0], hi[0], lo[0], lo[0]], [lo[1], lo[1], hi[1], hi[1], lo[1]], "k-",
            lw=0.4, alpha=0.4)
    ax.set_aspect("equal")
    ax.set_xlim(lo[0] - 0.05 * (hi[0] - lo[0]), hi[0] + 0.05 * (hi[0] - lo[0]))
    ax.set_ylim(lo[1] - 0.02 * (hi[1] - lo[1]), hi[1] + 0.02 * (hi[1] - lo[1]))
    ax.set_xticks([])
    ax.set_yticks([])
    for spine in ax.spines.values():
        spine.set_visible(False)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--small", action="store_true",
                    help="reduced specimen (1 cm x 2 cm, ~480 discs) and a 2 nm platen step")
    ap.add_argument("--out", default=None)
    ap.add_argument("--platen-step", type=float, default=None, help="[m per step]")
    ap.add_argument("--max-strain", type=float, default=None)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    small = args.small or os.environ.get("JDEM_SMALL") == "1"
    setup = dict(SMALL if small else FULL)
    if args.platen_step:
        setup["platen_step"] = args.platen_step
    if args.max_strain:
        setup["max_strain"] = args.max_strain
    out = pathlib.Path(args.out or ("results/ucs_fracture_strain" + ("_small" if small else "")))
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.time()

    print(f"specimen {setup['size'][0] * 100:g} cm x {setup['size'][1] * 100:g} cm, r in "
          f"[{setup['radii'][0] * 1e3:g}, {setup['radii'][1] * 1e3:g}] mm, N-bar target {N_BAR}")
    sp = generate("rectangle", setup["size"], *setup["radii"], seed=args.seed, density=DENSITY,
                  target_coordination=N_BAR, progress=not small)
    t_gen = time.time() - t_start
    n_part = int(sp.info["n_particles"])
    print(f"  {n_part} discs, {sp.info['n_bonds']} bonds, porosity {sp.porosity:.3f}, "
          f"N-bar {sp.coordination:.2f}  ({t_gen:.0f} s)")

    params = rock_params(2, kappa=list(KAPPAS), **MATERIAL)
    t1 = time.time()
    test = lab.UCS.setup(sp, params, platen_step=setup["platen_step"],
                         max_strain=setup["max_strain"], record_every=setup["record_every"],
                         damping=DAMPING)
    print(f"  {test}: the seed's local damping, not the lab default smooth()")
    res = lab.run(test, progress=True, stop_stress_ratio=STOP_RATIO, keep_peak_state=True)
    hist, state = res.history, res.state
    config, params = res.setup.plan.config, res.setup.params   # the time step and damping run
    t_run = time.time() - t1
    steps = int(np.max(np.asarray(state.step)))
    summary = lab.peak_summary(hist)
    print(f"  {steps} steps x {len(KAPPAS)} members in {t_run:.0f} s "
          f"({steps / t_run:.0f} batched steps/s)")

    plot_curves(hist, KAPPAS, out / "stress_strain.png")
    plot_peak(summary, KAPPAS, out / "peak_vs_kappa.png")
    plot_fd(summary, KAPPAS, out / "fracture_degree_vs_kappa.png")
    plot_fig15(hist, KAPPAS, out / "stress_fd_vs_strain.png")
    plot_failure(state, KAPPAS, sp.box, out / "failure_patterns.png")
    plot_damage(hist, KAPPAS, sp.box, out / "damage_at_peak.png")

    # throughput and the full run's estimate: cost ~ particles x steps (batched members too)
    rate = n_part * steps / t_run                           # particle-steps/s of the batch
    full_area = FULL["size"][0] * FULL["size"][1]
    n_full = n_part * full_area / (setup["size"][0] * setup["size"][1])
    strain_end = float(np.max(hist["axial_strain"][:, -1]))
    steps_full = strain_end * FULL["size"][1] / FULL["platen_step"]
    est_full_s = n_full * steps_full / rate
    table = []
    print(f"\n  {'kappa %':>8} {'peak MPa':>9} {'crit 1e-6':>9} {'E GPa':>6} {'nu':>5} "
          f"{'FD peak %':>9} {'FD end %':>8}")
    for b, k in enumerate(KAPPAS):
        row = {key: float(np.asarray(v)[b]) for key, v in summary.items()}
        row["kappa"] = k
        table.append(row)
        print(f"  {k * 100:8.2f} {row['peak_stress'] / 1e6:9.2f} {row['critical_strain'] * 1e6:9.0f} "
              f"{row['youngs_modulus'] / 1e9:6.1f} {row['poisson_ratio']:5.2f} "
              f"{row['fracture_degree_at_peak'] * 100:9.3f} {row['fracture_degree_end'] * 100:8.2f}")
    wall = time.time() - t_start
    info = dict(small=small, setup={k: list(v) if isinstance(v, tuple) else v
                                    for k, v in setup.items()},
                damping=str(test.plan.damping), dt=float(np.max(np.asarray(params.dt))),
                n_particles=n_part, n_bonds=int(sp.info["n_bonds"]), porosity=float(sp.porosity),
                coordination=float(sp.coordination), steps=steps, members=len(KAPPAS),
                generation_s=t_gen, run_s=t_run, wall_s=wall,
                particle_steps_per_s=rate, full_estimate=dict(
                    n_particles=n_full, steps=steps_full, run_s=est_full_s,
                    note="batched 6-member run, cost taken linear in particles x steps; "
                         "specimen generation not included"),
                table=table)
    (out / "summary.json").write_text(json.dumps(info, indent=1))
    attrs = {"what": "002 §2 uniaxial compression vs fracture strain", "kappas": list(KAPPAS),
             "wall_s": wall, "run_s": t_run, "generation_s": t_gen, "n_particles": n_part,
             "platen_step": setup["platen_step"], "full_estimate_s": est_full_s,
             "damping": str(test.plan.damping)}
    hist_out = dict(hist)
    for key, v in summary.items():
        hist_out[f"summary_{key}"] = np.asarray(v)
    path = jdem.io.save_run(out / "ucs_fracture_strain.h5", state=state, params=params,
                            config=config, history=hist_out, attrs=attrs)
    print(f"\n  wall time {wall:.0f} s (generation {t_gen:.0f} s, run {t_run:.0f} s); "
          f"throughput {rate:.3g} particle-steps/s")
    print(f"  full run estimate: ~{n_full:.0f} discs x {steps_full:.3g} steps -> "
          f"{est_full_s / 3600:.1f} h on this machine (batched, 6 members)")
    print(f"  -> {out}/*.png, {path}")
    return info


if __name__ == "__main__":
    main()
    sys.exit(0)
