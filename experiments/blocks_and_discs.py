#!/usr/bin/env python
"""Discs and blocks in one model (jdem.blocks.coupling): a rigid block dropped
onto a bed of discs in a container made of blocks.

    python experiments/blocks_and_discs.py [--out DIR] [--small]

A container of three fixed blocks (a base and two side walls, 1 m inside)
holds a bed of discs (radii 15-25 mm, settled under gravity first); a free
0.3 m square block is then dropped onto it from 0.2 m above the bed and comes
to rest.  Checked at the end (the model's static balance): the discs push the
free block up with its weight, and the container carries the weight of the
block and the discs.  Writes ``blocks_and_discs.png`` (the final state, discs
and blocks coloured by speed, and the force on the free block and on the
container against time), ``blocks_and_discs.h5`` (``jdem.io.load_history``)
and ``results.md`` to experiments/results/blocks_and_discs/ (or --out).
float64; about two minutes (``--small``: fewer discs, under a minute).
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

import jdem  # noqa: E402
import jdem.io  # noqa: E402
from jdem import blocks as bk  # noqa: E402
from jdem.blocks import coupling  # noqa: E402

G = 9.81
DENSITY = 2600.0                 # kg/m^3 (discs and blocks; 2D: per metre of thickness)
KN = 5e7                         # N/m, disc-disc and disc-block normal stiffness
FRICTION = 0.5


def container():
    """Base (top at y = 0) and two side walls (inner faces at x = 0 and 1 m),
    then the free block (index 3), placed later."""
    return [bk.rectangle(-0.2, -0.2, 1.4, 0.2), bk.rectangle(-0.2, 0.0, 0.2, 1.5),
            bk.rectangle(1.0, 0.0, 0.2, 1.5)]


def bed(n_columns, n_rows, seed=1):
    """Discs on a loose grid inside the container, radii uniform in 15-25 mm."""
    rng = np.random.default_rng(seed)
    pitch = 1.0 / n_columns
    x = (np.arange(n_columns) + 0.5) * pitch
    y = 0.03 + np.arange(n_rows) * 0.052
    pos = np.array([[xi + rng.uniform(-0.003, 0.003), yi] for yi in y for xi in x])
    return pos, rng.uniform(0.015, 0.025, len(pos))


def build(pos, radius, block_y):
    polys = container() + [bk.rectangle(0.35, block_y, 0.3, 0.3)]
    blocks = bk.make_blocks(polys, DENSITY, fixed=[0, 1, 2])
    parts = jdem.make_particles(pos, radius, density=DENSITY)
    state, config = jdem.make_state(parts)
    bstate, bconfig = bk.make_state(blocks)
    model = coupling.couple(state, bstate)
    params = jdem.make_params(dim=2, kn=KN, friction=FRICTION, gravity=[0.0, -G],
                              contact_damping=0.3, local_damping=0.5)
    bparams = bk.make_params(kn=KN, friction=FRICTION, gravity=(0.0, -G),
                             contact_damping=0.3, local_damping=0.5)
    dt = 0.3 * min(float(jdem.timestep.nominal_critical_timestep(parts, params, config)),
                   coupling.contact_limit(model, params, config))
    return (model, params._replace(dt=jnp.asarray(dt)), bparams._replace(dt=jnp.asarray(dt)),
            config, bconfig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="experiments/results/blocks_and_discs")
    ap.add_argument("--small", action="store_true")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    n_col, n_row = (12, 3) if args.small else (18, 5)
    pos, radius = bed(n_col, n_row)
    top = float(np.max(pos[:, 1] + radius))
    # the free block starts far above the bed while the bed settles, then drops
    model, params, bparams, config, bconfig = build(pos, radius, 5.0)
    b = model.blocks.blocks
    parked = b._replace(fixed=b.fixed.at[3].set(True))
    model = model._replace(blocks=model.blocks._replace(blocks=parked))
    dt = float(params.dt)
    settle = int(0.6 / dt)
    model, _, config, bconfig = coupling.run(model, params, bparams, config, bconfig, settle,
                                             record_every=max(settle // 20, 1))
    bed_top = float(np.max(np.asarray(model.discs.particles.pos[:, 1] +
                                      model.discs.particles.radius)))
    b = model.blocks.blocks
    drop = b._replace(fixed=b.fixed.at[3].set(False),
                      pos=b.pos.at[3].set(jnp.asarray([0.5, bed_top + 0.2 + 0.15])))
    model = model._replace(blocks=model.blocks._replace(blocks=drop))
    n_steps = int(1.5 / dt)
    every = max(n_steps // 300, 1)
    model, hist, config, bconfig = coupling.run(model, params, bparams, config, bconfig,
                                                n_steps, record_every=every)
    t = (np.arange(len(hist["step"])) + 1) * every * dt
    m_block = float(model.blocks.blocks.mass[3])
    m_discs = float(np.sum(np.asarray(model.discs.particles.mass)))
    on = hist["on_blocks"]                         # (R, K, 2)
    free_up = on[:, 3, 1] / (m_block * G)
    container_down = -np.sum(on[:, :3, 1], axis=1) / ((m_block + m_discs) * G)
    sideways = np.sum(on[:, :3, 0], axis=1) / ((m_block + m_discs) * G)
    settlement = hist["block_pos"][:, 3, 1]
    final = dict(free_block=float(free_up[-1]), container=float(container_down[-1]),
                 sideways=float(sideways[-1]), block_speed=float(np.linalg.norm(
                     hist["block_vel"][-1, 3])))
    print(f"settled: force on the free block / its weight {final['free_block']:.5f}, "
          f"on the container / total weight {final['container']:.5f} "
          f"(horizontal sum {final['sideways']:.1e}), block speed {final['block_speed']:.2e} m/s")
    jdem.io.save_run(out / "blocks_and_discs.h5", history=dict(
        time=t, on_blocks=on, block_pos=hist["block_pos"], block_angle=hist["block_angle"],
        disc_pos=hist["disc_pos"][-1], disc_radius=np.asarray(model.discs.particles.radius)),
        attrs=dict(discs=int(len(radius)), dt=dt, mass_block=m_block, mass_discs=m_discs,
                   **{f"final_{k}": v for k, v in final.items()}))
    _plot(model, t, free_up, container_down, settlement, out / "blocks_and_discs.png")
    wall = time.time() - t0
    cmd = "python experiments/blocks_and_discs.py" + (" --small" if args.small else "")
    (out / "results.md").write_text(
        f"# Discs and blocks in one model: a block dropped onto a bed of discs\n\n"
        f"{_dt.datetime.now(_dt.timezone.utc):%Y-%m-%dT%H:%M}Z, {platform.machine()}, "
        f"JAX {jax.__version__}, float64, {wall:.0f} s\n\nCommand: `{cmd}`\n\n"
        f"{len(radius)} discs (r 15-25 mm), a 0.3 m block dropped 0.2 m onto the bed, "
        f"{n_steps} steps of {dt:.3g} s after {settle} steps of settling.\n\n"
        f"| at the end | value |\n|---|---|\n"
        f"| upward force of the discs on the free block / its weight | {final['free_block']:.5f} |\n"
        f"| downward force on the container / weight of block and discs | {final['container']:.5f} |\n"
        f"| horizontal force on the container / total weight | {final['sideways']:.1e} |\n"
        f"| free block speed | {final['block_speed']:.2e} m/s |\n\n"
        f"![](blocks_and_discs.png)\n")
    print(f"wrote {out}/blocks_and_discs.png, .h5, results.md ({wall:.0f} s)")
    return final


def _plot(model, t, free_up, container_down, settlement, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    from jdem import plot

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.5))
    plot.plot_blocks(model.blocks, None, ax=ax0, title="final state (blocks by speed)")
    p = model.discs.particles
    discs = [Circle(xy, r) for xy, r in zip(np.asarray(p.pos), np.asarray(p.radius))]
    pc = PatchCollection(discs, facecolor="tab:orange", edgecolor="k", linewidth=0.3)
    ax0.add_collection(pc)
    ax0.set_aspect("equal")
    ax0.set_xlim(-0.25, 1.25)
    ax0.set_ylim(-0.25, 1.0)
    ax1.plot(t, free_up, label="discs on the free block / its weight")
    ax1.plot(t, container_down, label="on the container / weight of block + discs")
    ax1.axhline(1.0, color="k", lw=0.5)
    ax1.set_xlabel("time after the drop [s]")
    ax1.set_ylabel("force / weight")
    ax1.set_ylim(-0.2, 3.0)
    ax1.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
