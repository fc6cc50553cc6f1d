#!/usr/bin/env python
"""The four stages of the UCS curve (002 §2.2, Fig 10, 15) and the broken bonds by
mode (Fig 12), per fracture strain kappa, beside the seed's statements.

    python experiments/ucs_stages.py                        # kappa 0, 0.3 %, 2.4 %
    python experiments/ucs_stages.py --kappas 0 0.001 0.003 0.006 0.012 0.024 --seed 3
    python experiments/ucs_stages.py --plates --out experiments/results/ucs_stages_plates
    python experiments/ucs_stages.py --full --out experiments/results/ucs_stages_full
    python experiments/ucs_stages.py --kappas 0 0.024 --loading-rate 4e-6 --plates --free-plates
    python experiments/ucs_stages.py --kappas 0 0.024 --loading-rate 4e-6 --plates --free-plates \
        --area-fraction 0.895                               # and the seed's area fraction

One packing of the reduced study (``experiments/ucs_seed_bands.py``: a 1.8 cm x
3.6 cm rectangle, r in [0.2, 0.35] mm, N-bar 5, the seed's material, local damping
0.8, a 3 nm platen step), all kappa as one batch, loaded until every member has
fallen below 15 % of its peak (or 4e-3 strain), so that the residual stage shows.
Stages from :func:`jdem.lab.curve_stages`.  The seed (13,097 discs, 5 cm x
10 cm, 1 nm step) says: the linear stage ends near 5.9 MPa for every kappa; the
non-linear rise is about 20 % of the linear one at kappa = 0 and more than twice
it at 2.4 %; the residual stage sits at 0.4-2 MPa; with small kappa the failure
mixes tension and shear, with large kappa it is compression-shear.
``--full`` runs the seed's specimen instead: 5 cm x 10 cm, r in [0.228, 0.422] mm
(13,097 discs at the seed's density, as ``experiments/ucs_fracture_strain.py``),
still with the 3 nm platen step (the strain per step is then 2.8 x smaller than
the reduced study's, the loading rate the same).

The 3 nm step is a loading rate (platen speed / bar wave speed) of 5.2e-5 with
jdem's time step: 13 x the certified default and 3-13 x faster than the seed's
1 nm step (which is 3.9e-6 with the textbook's time step, 000 eq 3-26, 1.5e-5
with jdem's), and the kappa = 0 peak is the rate's there.  ``--loading-rate``
runs at a rate instead; the last example is the seed's protocol (its damping,
its step as a rate, its faces held and free sideways), where the seed's
kappa = 0 figures come back; with the seed's area fraction (``--area-fraction``,
or ``--embed`` the radius factor) its
kappa = 2.4 % figures too (experiments/results/ucs_stages_rate/NOTES.md).

Writes ``experiments/results/ucs_stages/``: ``ucs_stages.md`` (the table),
``.json``, ``.h5`` (curves and counts; reopen with ``jdem.io.load_run``) and
``.png`` (curves with the stage ends marked).  float64.
"""
from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jdem import io, lab  # noqa: E402
from jdem.materials import rock_params  # noqa: E402
from jdem.specimen import add_plates, embed, generate  # noqa: E402

SIZE = (0.018, 0.036)
RADII = (0.2e-3, 0.35e-3)
STEP = 3e-9
FULL_SIZE = (0.05, 0.10)                  # the seed's UCS specimen (002 §2.1)
FULL_RADII = (0.228e-3, 0.422e-3)         # 13,097 discs in it, as the seed's
OUT = pathlib.Path(__file__).parent / "results" / "ucs_stages"
COLUMNS = ("linear_end_stress", "first_break_stress", "peak_stress", "peak_strain",
           "rise_ratio", "descent_modulus", "residual_stress", "n_tension_at_peak",
           "n_shear_at_peak", "n_tension_end", "n_shear_end")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--kappas", type=float, nargs="+", default=[0.0, 3e-3, 2.4e-2])
    ap.add_argument("--out", type=pathlib.Path, default=OUT)
    ap.add_argument("--full", action="store_true",
                    help="the seed's 5 cm x 10 cm specimen (~13,000 discs) instead of the "
                         "reduced 1.8 cm x 3.6 cm one")
    ap.add_argument("--damping", default="local:0.8",
                    help="'local:ALPHA' (000 eq 3-19, default alpha 0.8 as the seed's) or "
                         "'smooth' (the lab tests' default, jdem.lab.smooth())")
    ap.add_argument("--plates", action="store_true",
                    help="load through steel plates bonded to the faces (jdem.specimen."
                         "add_plates, 002 Fig 7) instead of rigid frictionless platens")
    ap.add_argument("--free-plates", action="store_true",
                    help="with --plates: one row of plate discs bonded to the rock only, not "
                         "to each other, so the faces are held in the loading direction and "
                         "free sideways (the seed's UCS boundary, 002 §2.1)")
    ap.add_argument("--section", choices=("circular", "slab"), default="circular",
                    help="2D bond bending section (jdem.lab.UCS.setup's bond_section): the "
                         "seed's circular formula (002 eq 5, default) or a unit-thickness slab")
    ap.add_argument("--embed", type=float, default=None,
                    help="grow every radius by this factor at fixed centres and rebond "
                         "(jdem.specimen.embed): the seed's denser specimens, 002 §1.4")
    ap.add_argument("--area-fraction", type=float, default=None,
                    help="instead of --embed: grow the radii until the discs fill this "
                         "fraction of the specimen (the seed's: 0.895)")
    ap.add_argument("--loading-rate", type=float, default=None,
                    help="platen speed / bar wave speed (jdem.lab.UCS.setup's loading_rate) "
                         f"instead of the {STEP * 1e9:g} nm platen step; the lab tests' certified "
                         "default is 4e-6, the 3 nm step is 5.2e-5 on the reduced specimen")
    a = ap.parse_args(argv)
    if a.damping == "smooth":
        damping = lab.smooth()
    elif a.damping.startswith("local:"):
        damping = lab.local(float(a.damping.split(":", 1)[1]))
    else:
        ap.error(f"--damping must be 'local:ALPHA' or 'smooth', got {a.damping!r}")
    a.out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    size, radii = (FULL_SIZE, FULL_RADII) if a.full else (SIZE, RADII)
    spec = generate("rectangle", size, *radii, seed=a.seed, target_coordination=5.0)
    if a.embed is not None or a.area_fraction is not None:
        spec = embed(spec, a.embed, area_fraction=a.area_fraction)
        a.embed = spec.info["embedding"]
    n = int(np.sum(np.asarray(spec.particles.valid)))
    n_bonds = int(np.sum(np.asarray(spec.bonds.valid)))
    if a.free_plates and not a.plates:
        ap.error("--free-plates goes with --plates")
    if a.plates:
        spec = add_plates(spec, **(dict(rows=1, bond_plate_discs=False) if a.free_plates
                                   else {}))
    params = rock_params(2, kappa=list(a.kappas), plate_youngs=200e9 if a.plates else None)
    setup = lab.UCS.setup([spec] * len(a.kappas), params,
                          **(dict(platen_step=STEP) if a.loading_rate is None
                             else dict(loading_rate=a.loading_rate)),
                          max_strain=4e-3, damping=damping, bond_section=a.section,
                          record_every=50)
    # saved every minute; a run interrupted (Ctrl-C) continues from it when started again
    ckpt = a.out / "ucs_stages.checkpoint.h5"
    res = lab.run(setup, stop_stress_ratio=0.15, progress=True, warn_dynamic=False,
                  checkpoint=ckpt, resume=ckpt if ckpt.exists() else None)
    ckpt.unlink(missing_ok=True)          # finished: a later run starts afresh
    run_s = time.time() - t0
    st = lab.curve_stages(res.history)
    rows = [dict(kappa=k, **{c: float(np.asarray(st[c])[m]) for c in COLUMNS})
            for m, k in enumerate(a.kappas)]
    command = "python experiments/ucs_stages.py " + " ".join(
        argv if argv is not None else sys.argv[1:])
    rate = float(setup.plan.option("loading_rate"))
    out = dict(date=datetime.date.today().isoformat(), command=command, n_discs=n,
               n_bonds=n_bonds, run_s=run_s, rows=rows,
               loading_rate=rate, damping=a.damping,
               section=a.section, embed=a.embed, coordination=float(spec.coordination),
               area_fraction=float(spec.info.get("area_fraction", float("nan"))),
               boundary=("free plates" if a.free_plates else "bonded plates") if a.plates
               else "rigid platens")
    (a.out / "ucs_stages.json").write_text(json.dumps(out, indent=1))
    io.save_run(a.out / "ucs_stages.h5",
                history={k: res.history[k] for k in ("axial_strain", "axial_stress",
                                                     "fracture_degree", "n_tension", "n_shear")},
                attrs={"kappas": list(a.kappas), "seed": a.seed, "command": command})
    md = ["# Stages of the UCS curve and breaks by mode (002 §2.2-2.3, Fig 10, 12, 15)", "",
          f"{out['date']}, `{command}`, float64, 2-core CPU; packing {a.seed}: {n} discs, "
          f"{n_bonds} bonds, {size[0] * 100:g} cm x {size[1] * 100:g} cm, damping {a.damping}, "
          f"bond section {a.section}, "
          f"loading rate {rate:.3g}; "
          f"{run_s:.0f} s."
          + (f" Loaded through {'free' if a.free_plates else 'bonded'} steel plates "
             f"({spec.info['n_plate_discs']} discs; the break counts are the rock's, "
             "without its bonds to the plates)." if a.plates else ""),
          "",
          "| kappa % | linear end MPa (seed ~5.9) | first break MPa | peak MPa | peak strain "
          "1e-6 | non-linear / linear rise (seed ~0.2 at 0, > 2 at 2.4 %) | steepest descent "
          "GPa | residual MPa (seed 0.4-2) | tension / shear breaks at peak | at end |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {100 * r['kappa']:g} | {r['linear_end_stress'] / 1e6:.2f} | "
                  f"{r['first_break_stress'] / 1e6:.2f} | {r['peak_stress'] / 1e6:.2f} | "
                  f"{r['peak_strain'] * 1e6:.0f} | {r['rise_ratio']:.2f} | "
                  f"{r['descent_modulus'] / 1e9:.1f} | {r['residual_stress'] / 1e6:.2f} | "
                  f"{r['n_tension_at_peak']:.0f} / {r['n_shear_at_peak']:.0f} | "
                  f"{r['n_tension_end']:.0f} / {r['n_shear_end']:.0f} |")
    (a.out / "ucs_stages.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for m, r in enumerate(rows):
        e = res.history["axial_strain"][m] * 1e6
        s = res.history["axial_stress"][m] / 1e6
        ax.plot(e, s, color=f"C{m}", lw=1, label=f"κ = {100 * r['kappa']:g} %")
        stages = dict(linear_end=(st["linear_end_strain"][m], r["linear_end_stress"]),
                      peak=(r["peak_strain"], r["peak_stress"]),
                      residual=(st["residual_strain"][m], r["residual_stress"]))
        for (x, y), mk in zip(stages.values(), ("o", "^", "s")):
            if np.isfinite(x):
                ax.plot(x * 1e6, y / 1e6, mk, color=f"C{m}", mfc="none")
    ax.axhline(5.9, color="k", lw=0.5, ls=":")
    ax.set(xlabel="axial strain [1e-6]", ylabel="axial stress [MPa]",
           title="UCS stages (o linear end, ^ peak, s residual; dotted: the seed's 5.9 MPa)")
    ax.legend()
    fig.savefig(a.out / "ucs_stages.png", dpi=120, bbox_inches="tight")


if __name__ == "__main__":
    main()
