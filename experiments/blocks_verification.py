#!/usr/bin/env python
"""The block method's verification cases (000 ch. 2, 3, §9.2.1, §9.2.2), as figures.

    python experiments/blocks_verification.py            # full grids
    python experiments/blocks_verification.py --small    # coarse grids (a few minutes)
    python experiments/blocks_verification.py --out DIR

1. A block on an incline (joint friction 30 degrees): its acceleration against
   g (sin theta - mu cos theta) over the slope; zero below the friction angle.
2. The regimes of a block b x h on an incline (stays, slides, topples, both)
   over b / h and the slope: the simulation at onset against rigid-body
   dynamics (``jdem.blocks.cases.onset_regime``) and the static chart's lines
   (theta = phi, tan theta = b / h).
3. A wave across a joint (000 §9.2.1, fig 9-2): transmission and reflection
   coefficients (000 eq 9-2, 9-3 from int v^2 dt, eq 9-6) against
   omega Z / 2K, with the row's exact values and the continuum joint.
4. A jointed rock mass (two joint sets cut a 4 m x 2 m region) settling onto a
   fixed floor, coloured by speed, and its contact points by state (sticking,
   sliding, glued) with their normal forces.
5. The jointed basalt of 000 §9.2.2 under the book's biaxial cycle: staggered,
   square grid, and the grid with point stiffnesses only, against eq 9-7, 9-8 in
   the rigid-block limit.

Writes PNGs, ``blocks_verification.h5`` (jdem.io; reopen with
``jdem.io.load_history``) and ``results.md`` to experiments/results/blocks/
(or --out).  float64.
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
from jdem.blocks import cases  # noqa: E402
from jdem.plot import plot_blocks  # noqa: E402

PHI = 30.0


def incline_accelerations(slopes):
    out = []
    for slope in slopes:
        state, p, config = cases.incline(0.5, 0.5, slope, PHI)
        _, hist = bk.run(state, p, config, int(0.3 / float(p.dt)), record_every=50,
                         progress=False)
        t = hist["step"] * float(p.dt)
        late = t > 0.05
        out.append(2 * np.polyfit(t[late], hist["pos"][late, 1, 0], 2)[0])
    return np.array(out)


def regime_grid(ratios, slopes):
    names = ["stable", "slides", "topples", "both"]
    sim = np.zeros((len(ratios), len(slopes)), int)
    theory = np.zeros_like(sim)
    for a, bh in enumerate(ratios):
        for b, slope in enumerate(slopes):
            height = 0.8
            width = bh * height
            state, p, config = cases.incline(width, height, slope, PHI)
            _, hist = bk.run(state, p, config, int(0.5 / float(p.dt)), record_every=50,
                             progress=False)
            sim[a, b] = names.index(cases.observed_regime(hist, width, height))
            theory[a, b] = names.index(cases.onset_regime(width, height, slope, PHI))
    return sim, theory, names


def jointed_mass(n_steps):
    region = bk.rectangle(0.0, 0.0, 4.0, 2.0)
    polys = bk.cut_region(region, [bk.JointSet(30.0, 0.35, 0.05), bk.JointSet(100.0, 0.5)])
    floor = bk.rectangle(-1.0, -1.0, 6.0, 1.0)
    walls = [bk.rectangle(-1.0, 0.0, 1.0, 3.0), bk.rectangle(4.0, 0.0, 1.0, 3.0)]
    blocks = bk.make_blocks([floor] + walls + polys, 2600.0, fixed=[0, 1, 2])
    state, config = bk.make_state(blocks)
    p = bk.make_params(kn=2e9, friction=np.tan(np.deg2rad(30.0)), contact_damping=0.2,
                       local_damping=0.7)
    p = p._replace(dt=jnp.asarray(bk.recommended_timestep(blocks, p)))
    t0 = time.time()
    state, hist = bk.run(state, p, config, n_steps, record_every=max(1, n_steps // 40))
    wall = time.time() - t0
    _, force, _, _ = bk.contact_forces(state, p)
    weight = float(jnp.sum(blocks.mass[3:])) * 9.81
    reaction = -float(force[0, 1] + force[1, 1] + force[2, 1])
    speed = float(np.max(np.linalg.norm(np.asarray(state.blocks.vel), axis=1)))
    return state, p, hist, dict(blocks=len(polys), weight=weight, reaction=reaction,
                                steps=n_steps, wall_s=wall, max_speed=speed)


def basalt_cycle():
    """000 §9.2.2: the jointed basalt (staggered, square grid, and the grid with point
    stiffnesses only) held at 5 MPa along its rows and cycled 2 -> 10 -> 2 MPa
    across them; secant moduli per level against eq 9-7, 9-8 in the rigid limit."""
    joints = {k: v for k, v in cases.BASALT_JOINTS.items() if k != "spacing"}
    theory = cases.jointed_mass_moduli_rigid(**joints, s_s=0.2, s_n=0.2)
    sigma_n = np.array([2.0, 4.0, 6.0, 8.0, 10.0, 8.0, 6.0, 4.0, 2.0]) * 1e6
    runs = {}
    for name, stagger, face in (("staggered", True, True), ("grid", False, True),
                                ("grid, point stiffness only", False, False)):
        case = cases.jointed_mass(4, 5, stagger=stagger)
        if not face:
            p = case.params
            case = case._replace(params=p._replace(kn_face=jnp.zeros_like(p.kn_face),
                                                   ks_face=jnp.zeros_like(p.ks_face)))
        eps, _ = cases.load_jointed_mass(case, sigma_n, np.full(sigma_n.size, 5e6),
                                         steps_per_level=3000)
        runs[name] = dict(eps_n=eps[:, 0], eps_s=eps[:, 1],
                          E_n=np.diff(sigma_n) / np.diff(eps[:, 0]), E_s=5e6 / eps[:, 1])
    return dict(sigma_n=sigma_n, runs=runs, **theory)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--small", action="store_true", help="coarse grids")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out or pathlib.Path(__file__).parent / "results" / "blocks")
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t_start = time.time()
    slopes = np.array([20, 28, 32, 40, 50, 60.0]) if args.small else np.arange(20, 62, 4.0)
    acc = incline_accelerations(slopes)
    mu = np.tan(np.deg2rad(PHI))
    th = np.deg2rad(slopes)
    acc_theory = np.where(slopes > PHI, 9.81 * (np.sin(th) - mu * np.cos(th)), 0.0)
    print("incline accelerations", np.round(acc, 5), "theory", np.round(acc_theory, 5), flush=True)

    ratios = np.array([0.2, 0.5, 0.8, 1.2]) if args.small else np.array([0.15, 0.25, 0.35, 0.45, 0.7, 0.85, 1.0, 1.2])
    # slopes between the friction angle's and b/h's lines, so that no case sits on a boundary
    rslopes = np.array([20.0, 35.0, 50.0]) if args.small else np.arange(17.5, 61.0, 5.0)
    sim, theory, names = regime_grid(ratios, rslopes)
    agree = float(np.mean(sim == theory))
    print(f"regimes agree with onset dynamics in {agree:.0%} of {sim.size} cases", flush=True)
    differ = [(float(ratios[a]), float(rslopes[b]), names[sim[a, b]], names[theory[a, b]])
              for a, b in zip(*np.nonzero(sim != theory))]
    for d in differ:
        print("  b/h %.3g, slope %.3g: simulated %s, onset dynamics %s" % d, flush=True)

    wave_ratios = [0.25, 0.5, 1.0, 2.0] if args.small else [0.125, 0.25, 0.5, 1.0, 2.0, 4.0]
    waves = [cases.wave_across_joint(r) for r in wave_ratios]
    for r, d in zip(wave_ratios, waves):
        print(f"wave omega Z/2K = {r}: T {d['T']:.4f} (row {d['T_lattice']:.4f}, continuum "
              f"{d['T_continuum']:.4f}), R {d['R']:.4f} (row {d['R_lattice']:.4f}, "
              f"continuum {d['R_continuum']:.4f})", flush=True)

    mass_state, mass_params, mass_hist, mass_info = jointed_mass(30000 if args.small else 60000)
    print("jointed mass", mass_info, flush=True)

    basalt = basalt_cycle()
    for name, b in basalt["runs"].items():
        print(f"basalt {name}: E_n / (k_nh s_n) {np.round(b['E_n'] / basalt['E_n'], 4)}, "
              f"E_s / (k_nv s_s) {np.round(b['E_s'] / basalt['E_s'], 4)}", flush=True)

    # ---- figures
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ss = np.linspace(slopes.min(), slopes.max(), 200)
    ax.plot(ss, np.where(ss > PHI, 9.81 * (np.sin(np.deg2rad(ss)) - mu * np.cos(np.deg2rad(ss))),
                         0.0), "k-", label="g (sin θ − μ cos θ)")
    ax.plot(slopes, acc, "o", label="jdem blocks")
    ax.set(xlabel="slope θ [deg]", ylabel="acceleration [m/s²]",
           title=f"block on an incline, φ = {PHI:.0f}°")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "incline_acceleration.png", dpi=120)

    from matplotlib.colors import BoundaryNorm, ListedColormap

    cmap = ListedColormap(["#cccccc", "#66c2a5", "#fc8d62", "#8da0cb"])   # one colour per regime
    norm = BoundaryNorm([-0.5, 0.5, 1.5, 2.5, 3.5], cmap.N)
    fig, axs = plt.subplots(1, 2, figsize=(9, 3.8), sharey=True)
    for ax, grid, title in ((axs[0], sim, "simulated"), (axs[1], theory, "onset dynamics")):
        im = ax.pcolormesh(rslopes, ratios, grid, cmap=cmap, norm=norm, shading="nearest")
        ax.axvline(PHI, color="k", lw=1)
        ax.plot(rslopes, np.tan(np.deg2rad(rslopes)), "k--", lw=1)
        ax.set(xlabel="slope θ [deg]", title=title, ylim=(ratios.min(), ratios.max()))
    axs[0].set_ylabel("b / h")
    cb = fig.colorbar(im, ax=axs, ticks=range(4))
    cb.ax.set_yticklabels(names)
    fig.suptitle("block on an incline (lines: static chart θ = φ, tan θ = b/h)")
    fig.savefig(out / "incline_regimes.png", dpi=120)

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    x = np.array(wave_ratios)
    xx = np.geomspace(x.min(), x.max(), 200)
    ax.semilogx(xx, 1 / np.sqrt(1 + xx ** 2), "k-", label="T continuum")
    ax.semilogx(xx, xx / np.sqrt(1 + xx ** 2), "k--", label="R continuum")
    ax.semilogx(x, [d["T_lattice"] for d in waves], "s", mfc="none", label="T block row (exact)")
    ax.semilogx(x, [d["R_lattice"] for d in waves], "D", mfc="none", label="R block row (exact)")
    ax.semilogx(x, [d["T"] for d in waves], "o", label="T measured")
    ax.semilogx(x, [d["R"] for d in waves], "^", label="R measured")
    from matplotlib.ticker import NullFormatter

    ax.set_xticks(x)
    ax.set_xticklabels([f"{r:g}" for r in x])
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set(xlabel="ω Z / 2K", ylabel="coefficient", title="wave across a joint (000 §9.2.1)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "wave_across_joint.png", dpi=120)

    fig, axs = plt.subplots(2, 1, figsize=(7, 7))
    title = f"jointed mass, {mass_info['blocks']} blocks, after {mass_info['steps']} steps"
    plot_blocks(mass_state, mass_params, color="speed", title=title, ax=axs[0])
    plot_blocks(mass_state, mass_params, color="contacts", title="contact states", ax=axs[1])
    fig.tight_layout()
    fig.savefig(out / "jointed_mass.png", dpi=120)
    plt.close("all")

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for name, b in basalt["runs"].items():
        ax.plot(b["eps_n"] * 1e6, basalt["sigma_n"] / 1e6, "o-", ms=3, label=name)
    e0 = basalt["runs"]["grid"]["eps_n"][0]
    ee = np.array([e0, e0 + 8e6 / basalt["E_n"]])
    ax.plot(ee * 1e6, [2.0, 10.0], "k--", lw=1, label="E_n = k_nh s_n (eq 9-7, rigid limit)")
    ax.set(xlabel="strain across the horizontal joints [1e-6]", ylabel="σ_n [MPa]",
           title="jointed basalt, 5 MPa along the rows (000 §9.2.2)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "jointed_basalt.png", dpi=120)
    plt.close("all")

    history = dict(incline_slope=slopes, incline_accel=acc, incline_accel_theory=acc_theory,
                   regime_ratio=ratios, regime_slope=rslopes, regime_sim=sim,
                   regime_theory=theory, wave_ratio=x,
                   wave_T=np.array([d["T"] for d in waves]),
                   wave_R=np.array([d["R"] for d in waves]),
                   wave_T_lattice=np.array([d["T_lattice"] for d in waves]),
                   wave_R_lattice=np.array([d["R_lattice"] for d in waves]),
                   wave_T_continuum=np.array([d["T_continuum"] for d in waves]),
                   wave_R_continuum=np.array([d["R_continuum"] for d in waves]),
                   mass_pos=mass_hist["pos"], mass_angle=mass_hist["angle"],
                   basalt_sigma_n=basalt["sigma_n"],
                   **{f"basalt_{name.split(',')[0]}{'_point' if ',' in name else ''}_{k}": v
                      for name, b in basalt["runs"].items() for k, v in b.items()})
    attrs = dict(command=" ".join([pathlib.Path(sys.argv[0]).name] + list(argv or sys.argv[1:])),
                 date=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                 machine=f"{platform.node()} {platform.processor() or platform.machine()}",
                 regime_names=names, regimes_agree=agree, **{f"mass_{k}": v for k, v in
                                                              mass_info.items()})
    jdem.io.save_run(out / "blocks_verification.h5", history=history, attrs=attrs)
    lines = [f"# Block method verification ({attrs['date']})", "",
             f"Command: `python experiments/{attrs['command']}`; machine {attrs['machine']}; "
             f"{time.time() - t_start:.0f} s.", "",
             "| slope [deg] | acceleration | g (sin − μ cos) |", "|---|---|---|"]
    lines += [f"| {s:.0f} | {a:.5f} | {b:.5f} |" for s, a, b in zip(slopes, acc, acc_theory)]
    lines += ["", f"Regimes (b/h x slope grid of {sim.size}): the simulation agrees with "
              f"onset dynamics in {agree:.0%} of the cases."]
    lines += [f"- b/h {a:.3g}, slope {b:.3g}: simulated {c}, onset dynamics {d}"
              for a, b, c, d in differ]
    lines += ["",
              "| ω Z / 2K | T | T row | T continuum | R | R row | R continuum |",
              "|---|---|---|---|---|---|---|"]
    lines += [f"| {r} | {d['T']:.4f} | {d['T_lattice']:.4f} | {d['T_continuum']:.4f} | "
              f"{d['R']:.4f} | {d['R_lattice']:.4f} | {d['R_continuum']:.4f} |"
              for r, d in zip(wave_ratios, waves)]
    lines += ["", "Jointed basalt of 000 §9.2.2 (4 x 5 blocks of 20 cm, the book's joint "
              "stiffnesses, rollers at base and wall), 5 MPa along the rows, σ_n 2 → 10 → 2 MPa: "
              f"moduli between levels over E_n = k_nh s_n = {basalt['E_n'] / 1e9:.1f} GPa and "
              f"E_s = k_nv s_s = {basalt['E_s'] / 1e9:.1f} GPa (eq 9-7, 9-8, rigid limit).", "",
              "| joints | E_n / (k_nh s_n) per step | E_s / (k_nv s_s) per level |", "|---|---|---|"]
    lines += [f"| {name} | {', '.join(f'{x:.4f}' for x in b['E_n'] / basalt['E_n'])} | "
              f"{', '.join(f'{x:.4f}' for x in b['E_s'] / basalt['E_s'])} |"
              for name, b in basalt["runs"].items()]
    lines += ["", f"Jointed mass: {mass_info['blocks']} blocks, {mass_info['steps']} steps in "
              f"{mass_info['wall_s']:.1f} s (compile included); floor and walls carry "
              f"{mass_info['reaction'] / mass_info['weight']:.4f} of the weight; fastest block "
              f"{mass_info['max_speed']:.2e} m/s.", ""]
    (out / "results.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
