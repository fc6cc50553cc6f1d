#!/usr/bin/env python
"""Tunnel with free-field boundaries (001 §4.2, Fig 17, 18), reduced.

    python experiments/tunnel_free_field.py            # 5 m discs (3,600 in the main model)
    python experiments/tunnel_free_field.py --small    # 10 m discs
    python experiments/tunnel_free_field.py --out DIR

A 300 m x 300 m model with a circular tunnel (radius 20 m, centre at mid
height) is hit from the base by the SV pulse of 001 eq 12 (M = 0.5 m/s,
T = 0.5 s), entering through a viscous input boundary (001 eq 6).  The
lateral boundaries are free-field boundaries (001 eq 21): dashpots tied to a
one-disc-wide free-field column on each side (same base input) plus the
column's stress.  Discs are equal, in a square arrangement (Pattern A rather
than the seed's Pattern C), with fixed rotations and bond nu = 0, so the
lattice behaves like an elastic solid with E = rho c_P^2, nu = 0 for waves
along its axes (c_P = 1000 m/s, c_S = 707 m/s, rho = 2500 kg/m^3).

The seed checks its result against FLAC; here the reference is the same
tunnel in a model five times as wide (1500 m) with roller lateral boundaries
(y fixed), whose waves scattered by the tunnel come back from the far sides
only after the record.  Also run: the same 300 m model with plain viscous
lateral boundaries (no free field).  Monitors: horizontal velocity at the
left side-wall centre (P1) and at the crown (P2).

Writes tunnel_velocity.png and tunnel.h5 to experiments/results/tunnel_free_field/
(or --out) and prints the RMS differences from the wide reference.
"""
from __future__ import annotations

import argparse
import math
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
from jdem.simulate import make_state, run  # noqa: E402

RHO, CP = 2500.0, 1000.0
CS = CP / math.sqrt(2.0)
SIZE, TUNNEL_R = 300.0, 20.0
M, T = 0.5, 0.5


def build(radius, *, width, lateral, t_end):
    """The model (main width ``width``) with lateral boundaries ``lateral`` in
    ("free-field", "viscous", "roller").  Returns (state, params, config, cond,
    monitors, n_steps)."""
    d = 2.0 * radius
    nx, ny = int(round(width / d)), int(round(SIZE / d))
    x0 = -(width - SIZE) / 2.0
    pos, rad = waves.square_packing(nx, ny, radius, origin=(x0, 0.0))
    centre = np.array([SIZE / 2.0, SIZE / 2.0])
    keep = np.linalg.norm(pos - centre, axis=1) > TUNNEL_R
    pos, rad = pos[keep], rad[keep]
    n_main = len(rad)
    columns = []
    if lateral == "free-field":
        for xc in (x0 - width, x0 + 2 * width):           # far from the main model
            cp, cr = waves.square_packing(1, ny, radius, origin=(xc, 0.0))
            columns.append(np.arange(len(rad), len(rad) + ny))
            pos, rad = np.vstack([pos, cp]), np.concatenate([rad, cr])
    parts, bonds = waves.lattice(pos, rad, waves.square_density(RHO), fix_rotation=True)
    main = np.arange(n_main)
    params = waves.wave_params(CP, RHO, bond_poisson=0.0)
    if lateral == "roller":
        for side in ("left", "right"):
            idx = waves.boundary_particles(parts, side, among=main).index
            parts = parts._replace(fixed_vel=parts.fixed_vel.at[idx, 1].set(True))
    state, config = make_state(parts, bonds=bonds)
    params = params._replace(dt=jax.numpy.asarray(waves.stable_dt(state, params, config, 0.9)))

    time_, vel, disp = waves.cosine_pulse(M, T)
    v_in, u_in = waves.incident_wave(time_, vel, disp, (1.0, 0.0))   # SV: along +x
    kw = dict(density=RHO, c_p=CP, c_s=CS)
    base = waves.boundary_particles(parts, "bottom", among=main)
    bounds = [waves.make_boundary(base, parts, incident_vel=v_in, incident_disp=u_in, **kw)]
    for col in columns:
        foot = waves.BoundarySet(index=col[:1], width=2 * rad[col[:1]], normal=np.array([0.0, -1.0]),
                              tangent=np.array([1.0, 0.0]), position=0.0)
        bounds.append(waves.make_boundary(foot, parts, incident_vel=v_in, incident_disp=u_in, **kw))
    if lateral in ("free-field", "viscous"):
        for k, side in enumerate(("left", "right")):
            bset = waves.boundary_particles(parts, side, among=main)
            ff = (waves.free_field_coupling(parts, bonds, bset, columns[k])
                  if lateral == "free-field" else None)
            bounds.append(waves.make_boundary(bset, parts, free_field=ff, **kw))
    cond = waves.Conditions(boundaries=tuple(bounds))
    state, cond = waves.activate(state, params, config, cond)
    p1 = centre - [TUNNEL_R + radius, 0.0]
    p2 = centre + [0.0, TUNNEL_R + radius]
    monitors = waves.Monitors(waves.monitor_groups(parts, [p1, p2]))
    n_steps = int(math.ceil(t_end / float(params.dt) / 100)) * 100
    return state, params, config, cond, monitors, n_steps


def simulate(radius, width, lateral, t_end):
    t0 = time.perf_counter()
    state, params, config, cond, mon, n = build(radius, width=width, lateral=lateral, t_end=t_end)
    res = run(state, params, config, n, record_every=2, observe=mon, chunk_steps=1000,
              progress=False, boundary=(waves.apply_conditions, cond))
    n_disc = int(np.sum(np.asarray(state.particles.valid)))
    wall = time.perf_counter() - t0
    print(f"  {lateral:10s} width {width:6.0f} m: {n_disc} discs, {n} steps, {wall:.1f} s")
    return dict(time=res.history["time"], vx=res.history["vel"][:, :, 0], wall=wall, n=n_disc)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--small", action="store_true", help="10 m discs instead of 5 m")
    ap.add_argument("--out", default=None, help="output directory")
    ap.add_argument("--t-end", type=float, default=1.5, help="record length [s]")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out or pathlib.Path(__file__).parent / "results" / "tunnel_free_field")
    out.mkdir(parents=True, exist_ok=True)
    radius = 5.0 if args.small else 2.5
    runs = {name: simulate(radius, width, lateral, args.t_end) for name, width, lateral in (
        ("free_field", SIZE, "free-field"), ("viscous", SIZE, "viscous"),
        ("reference", 5 * SIZE, "roller"))}
    ref = runs["reference"]
    summary = {}
    for name in ("free_field", "viscous"):
        n = min(len(ref["time"]), len(runs[name]["time"]))
        diff = runs[name]["vx"][:n] - ref["vx"][:n]
        rel = np.sqrt(np.mean(diff ** 2, axis=0)) / np.sqrt(np.mean(ref["vx"][:n] ** 2, axis=0))
        summary[name] = rel
        print(f"{name}: RMS difference from the wide reference P1 {rel[0]:.3f}, P2 {rel[1]:.3f}")
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for k, label in enumerate(("P1 (side wall)", "P2 (crown)")):
        ax = axes[k]
        ax.plot(ref["time"], ref["vx"][:, k], "k-", lw=2, label="wide model (reference)")
        ax.plot(runs["free_field"]["time"], runs["free_field"]["vx"][:, k], "r--",
                label=f"free-field boundary (RMS diff {summary['free_field'][k]:.1%})")
        ax.plot(runs["viscous"]["time"], runs["viscous"]["vx"][:, k], "b:",
                label=f"viscous boundary only (RMS diff {summary['viscous'][k]:.1%})")
        ax.set_ylabel(f"{label}\nv_x [m/s]")
        ax.legend(fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"Tunnel, SV pulse from the base (001 §4.2), discs D = {2 * radius:g} m")
    fig.tight_layout()
    fig.savefig(out / "tunnel_velocity.png", dpi=120)
    hist = {}
    for name, r in runs.items():
        hist[f"{name}_time"] = r["time"]
        hist[f"{name}_vx"] = r["vx"]
    attrs = dict(disc_diameter=2 * radius, t_end=args.t_end,
                 rms_free_field_P1=float(summary["free_field"][0]),
                 rms_free_field_P2=float(summary["free_field"][1]),
                 rms_viscous_P1=float(summary["viscous"][0]),
                 rms_viscous_P2=float(summary["viscous"][1]),
                 wall_time_s=float(sum(r["wall"] for r in runs.values())))
    jdem.io.save_run(out / "tunnel.h5", history=hist, attrs=attrs)
    print(f"wrote {out / 'tunnel_velocity.png'} and {out / 'tunnel.h5'}")


if __name__ == "__main__":
    main()
