#!/usr/bin/env python
"""Throughput of the block method's jitted step loop: block-steps per second.

    python experiments/blocks_benchmark.py                  # ~1,000 and ~4,000 blocks
    python experiments/blocks_benchmark.py --sizes 1000 --x64
    python experiments/blocks_benchmark.py --quick          # ~250 blocks, short chunks
    python experiments/blocks_benchmark.py --corner-radius 0.0002 --yielding  # R must fit the slivers

The work: a W x H region (aspect 2) cut by two joint sets (dip 30 degrees and
100 degrees, spacings chosen for the requested number of blocks) into convex
blocks resting on a fixed floor between fixed walls, under gravity, joint
friction 30 degrees, contact dashpots 0.2 of critical, local damping 0.7: a
jointed rock mass settling, the block method's typical quasi-static run.
``--corner-radius`` rounds the corners (000 eq 3-34, 3-35), ``--yielding``
makes the joints continuously yielding (phi_0 = 40 degrees, R = 1 mm); the
loop takes the static paths ``jdem.blocks.run`` takes for these parameters
(``sharp_corners``, ``coulomb_only``).  The
first chunk is run and discarded (compilation and the first contacts); then
``--chunks`` chunks of ``--chunk-steps`` steps of ``jdem.blocks.rollout`` are
timed with ``block_until_ready``; the median chunk gives the rate.  Then one
step's parts are timed alone: the pair geometry (narrow phase), the joint law
and scatter (``contact_forces``), and the whole step.

Results go to stdout and ``<out>/blocks_benchmark.json`` / ``.md`` with the
machine, date and command.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import pathlib
import platform
import sys
import time


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=None, help="approximate block counts")
    ap.add_argument("--x64", action="store_true", help="float64 (default float32)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--corner-radius", type=float, default=0.0, help="[m]")
    ap.add_argument("--yielding", action="store_true", help="continuously yielding joints")
    ap.add_argument("--chunk-steps", type=int, default=None)
    ap.add_argument("--chunks", type=int, default=None)
    ap.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "blocks"))
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", bool(args.x64))
    import jax.numpy as jnp
    import numpy as np

    from jdem import blocks as bk
    from jdem.blocks import cycle, detect

    sizes = args.sizes or ([250] if args.quick else [1000, 4000])
    chunk = args.chunk_steps or (50 if args.quick else 200)
    n_chunks = args.chunks or (3 if args.quick else 5)
    dtype = jnp.float64 if args.x64 else jnp.float32
    rows = []
    for target in sizes:
        width, height = 4.0, 2.0
        spacing = float(np.sqrt(width * height / target))       # two sets: ~target blocks
        polys = bk.cut_region(bk.rectangle(0.0, 0.0, width, height),
                              [bk.JointSet(30.0, spacing, 0.013), bk.JointSet(100.0, spacing)])
        frame = [bk.rectangle(-1.0, -1.0, width + 2.0, 1.0), bk.rectangle(-1.0, 0.0, 1.0, 3.0),
                 bk.rectangle(width, 0.0, 1.0, 3.0)]
        blocks = bk.make_blocks(frame + polys, 2600.0, fixed=[0, 1, 2], dtype=dtype)
        state, config = bk.make_state(blocks)
        p = bk.make_params(kn=2e9, friction=np.tan(np.deg2rad(30.0)), contact_damping=0.2,
                           local_damping=0.7, corner_radius=args.corner_radius,
                           cy_friction0=np.tan(np.deg2rad(40.0)) if args.yielding else 0.0,
                           cy_roughness=1e-3, dtype=dtype)
        p = p._replace(dt=jnp.asarray(bk.recommended_timestep(blocks, p), dtype))
        paths = dict(sharp_corners=args.corner_radius == 0, coulomb_only=not args.yielding)
        t0 = time.perf_counter()
        state, _ = bk.rollout(state, p, config, 1, chunk, **paths)
        jax.block_until_ready(state)
        first = time.perf_counter() - t0
        times = []
        for _ in range(n_chunks):
            t0 = time.perf_counter()
            state, _ = bk.rollout(state, p, config, 1, chunk, **paths)
            jax.block_until_ready(state)
            times.append(time.perf_counter() - t0)
        med = float(np.median(times))
        n_blocks = len(polys)

        def best_of(fn, *a, repeats=10):
            jax.block_until_ready(fn(*a))
            ts = []
            for _ in range(repeats):
                t1 = time.perf_counter()
                jax.block_until_ready(fn(*a))
                ts.append(time.perf_counter() - t1)
            return float(min(ts))

        radius = 0.0 if paths["sharp_corners"] else p.corner_radius
        geometry = jax.jit(lambda s: detect.pair_geometry(s.blocks, s.contacts.i, s.contacts.j,
                                                          radius))
        forces = jax.jit(lambda s, q: cycle.contact_forces(s, q, **paths)[1])
        one = jax.jit(lambda s, q: cycle.step(s, q, config, **paths))
        row = dict(blocks=n_blocks, pairs=int(state.contacts.i.shape[0]),
                   listed=int(jnp.sum(state.contacts.valid)), dtype=str(np.dtype(dtype)),
                   corner_radius=args.corner_radius,
                   joint="yielding" if args.yielding else "Coulomb",
                   first_chunk_s=first, chunk_steps=chunk, median_chunk_s=med,
                   steps_per_s=chunk / med, block_steps_per_s=n_blocks * chunk / med,
                   geometry_us=1e6 * best_of(geometry, state),
                   contact_forces_us=1e6 * best_of(forces, state, p),
                   step_us=1e6 * best_of(one, state, p),
                   rebuilds=int(state.contacts.n_builds))
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = dict(date=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="minutes"),
                machine=f"{platform.machine()} {os.cpu_count()} cores, {platform.platform()}",
                devices=[str(d) for d in jax.devices()], jax=jax.__version__,
                command=" ".join(["python", "experiments/blocks_benchmark.py"] +
                                 list(argv if argv is not None else sys.argv[1:])))
    stem = "blocks_benchmark" + ("_x64" if args.x64 else "") + \
        (f"_r{args.corner_radius:g}" if args.corner_radius else "") + \
        ("_yielding" if args.yielding else "")
    (out / f"{stem}.json").write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))
    lines = [f"# Block method throughput ({meta['date']})", "",
             f"`{meta['command']}` on {meta['machine']}, jax {meta['jax']}, {meta['devices']}.",
             "", "| blocks | dtype | corner radius [m] | joint | listed pairs | steps/s | "
             "block-steps/s | geometry [us] | contact forces [us] | step [us] |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['blocks']} | {r['dtype']} | {r['corner_radius']:g} | {r['joint']} | "
              f"{r['listed']} | {r['steps_per_s']:.0f} | "
              f"{r['block_steps_per_s']:.3g} | {r['geometry_us']:.0f} | "
              f"{r['contact_forces_us']:.0f} | {r['step_us']:.0f} |" for r in rows]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
