#!/usr/bin/env python
"""Throughput of jdem's jitted step loop on dense packings, with a cost breakdown.

    python experiments/benchmark.py                 # 2D 10,000 discs + 3D 20,000 spheres
    python experiments/benchmark.py --quick         # 1,000 / 2,000 particles, smoke run
    python experiments/benchmark.py --dim 3 --n 1000000 --device-label "H100"
    python experiments/benchmark.py --sizes 10000 20000 --x64
    python experiments/benchmark.py --sweep         # also re-run under other XLA_FLAGS / 1 core
    python experiments/benchmark.py --bonded --yade # bonded 3D UCS loop, float32 and float64,
                                                    # and YADE on the same spheres and bonds

Every case is a dense, deterministic (seeded NumPy) packing: a triangular lattice
(2D) or an FCC lattice (3D) of spacing a little below the mean diameter, radii
uniform in [0.8 r, r] (r = 1 mm), a small positional jitter, rigid walls all
round (``jdem.make_walls``), no gravity, the linear contact law, friction 0.5,
density 2500 and random initial velocities.  The overlaps left by the lattice
and the initial velocities keep the particles moving, so the neighbour list is
refreshed inside the step (``lax.cond`` in ``jdem.integrate.step``) several
times during the timed window; the report gives the count from
``state.contacts.n_builds``.

Timing: one ``jax.jit`` of a ``lax.fori_loop`` over ``integrate.step`` for K
steps is compiled (timed separately), run once as a warm-up, then run for
several consecutive chunks, each timed with ``block_until_ready``.  Throughputs
are given for the median chunk, the best chunk and the whole window.  Then
each part of the step is timed on its own (jitted, best of repeats, same
packing): contact forces, wall forces, the rebuild test, the rebuild, the whole
step, plus a breakdown of the rebuild and of the contact kernel.

Results go to stdout, ``<out>/benchmark.json`` and ``<out>/benchmark.md``
(overwritten on every run).  XLA flags must be set before JAX starts, so
``--xla-flags`` and ``--cpus`` are applied here before ``import jax``.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# ----------------------------------------------------------------------------- arguments
DEFAULT_SIZES = {2: 10_000, 3: 20_000}
QUICK_SIZES = {2: 1_000, 3: 2_000}
SWEEP_FLAGS = [  # (label, XLA_FLAGS to add, cpus to pin or None)
    ("default", "", None),
    ("ynn fusion off", "--xla_cpu_experimental_ynn_fusion_type=", None),
    ("eigen single-thread", "--xla_cpu_multi_thread_eigen=false", None),
    ("fast math", "--xla_cpu_enable_fast_math=true", None),
    ("one core (taskset-like)", "", "0"),
    ("one core, ynn off", "--xla_cpu_experimental_ynn_fusion_type=", "0"),
]


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sizes (1,000 / 2,000), short chunks")
    ap.add_argument("--out", default="experiments/results", help="folder for benchmark.json / .md")
    ap.add_argument("--x64", action="store_true", help="float64 (default float32)")
    ap.add_argument("--sizes", type=int, nargs="+", metavar="N",
                    help="particle counts: 'N2D N3D' (0 skips a case), or one N for --dim")
    ap.add_argument("--dim", type=int, choices=(2, 3), help="run only this dimension")
    ap.add_argument("--n", type=int, help="particle count for --dim")
    ap.add_argument("--device-label", default="", help="free text naming the machine for the report")
    ap.add_argument("--chunk-steps", type=int, help="steps per jitted chunk (default 100; quick 50)")
    ap.add_argument("--chunks", type=int, help="timed chunks (default 5; quick 3)")
    ap.add_argument("--repeats", type=int, help="repeats per profiled function (default 15; quick 3)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--spacing", type=float, default=0.97,
                    help="lattice spacing / mean diameter (default 0.97: dense, overlapping)")
    ap.add_argument("--jitter", type=float, default=0.05, help="positional jitter / spacing")
    ap.add_argument("--kn", type=float, default=1e5, help="normal stiffness [N/m] (ks = kn)")
    ap.add_argument("--v0", type=float, default=0.1, help="initial velocity spread per component [m/s]")
    ap.add_argument("--skin", type=float, default=None,
                    help="neighbour skin [m] (default: jdem's, 0.3 x mean radius)")
    ap.add_argument("--no-profile", action="store_true", help="skip the per-function breakdown")
    ap.add_argument("--detail", dest="detail", action="store_true", default=None,
                    help="also break down the rebuild and the contact kernel (default: on unless --quick)")
    ap.add_argument("--no-detail", dest="detail", action="store_false")
    ap.add_argument("--xla-flags", default="", help="appended to XLA_FLAGS before JAX starts; write it as --xla-flags=--xla_...")
    ap.add_argument("--cpus", default=None,
                    help="pin the process to these CPUs before JAX starts, e.g. '0' or '0,1'")
    ap.add_argument("--sweep", action="store_true",
                    help="also re-run every case in child processes under other XLA flags / 1 core")
    ap.add_argument("--bonded", action="store_true",
                    help="the bonded 3D benchmark (bench/bonded.py): a UCS loop on N bonded spheres, "
                         "timed in float32 and float64; writes bonded_benchmark.json / .md")
    ap.add_argument("--bonded-n", type=int, default=20_000, help="spheres of the bonded specimen")
    ap.add_argument("--records", type=int, default=4,
                    help="--bonded: records (of 50 steps) per timed chunk (default 4)")
    ap.add_argument("--yade", action="store_true",
                    help="--bonded: also run YADE (yade -j 2) on the same specimen, in this run")
    ap.add_argument("--precisions", nargs="+", default=["float32", "float64"],
                    choices=["float32", "float64"], help="--bonded: precisions to time")
    ap.add_argument("--child-json", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.quick:
        args.chunk_steps = args.chunk_steps or 50
        args.chunks = args.chunks or 3
        args.repeats = args.repeats or 3
    if args.detail is None:
        args.detail = not args.quick
    args.chunk_steps = args.chunk_steps or 100
    args.chunks = args.chunks or 5
    args.repeats = args.repeats or 15
    base = dict(QUICK_SIZES if args.quick else DEFAULT_SIZES)
    if args.dim is not None:
        n = args.n or (args.sizes[0] if args.sizes else base[args.dim])
        sizes = {args.dim: n}
    elif args.sizes:
        if len(args.sizes) != 2:
            ap.error("--sizes takes two counts (2D 3D); use --dim D --n N for one case")
        sizes = {2: args.sizes[0], 3: args.sizes[1]}
    else:
        sizes = base
    args.size_map = {d: n for d, n in sizes.items() if n and n > 0}
    if not args.size_map:
        ap.error("no case to run")
    return args


ARGS = parse_args() if __name__ == "__main__" else None
if ARGS is not None:
    if ARGS.xla_flags:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + ARGS.xla_flags).strip()
    if ARGS.cpus:
        os.sched_setaffinity(0, {int(c) for c in ARGS.cpus.split(",")})

import jax  # noqa: E402

# --bonded casts each set-up to its precision; x64 only where float64 is timed
if ARGS is not None and (ARGS.x64 or (ARGS.bonded and "float64" in ARGS.precisions)):
    jax.config.update("jax_enable_x64", True)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import numpy as np  # noqa: E402

import jax.numpy as jnp  # noqa: E402

from jdem import measure, neighbors  # noqa: E402
from bench.cases import TARGETS, environment, make_case  # noqa: E402
from bench.profile import cost_model, profile_case  # noqa: E402
from bench.report import print_summary, write_markdown  # noqa: E402
from bench.timing import all_finite, block, capacity, make_chunk  # noqa: E402

# ----------------------------------------------------------------------------- one case
def run_case(dim, n, args, log=print):
    t_setup = time.perf_counter()
    state, params, config, info = make_case(dim, n, args)
    setup_s = time.perf_counter() - t_setup
    coord = jax.jit(measure.coordination_number)
    coord0 = float(coord(state))
    log(f"[{dim}D N={n}] setup {setup_s:.1f} s, dt {info['dt_s']:.3g} s "
        f"(critical {info['critical_dt_s']:.3g}, nominal {info['nominal_critical_dt_s']:.3g}), "
        f"capacity {capacity(state)}, max_per_cell {config.max_per_cell}, grid {config.grid_shape}, "
        f"initial coordination {coord0:.2f}")

    k = args.chunk_steps
    regrows = 0
    while True:  # compile + warm-up; re-allocate the list if the warm-up overflowed it
        chunk = make_chunk(config, k)
        t0 = time.perf_counter()
        compiled = chunk.lower(state, params).compile()
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        warm = block(compiled(state, params))
        warmup_s = time.perf_counter() - t0
        if not bool(neighbors.overflowed(warm.contacts, config)) or regrows >= 3:
            break
        contacts, config = neighbors.allocate(warm.particles, config, warm.bonds, slack=1.5,
                                              old=warm.contacts)
        state = warm._replace(contacts=contacts)
        regrows += 1
        log(f"  neighbour list overflowed in warm-up; re-allocated to capacity {capacity(state)}")
    state = warm
    log(f"  compile {compile_s:.1f} s, warm-up chunk ({k} steps) {warmup_s:.2f} s, "
        f"rebuilds so far {int(state.contacts.n_builds)}")

    builds_before = int(state.contacts.n_builds)
    pairs, touching, coords, times, cpu, chunk_builds = [], [], [], [], [], []
    pairs.append(int(jnp.sum(state.contacts.valid)))
    coords.append(float(coord(state)))
    load0 = os.getloadavg()[0]
    for c in range(args.chunks):
        b0 = int(state.contacts.n_builds)
        c0, t0 = time.process_time(), time.perf_counter()
        state = block(compiled(state, params))
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        chunk_builds.append(int(state.contacts.n_builds) - b0)
        pairs.append(int(jnp.sum(state.contacts.valid)))
        coords.append(float(coord(state)))
        log(f"  chunk {c}: {times[-1]:.3f} s, {n * k / times[-1] / 1e6:.3f} M particle-steps/s, "
            f"{chunk_builds[-1]} rebuilds, {pairs[-1]} listed pairs, coordination {coords[-1]:.2f}")
    load1 = os.getloadavg()[0]
    builds_after = int(state.contacts.n_builds)
    finite = all_finite(state)
    overflow = bool(neighbors.overflowed(state.contacts, config))
    times = np.array(times)
    mean_pairs = float(np.mean(pairs))
    mean_coord = float(np.mean(coords))
    mean_touch = mean_coord * n / 2.0
    steps_total = k * args.chunks
    per_chunk = dict(median=float(np.median(times)), best=float(times.min()),
                     aggregate=float(times.sum() / args.chunks))

    def rates(sec_per_chunk):
        steps = k / sec_per_chunk
        return dict(steps_per_s=steps, particle_steps_per_s=n * steps,
                    listed_pair_updates_per_s=mean_pairs * steps,
                    touching_contact_updates_per_s=mean_touch * steps,
                    capacity_rows_per_s=capacity(state) * steps,
                    ms_per_step=1e3 / steps)

    result = dict(
        dim=dim, n=n, packing=info, setup_s=setup_s, compile_s=compile_s, warmup_s=warmup_s,
        regrows=regrows,
        config=dict(capacity=capacity(state), max_per_cell=config.max_per_cell,
                    grid_shape=list(config.grid_shape), cell_size_m=config.cell_size,
                    skin_m=config.skin),
        chunk_steps=k, chunks=args.chunks, steps_timed=steps_total,
        chunk_times_s=times.tolist(), chunk_rebuilds=chunk_builds,
        cpu_cores_busy=float(np.sum(cpu) / times.sum()),
        load_average_1min=[load0, load1],
        n_builds_before=builds_before, n_builds_after=builds_after,
        rebuilds_timed=builds_after - builds_before,
        steps_per_rebuild=(steps_total / (builds_after - builds_before)
                           if builds_after > builds_before else None),
        coordination=dict(initial=coord0, timed_mean=mean_coord, timed_min=float(np.min(coords)),
                          timed_max=float(np.max(coords))),
        listed_pairs_mean=mean_pairs, listed_pairs_min=int(np.min(pairs)),
        listed_pairs_max=int(np.max(pairs)), touching_contacts_mean=mean_touch,
        neighbour_capacity=capacity(state),
        max_pairs_seen=int(state.contacts.n_pairs), max_in_cell_seen=int(state.contacts.max_in_cell),
        throughput={key: rates(v) for key, v in per_chunk.items()},
        final_finite=finite, overflowed=overflow,
        final_kinetic_energy_J=float(measure.kinetic_energy(state)),
    )
    target = TARGETS.get((jax.default_backend(), dim))
    if target:
        result["target"] = target
    if not finite:
        log("  WARNING: final state is not finite")
    if overflow:
        log("  WARNING: neighbour list overflowed during the timed window")
    if builds_after == builds_before:
        log("  WARNING: no rebuild happened in the timed window")

    if not args.no_profile:
        result["profile"] = profile_case(state, params, config, args.repeats, log, detail=args.detail,
                                         loop_steps=k, quick=args.quick)
        result["cost_model"] = cost_model(result)
    return result


# ----------------------------------------------------------------------------- sweep
def run_sweep(args, log=print):
    """Re-run the cases in child processes under other XLA flags / CPU pinning."""
    rows = []
    script = os.path.abspath(__file__)
    base_flags = os.environ.get("XLA_FLAGS", "")
    for label, flags, cpus in SWEEP_FLAGS:
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "child.json")
            cmd = [sys.executable, script, "--child-json", path, "--chunks", str(min(args.chunks, 3)),
                   "--chunk-steps", str(args.chunk_steps), "--repeats", str(max(3, args.repeats // 2)),
                   "--seed", str(args.seed), "--spacing", str(args.spacing), "--jitter", str(args.jitter),
                   "--kn", str(args.kn), "--v0", str(args.v0), "--no-detail"]
            if len(args.size_map) == 1:
                (d, nn), = args.size_map.items()
                cmd += ["--dim", str(d), "--n", str(nn)]
            else:
                cmd += ["--sizes", str(args.size_map.get(2, 0)), str(args.size_map.get(3, 0))]
            if args.skin is not None:
                cmd += ["--skin", str(args.skin)]
            if args.x64:
                cmd.append("--x64")
            if flags:
                cmd.append(f"--xla-flags={flags}")
            if cpus:
                cmd += ["--cpus", cpus]
            env = dict(os.environ, XLA_FLAGS=base_flags)
            log(f"[sweep] {label}: {' '.join(shlex.quote(a) for a in cmd[2:])}")
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
            if proc.returncode != 0 or not os.path.exists(path):
                log(f"[sweep] {label} failed:\n{proc.stderr[-2000:]}")
                rows.append(dict(label=label, xla_flags=flags, cpus=cpus, error=proc.stderr[-2000:]))
                continue
            child = json.load(open(path))
        row = dict(label=label, xla_flags=flags, cpus=cpus, wall_s=time.perf_counter() - t0, cases=[])
        for case in child["cases"]:
            tp = case["throughput"]
            prof = case.get("profile", {})
            row["cases"].append(dict(
                dim=case["dim"], n=case["n"],
                particle_steps_per_s_median=tp["median"]["particle_steps_per_s"],
                particle_steps_per_s_best=tp["best"]["particle_steps_per_s"],
                rebuilds_timed=case["rebuilds_timed"], steps_timed=case["steps_timed"],
                cpu_cores_busy=case["cpu_cores_busy"],
                **{f"{k}_ms": prof.get("loop." + k, {}).get("best_ms") for k in
                   ("contact_forces", "wall_forces", "needs_rebuild", "build", "step")}))
            log(f"[sweep]   {case['dim']}D N={case['n']}: "
                f"{tp['median']['particle_steps_per_s'] / 1e6:.3f} M particle-steps/s (median)")
        rows.append(row)
    return rows


# ----------------------------------------------------------------------------- bonded
def run_bonded(args, env, log=print):
    """The bonded benchmark: jdem in every precision asked for, then YADE."""
    from bench import bonded

    particles, bonds, pos, rad, pairs, info = bonded.bonded_specimen(args.bonded_n, args.seed,
                                                                     log=log)
    report = dict(environment=env, specimen=info, cases=[])
    first_params = None     # the material and time step YADE is given
    for prec in args.precisions:
        res, state, params, config = bonded.time_bonded(particles, bonds, prec, args.records,
                                                        args.chunks, log)
        first_params = params if first_params is None else first_params
        if not args.no_profile:
            res["profile"] = profile_case(state, params, config, args.repeats, log,
                                          detail=False, loop_steps=res["chunk_steps"])
            res["cost_model"] = cost_model(res)
        report["cases"].append(res)
    if args.yade:
        with tempfile.TemporaryDirectory() as tmp:
            inp, outp = os.path.join(tmp, "spec.npz"), os.path.join(tmp, "yade.json")
            bonded.write_yade_input(inp, pos, rad, pairs, particles, first_params)
            steps = report["cases"][0]["chunk_steps"]
            cmd = ["yade", "-j", "2", "-n", "-x", os.path.join(os.path.dirname(__file__), "bench",
                                                              "yade_bonded.py"),
                   inp, outp, str(steps), str(args.chunks)]
            log("[bonded] " + " ".join(cmd))
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0 or not os.path.exists(outp):
                log(f"[bonded] YADE failed:\n{proc.stdout[-1500:]}\n{proc.stderr[-1500:]}")
                report["yade"] = dict(error=(proc.stdout + proc.stderr)[-3000:])
            else:
                report["yade"] = json.load(open(outp))
                ver = subprocess.run(["yade", "--version"], capture_output=True, text=True)
                report["yade"]["version"] = (ver.stdout.strip() or ver.stderr.strip())[:200]
                y = report["yade"]
                log(f"[bonded] YADE: {y['steps_per_s']:.1f} steps/s, "
                    f"{y['particle_steps_per_s'] / 1e6:.2f} M particle-steps/s, bonds made "
                    f"{y['bonds_made']} (input {y['bonds_input']})")
                for c in report["cases"]:
                    c["ratio_to_yade"] = c["steps_per_s"] / y["steps_per_s"]
    env["load_average_end"] = list(os.getloadavg())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bonded_benchmark.json").write_text(json.dumps(report, indent=1))
    write_bonded_markdown(out / "bonded_benchmark.md", report)
    print((out / "bonded_benchmark.md").read_text())
    return 0 if all(c["finite"] and not c["overflowed"] for c in report["cases"]) else 1


def write_bonded_markdown(path, report):
    env, sp = report["environment"], report["specimen"]
    lines = [f"# Bonded 3D benchmark ({env['date_utc']})", "",
             f"`{env['command']}` on {env['cpu_model']} ({env['cpus_usable']} CPUs usable), "
             f"jax {env['jax_version']}, backend {env['backend']}.", "",
             f"Specimen: {sp['n']} spheres, radii {sp['radius_range_m']} m, {sp['n_bonds']} bonds "
             f"({sp['bonds_per_sphere']:.2f} per sphere, {sp['bond_rule']}), a cell of "
             f"{sp['cell_spheres']} at porosity {sp['cell_porosity']:.3f} tiled {sp['tiles']}^3 and "
             f"cut to a cube; UCS platens, 2e-7 strain per step, local damping 0.2.", "",
             "| code | precision | steps/s | particle-steps/s | bond-steps/s | vs YADE |",
             "|---|---|---|---|---|---|"]
    for c in report["cases"]:
        lines.append(f"| jdem | {c['precision']} | {c['steps_per_s']:.1f} | "
                     f"{c['particle_steps_per_s'] / 1e6:.2f} M | {c['bond_steps_per_s'] / 1e6:.1f} M | "
                     f"{c.get('ratio_to_yade', float('nan')):.2f} |")
    y = report.get("yade")
    if y and "steps_per_s" in y:
        lines.append(f"| YADE ({y['threads']} threads) | float64 | {y['steps_per_s']:.1f} | "
                     f"{y['particle_steps_per_s'] / 1e6:.2f} M | {y['bond_steps_per_s'] / 1e6:.1f} M | 1 |")
    elif y:
        lines.append(f"\nYADE failed: `{y['error'][-300:]}`")
    lines.append("")
    for c in report["cases"]:
        cm = c.get("cost_model", {})
        if cm.get("parts_ms_per_step"):
            lines.append(f"Where a {c['precision']} step goes (in-loop kernels, ms per step; measured "
                         f"{cm['measured_ms_per_step']:.2f}, sum {cm['predicted_ms_per_step']:.2f}):")
            for k, v in cm["parts_ms_per_step"].items():
                lines.append(f"- {k}: {v:.3f} ({100 * cm['shares'][k]:.0f} %)")
            lines.append("")
        lines.append(f"{c['precision']}: compile {c['compile_s']:.1f} s (excluded), "
                     f"{c['rebuilds_timed']} rebuilds in {c['steps_timed']} timed steps, "
                     f"float64 primitives in the float32 chunk: "
                     f"{c['float64_primitives_in_float32_chunk']}, bonds broken at the end "
                     f"{c['bonds_broken_at_end']}.")
        lines.append("")
    Path(path).write_text("\n".join(lines) + "\n")


# ----------------------------------------------------------------------------- main
def main(args):
    env = environment(args)
    if args.bonded:
        return run_bonded(args, env)
    log = (lambda *a, **k: print(*a, **k, file=sys.stderr, flush=True)) if args.child_json else \
        (lambda *a, **k: print(*a, **k, flush=True))
    log(f"jax {env['jax_version']} on {env['backend']} ({env['device']}), {env['dtype']}, "
        f"XLA_FLAGS='{env['xla_flags']}', CPUs usable {env['cpus_usable']}")
    cases = [run_case(d, n, args, log) for d, n in sorted(args.size_map.items())]
    env["load_average_end"] = list(os.getloadavg())
    report = dict(environment=env, cases=cases,
                  settings=dict(chunk_steps=args.chunk_steps, chunks=args.chunks, repeats=args.repeats))
    if args.child_json:
        Path(args.child_json).write_text(json.dumps(report, indent=1))
        return 0 if all(c["final_finite"] for c in cases) else 1
    if args.sweep:
        report["sweep"] = run_sweep(args, log)
        env["load_average_end"] = list(os.getloadavg())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "benchmark.json").write_text(json.dumps(report, indent=1))
    write_markdown(out / "benchmark.md", report)
    print_summary(report)
    print(f"wrote {out / 'benchmark.json'} and {out / 'benchmark.md'}")
    return 0 if all(c["final_finite"] for c in cases) else 1


if __name__ == "__main__":
    sys.exit(main(ARGS))
