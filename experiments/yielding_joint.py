#!/usr/bin/env python
"""The continuously yielding joint (000 §3.4.1 item 5, fig 3-16 to 3-18) in direct shear.

    python experiments/yielding_joint.py [--out DIR]

1. Shear stress against shear displacement at constant normal stress for three
   roughnesses R (000 fig 3-16): the peak, then the fall towards the residual
   strength sigma_n tan(phi), with the strength sigma_n tan(phi_e(u_p)).
2. Normal displacement (the dilation) against shear displacement (fig 3-17).
3. Cyclic shear, +-2 mm three times (fig 3-18): the joint unloads along its
   initial stiffness and softens as it nears the opposite strength.
4. The block engine: a 1 m block pressed into a fixed base and moved along it
   (both prescribed, so the normal force grows with the dilation), against the
   point law driven by the same displacements.

The joint is a unit area (1 m of joint, unit thickness): forces in N are
stresses in Pa.  sigma_n = 1 MPa, k_s = 10 GPa/m, phi = 30 deg, phi_0 = 45 deg.
Writes PNGs, ``yielding_joint.h5`` (``jdem.io.load_history``) and ``results.md``
to experiments/results/yielding_joint/ (or --out).  float64, about a minute.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import pathlib
import platform
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jdem.io  # noqa: E402
from jdem import blocks as bk  # noqa: E402
from jdem.blocks import joint  # noqa: E402
from jdem.blocks.cycle import history_field  # noqa: E402

SIGMA_N, KS = 1e6, 1e10                  # Pa (N on a unit area), Pa/m
MU, MU0 = np.tan(np.deg2rad(30.0)), np.tan(np.deg2rad(45.0))
ROUGHNESS = (2e-4, 1e-3, 5e-3)           # m


def monotonic(u):
    return {r: {k: np.asarray(v) for k, v in
                joint.yielding_shear_path(u, SIGMA_N, KS, MU, MU0, r).items()}
            for r in ROUGHNESS}


def cyclic(amplitude=2e-3, cycles=3, n=400):
    leg = np.linspace(0.0, 1.0, n + 1)[1:]
    parts = [leg * amplitude]
    for _ in range(cycles):
        parts += [amplitude * (1 - 2 * leg), amplitude * (-1 + 2 * leg)]
    u = np.concatenate([[0.0]] + parts)
    out = joint.yielding_shear_path(u, SIGMA_N, KS, MU, MU0, 1e-3)
    return u, {k: np.asarray(v) for k, v in out.items()}


def shear_box(n_steps=6000, v=0.5, overlap=1e-4, kn=1e10, roughness=1e-3):
    """Two points of kn (each half of a 1 m face), the lid moved at v [m/s]."""
    base = bk.rectangle(-2.0, -1.0, 4.0, 1.0)
    lid = bk.rectangle(-0.5, -overlap, 1.0, 0.5)
    blocks = bk.make_blocks([base, lid], 2500.0, fixed=[0, 1], vel=[[0.0, 0.0], [v, 0.0]])
    state, config = bk.make_state(blocks)
    dt = 1e-6
    p = bk.make_params(kn=kn / 2, ks=KS / 2, friction=MU, cy_friction0=MU0,
                       cy_roughness=roughness, gravity=(0.0, 0.0), dt=dt)

    def observe(s, _):
        h = s.contacts.shear * s.contacts.valid[:, None]
        return dict(shear=jnp.abs(jnp.sum(history_field(h, "shear"))),
                    dilation=jnp.max(history_field(h, "dilation")))

    t0 = time.time()
    _, hist = bk.run(state, p, config, n_steps, record_every=20, observe=observe,
                     progress=False)
    wall = time.time() - t0
    u = np.arange(n_steps + 1) * v * dt
    ref = joint.yielding_shear_path(u, kn / 2 * overlap, KS / 2, MU, MU0, roughness,
                                    kn=kn / 2)
    ref = {k: np.asarray(v)[19::20] for k, v in ref.items()}
    return dict(u=u[20::20], shear=hist["shear"], dilation=hist["dilation"],
                ref_shear=2 * ref["shear"], ref_dilation=ref["dilation"],
                ref_normal=2 * ref["normal"], wall_s=wall)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out or pathlib.Path(__file__).parent / "results" / "yielding_joint")
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t_start = time.time()
    u = np.linspace(0.0, 0.02, 8001)
    mono = monotonic(u)
    uc, cyc = cyclic()
    box = shear_box()
    box_err = float(np.max(np.abs(box["shear"] - box["ref_shear"])) / np.max(box["ref_shear"]))

    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    ax = axes[0, 0]
    for r, o in mono.items():
        ax.plot(u[1:] * 1e3, o["shear"] / 1e6, label=f"R = {r * 1e3:g} mm")
    ax.axhline(SIGMA_N * MU0 / 1e6, color="k", ls=":", lw=1, label="σ_n tan φ_0")
    ax.axhline(SIGMA_N * MU / 1e6, color="k", ls="--", lw=1, label="σ_n tan φ (residual)")
    ax.set(xlabel="shear displacement [mm]", ylabel="shear stress [MPa]",
           title="constant σ_n = 1 MPa (000 fig 3-16)")
    ax.legend(fontsize=7)
    ax = axes[0, 1]
    for r, o in mono.items():
        ax.plot(u[1:] * 1e3, o["dilation"] * 1e3, label=f"R = {r * 1e3:g} mm")
    ax.set(xlabel="shear displacement [mm]", ylabel="normal displacement (dilation) [mm]",
           title="dilation (000 fig 3-17)")
    ax.legend(fontsize=7)
    ax = axes[1, 0]
    ax.plot(uc[1:] * 1e3, cyc["shear"] / 1e6, lw=1)
    ax.set(xlabel="shear displacement [mm]", ylabel="shear stress [MPa]",
           title="cyclic shear, R = 1 mm (000 fig 3-18)")
    ax = axes[1, 1]
    ax.plot(box["u"] * 1e3, box["ref_shear"] / 1e6, "k-", lw=2, label="point law")
    ax.plot(box["u"] * 1e3, box["shear"] / 1e6, "C1--", label="block engine")
    ax.plot(box["u"] * 1e3, box["ref_normal"] * MU / 1e6, "k:", lw=1,
            label="F_n tan φ (F_n grows with the dilation)")
    ax.set(xlabel="shear displacement [mm]", ylabel="shear force [MN]",
           title="shear box, lid held: constant normal stiffness")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "yielding_joint.png", dpi=120)
    plt.close("all")

    rows = []
    for r, o in mono.items():
        k = int(np.argmax(o["shear"]))
        rows.append((r, o["shear"][k] / SIGMA_N, u[k + 1], o["shear"][-1] / SIGMA_N,
                     o["dilation"][-1]))
    history = dict(u=u[1:], cyclic_u=uc[1:],
                   **{f"R{r * 1e3:g}mm_{k}": v for r, o in mono.items() for k, v in o.items()},
                   **{f"cyclic_{k}": v for k, v in cyc.items()},
                   **{f"box_{k}": v for k, v in box.items() if k != "wall_s"})
    attrs = dict(command=" ".join([pathlib.Path(sys.argv[0]).name] + list(argv or sys.argv[1:])),
                 date=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                 machine=f"{platform.node()} {platform.processor() or platform.machine()}",
                 sigma_n=SIGMA_N, ks=KS, mu=MU, mu_initial=MU0, box_rel_err=box_err)
    jdem.io.save_run(out / "yielding_joint.h5", history=history, attrs=attrs)
    lines = [f"# Continuously yielding joint in direct shear ({attrs['date']})", "",
             f"Command: `python experiments/{attrs['command']}`; machine {attrs['machine']}; "
             f"{time.time() - t_start:.0f} s.", "",
             "σ_n = 1 MPa, k_s = 10 GPa/m, φ = 30°, φ_0 = 45° (tan φ = 0.5774, tan φ_0 = 1), "
             "000 §3.4.1 item 5 with the initial angle φ_0 in place of the book's π/2 "
             "(with π/2 the strength is infinite at u_p = 0 and the joint never yields).", "",
             "| R [mm] | peak τ/σ_n | at u [mm] | τ/σ_n at 20 mm | dilation at 20 mm [mm] |",
             "|---|---|---|---|---|"]
    lines += [f"| {r * 1e3:g} | {a:.4f} | {b * 1e3:.3f} | {c:.4f} | {d * 1e3:.3f} |"
              for r, a, b, c, d in rows]
    lines += ["", f"Shear box in the block engine (two points, lid held, {box['u'].size * 20} "
              f"steps in {box['wall_s']:.1f} s): largest difference from the point law "
              f"{box_err:.2e} of its peak.", ""]
    (out / "results.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
