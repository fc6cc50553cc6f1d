"""How the UCS curve converges to its quasi-static limit as the loading slows.

Peak stress, critical strain and modulus (10-40 % of the peak) of the UCS test
(:data:`jdem.lab.UCS`) against the loading rate (platen speed / wave speed),
for both dampings of the lab layer: the default smooth damping (dashpots plus
background damping against the platens' affine motion) and the seed's local
damping 0.8 (000 eq 3-19).  Specimens: the calibration demo's 4 mm x 8 mm
(~100 discs) and, without ``--small``, a 1.8 cm x 3.6 cm block (~2,200 discs,
the reduced study of tests/test_ucs_reduced.py).  Every rate halves the one
before; the change from one rate to the next is the quasi-static certificate
of :func:`jdem.lab.certify`.  The two dampings of one rate run as one batch of
two members (:func:`jdem.lab.stack_setups`).

    python experiments/rate_convergence.py [--small] [--out experiments/results/rate_convergence]

Writes ``rate_convergence.png``, ``rate_convergence.h5`` (one row per
specimen x damping x rate) and ``rate_convergence.md`` (the table).
"""
from __future__ import annotations

import argparse
import datetime
import pathlib
import platform
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jdem import io, lab  # noqa: E402
from jdem.materials import rock_params  # noqa: E402
from jdem.specimen import generate  # noqa: E402

SPECIMENS = {"demo (4 mm x 8 mm)": ((0.004, 0.008), 4.5, 2),
             "reduced study (1.8 cm x 3.6 cm)": ((0.018, 0.036), 5.0, 2)}
RADII = (0.2e-3, 0.35e-3)
RATES = (6.4e-5, 3.2e-5, 1.6e-5, 8e-6, 4e-6, 2e-6)
LARGE_RATES = (3.2e-5, 1.6e-5, 8e-6, 4e-6)
MAX_STRAIN = 1.2e-3


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--small", action="store_true", help="the ~100-disc specimen only")
    ap.add_argument("--out", default="experiments/results/rate_convergence")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    names = list(SPECIMENS)[:1] if args.small else list(SPECIMENS)
    params = rock_params(2, kappa=3e-3)
    rows = []
    t_all = time.time()
    for name in names:
        size, nbar, seed = SPECIMENS[name]
        spec = generate("rectangle", size, *RADII, seed=seed, target_coordination=nbar)
        n = int(np.sum(np.asarray(spec.particles.valid)))
        rates = RATES if n < 1000 else LARGE_RATES
        dampings = (lab.smooth(), lab.local(0.8))
        for rate in rates:
            # both dampings as one batch of two members (same specimen, schedule, dt)
            setups = [lab.UCS.setup(spec, params, max_strain=MAX_STRAIN, loading_rate=rate,
                                    damping=d) for d in dampings]
            setup = lab.stack_setups(setups)
            t0 = time.time()
            res = lab.run(setup, progress=True, warn_dynamic=False)
            s = lab.peak_summary(res.history)
            wall = time.time() - t0
            for b, damping in enumerate(dampings):
                row = dict(specimen=name, n_particles=n, damping=str(damping),
                           kind=damping.kind, rate=rate,
                           steps=setup.plan.n_records * setup.plan.record_every,
                           peak=float(s["peak_stress"][b]), strain=float(s["critical_strain"][b]),
                           modulus=float(s["youngs_modulus"][b]),
                           kinetic_ratio=float(s["kinetic_ratio"][b]), seconds=wall)
                rows.append(row)
                print(f"{name}, {n} discs, {damping}, rate {rate:.2g}: peak "
                      f"{row['peak'] / 1e6:.3f} MPa at {row['strain'] * 1e6:.0f} ue, E "
                      f"{row['modulus'] / 1e9:.2f} GPa, KE/strain {row['kinetic_ratio']:.2e}, "
                      f"{row['steps']} steps in {wall:.0f} s (both dampings)", flush=True)
            _write(rows, out, time.time() - t_all, argv, quiet=True)   # nothing long is lost
    _write(rows, out, time.time() - t_all, argv)


def _write(rows, out, wall, argv, quiet=False):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sorted(rows, key=lambda r: (list(SPECIMENS).index(r["specimen"]),
                                       r["kind"] != "smooth", -r["rate"]))
    hist = {k: np.asarray([r[k] for r in rows]) for k in ("n_particles", "rate", "steps", "peak",
                                                         "strain", "modulus", "kinetic_ratio",
                                                         "seconds")}
    hist["smooth"] = np.asarray([r["kind"] == "smooth" for r in rows])
    io.save_run(out / "rate_convergence.h5", history=hist,
                attrs=dict(what="UCS peak / modulus against loading rate, both dampings",
                           max_strain=MAX_STRAIN))
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4))
    for name in dict.fromkeys(r["specimen"] for r in rows):
        for kind, style in (("smooth", "-o"), ("local", "--s")):
            sel = [r for r in rows if r["specimen"] == name and r["kind"] == kind]
            if not sel:
                continue
            x = [r["rate"] for r in sel]
            label = f"{name}, {kind}"
            ax.semilogx(x, [r["peak"] / 1e6 for r in sel], style, label=label)
            bx.semilogx(x, [r["modulus"] / 1e9 for r in sel], style, label=label)
    ax.axvline(lab.platen.DEFAULT_LOADING_RATE, color="k", lw=0.8, ls=":")
    bx.axvline(lab.platen.DEFAULT_LOADING_RATE, color="k", lw=0.8, ls=":")
    ax.set_xlabel("loading rate (platen speed / wave speed)")
    ax.set_ylabel("peak stress [MPa]")
    bx.set_xlabel("loading rate (platen speed / wave speed)")
    bx.set_ylabel("modulus 10-40 % of peak [GPa]")
    for a in (ax, bx):
        a.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "rate_convergence.png", dpi=120)
    plt.close(fig)
    lines = ["# UCS curve against loading rate", "",
             f"`python experiments/rate_convergence.py {' '.join(argv or sys.argv[1:])}`, "
             f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
             f"{platform.machine()} {jax.devices()[0].platform}, float64, {wall:.0f} s in all. "
             f"Dotted line in the plot: the default rate {lab.platen.DEFAULT_LOADING_RATE:g}.",
             "", "| specimen | discs | damping | rate | steps | peak MPa | change vs next slower "
             "| critical strain µε | modulus GPa | change | KE / strain energy |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for k, r in enumerate(rows):
        nxt = rows[k + 1] if k + 1 < len(rows) else None
        same = nxt is not None and nxt["specimen"] == r["specimen"] and nxt["kind"] == r["kind"]
        dp = f"{100 * (r['peak'] / nxt['peak'] - 1):+.2f} %" if same else ""
        dm = f"{100 * (r['modulus'] / nxt['modulus'] - 1):+.2f} %" if same else ""
        lines.append(f"| {r['specimen']} | {r['n_particles']} | {r['kind']} | {r['rate']:.2g} | "
                     f"{r['steps']} | {r['peak'] / 1e6:.3f} | {dp} | {r['strain'] * 1e6:.0f} | "
                     f"{r['modulus'] / 1e9:.2f} | {dm} | {r['kinetic_ratio']:.1e} |")
    (out / "rate_convergence.md").write_text("\n".join(lines) + "\n")
    if not quiet:
        print("\n".join(lines))


if __name__ == "__main__":
    main()
