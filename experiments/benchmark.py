#!/usr/bin/env python
"""Throughput of jdem's jitted step loop on dense packings, with a cost breakdown.

    python experiments/benchmark.py                 # 2D 10,000 discs + 3D 20,000 spheres
    python experiments/benchmark.py --quick         # 1,000 / 2,000 particles, smoke run
    python experiments/benchmark.py --dim 3 --n 1000000 --device-label "H100"
    python experiments/benchmark.py --sizes 10000 20000 --x64
    python experiments/benchmark.py --sweep         # also re-run under other XLA_FLAGS / 1 core

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
import datetime as _dt
import hashlib
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# ----------------------------------------------------------------------------- arguments
DEFAULT_SIZES = {2: 10_000, 3: 20_000}
QUICK_SIZES = {2: 1_000, 3: 2_000}
TARGETS = {  # (backend, dim) -> particle-steps/s to compare against
    ("cpu", 3): dict(target=1.5e6, reference="YADE ~0.7 M particle-steps/s on one core",
                     note="target: >= 1.5 M particle-steps/s for 20,000 spheres on this 2-core CPU"),
    ("gpu", 3): dict(target=100e6, reference="CPU target 1.5 M particle-steps/s (2 cores)",
                     note="target: >= 100 M particle-steps/s at 1,000,000 spheres on one GPU"),
}
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

import numpy as np  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

if ARGS is not None and ARGS.x64:
    jax.config.update("jax_enable_x64", True)

import jdem  # noqa: E402
from jdem import contact, integrate, measure, neighbors, timestep  # noqa: E402
from jdem.specimen import lattice  # noqa: E402
from jdem import walls as walls_mod  # noqa: E402
from jdem.kinematics import dot, segment_add  # noqa: E402

RADIUS = 1e-3  # r [m]; radii uniform in [0.8 r, r]
DENSITY = 2500.0
FRICTION = 0.5


# ----------------------------------------------------------------------------- environment
def environment(args):
    model, flags = "unknown", ""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name") and model == "unknown":
                    model = line.split(":", 1)[1].strip()
                if line.startswith("flags") and not flags:
                    flags = line.split(":", 1)[1]
    except OSError:
        pass
    isa = [f for f in ("avx2", "fma", "avx512f", "avx512_bf16", "amx_tile") if f" {f} " in f" {flags} "]
    dev = jax.devices()[0]
    src = hashlib.sha1()
    for f in sorted(Path(jdem.__file__).parent.glob("*.py")):
        src.update(f.name.encode() + f.read_bytes())
    return dict(
        date_utc=_dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"),
        command="python " + " ".join(shlex.quote(a) for a in sys.argv),
        device_label=args.device_label,
        jax_version=jax.__version__,
        jaxlib_version=getattr(__import__("jaxlib"), "__version__", "?"),
        jdem_version=getattr(jdem, "__version__", "?"),
        jdem_source_sha1=src.hexdigest()[:12],
        python=platform.python_version(),
        backend=jax.default_backend(),
        device=str(getattr(dev, "device_kind", dev.platform)),
        cpu_model=model, cpu_isa=isa,
        cpu_count=os.cpu_count(), cpus_usable=len(os.sched_getaffinity(0)),
        dtype="float64" if jax.config.jax_enable_x64 else "float32",
        xla_flags=os.environ.get("XLA_FLAGS", ""),
        load_average_start=list(os.getloadavg()),
    )


# ----------------------------------------------------------------------------- packing
def lattice_sites(dim, n, spacing):
    """First ``n`` sites of a triangular (2D) or FCC (3D) lattice of nearest-
    neighbour distance ``spacing`` (:func:`jdem.specimen.lattice.lattice_sites`),
    filling a near-square / near-cubic block row by row (layer by layer), so the
    top row may be partial."""
    if dim == 2:
        ny = int(np.ceil(np.sqrt(n / (np.sqrt(3) / 2))))
        nx = int(np.ceil(n / ny))
        return lattice.lattice_sites("triangular", (nx, ny), spacing)[:n]
    m = int(np.ceil((n / 4) ** (1 / 3)))
    return lattice.lattice_sites("fcc", (m, m, m), spacing)[:n]


def make_case(dim, n, args):
    """Dense packing in a box of walls; returns (state, params, config, info)."""
    rng = np.random.default_rng(args.seed + 1000 * dim)
    s = args.spacing * 2.0 * 0.9 * RADIUS  # mean diameter 1.8 r
    pos = lattice_sites(dim, n, s) + rng.uniform(-args.jitter, args.jitter, (n, dim)) * s
    rad = rng.uniform(0.8 * RADIUS, 1.0 * RADIUS, n)
    vel = rng.normal(0.0, args.v0, (n, dim))
    particles = jdem.make_particles(pos, rad, density=DENSITY, vel=vel)
    lo, hi = pos.min(0) - 0.5 * s, pos.max(0) + 0.5 * s
    points, normals = [], []
    for axis in range(dim):
        e = np.eye(dim)[axis]
        centre = 0.5 * (lo + hi)
        p = centre.copy(); p[axis] = lo[axis]; points.append(p); normals.append(e)
        p = centre.copy(); p[axis] = hi[axis]; points.append(p); normals.append(-e)
    walls = jdem.make_walls(np.array(points), np.array(normals), n_particles=n)
    params = jdem.make_params(dim=dim, kn=args.kn, friction=FRICTION)
    state, config = jdem.make_state(particles, walls=walls, skin=args.skin)
    crit = float(timestep.critical_timestep(state, params, config))
    nominal = float(timestep.nominal_critical_timestep(particles, params, config))
    dt = float(timestep.recommended(min(crit, nominal)))
    params = params._replace(dt=jnp.asarray(dt, params.dt.dtype))
    info = dict(lattice="triangular" if dim == 2 else "fcc", spacing_m=s,
                spacing_over_mean_diameter=args.spacing, jitter_over_spacing=args.jitter,
                radius_range_m=[0.8 * RADIUS, RADIUS], density=DENSITY, kn=args.kn, ks=args.kn,
                friction=FRICTION, contact_model=config.contact_model, gravity=0.0,
                v0_m_per_s=args.v0, seed=args.seed, box_lo=lo.tolist(), box_hi=hi.tolist(),
                n_walls=2 * dim, critical_dt_s=crit, nominal_critical_dt_s=nominal, dt_s=dt,
                dt_rule="timestep.recommended(min(critical_timestep, nominal_critical_timestep))")
    return state, params, config, info


# ----------------------------------------------------------------------------- timing helpers
def _block(x):
    return jax.block_until_ready(x)


def time_fn(fn, *args, repeats=15, warm=1):
    """Compile ``jax.jit(fn)`` and time calls; returns dict (ms) and the last output."""
    jitted = jax.jit(fn)
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    out = None
    for _ in range(warm):
        out = _block(compiled(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = _block(compiled(*args))
        times.append(time.perf_counter() - t0)
    times = np.array(times) * 1e3
    return dict(best_ms=float(times.min()), median_ms=float(np.median(times)),
                repeats=repeats, compile_s=compile_s), out


def make_chunk(config, k):
    def chunk(state, params):
        return jax.lax.fori_loop(0, k, lambda _, s: integrate.step(s, params, config), state)

    return jax.jit(chunk)


def capacity(state):
    """Rows of the neighbour list (the length of the Contacts arrays)."""
    return int(state.contacts.i.shape[-1])


def all_finite(state):
    p = state.particles
    return bool(jnp.all(jnp.isfinite(p.pos)) & jnp.all(jnp.isfinite(p.vel))
                & jnp.all(jnp.isfinite(p.angvel))) and int(state.first_bad_step) < 0


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
        warm = _block(compiled(state, params))
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
        state = _block(compiled(state, params))
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


# ----------------------------------------------------------------------------- profile
def profile_case(state, params, config, repeats, log=print, detail=True, loop_steps=100,
                 quick=False):
    """Time the parts of a step on the final state of the timed run.

    Main figures ("loop.*") are per call inside a jitted ``lax.fori_loop`` whose
    carry feeds each call's output (or a 1e-30 nudge of the positions that
    depends on it) back into the next call, so XLA cannot hoist the work out of
    the loop and buffers are reused as in the real step loop.  The plain names
    are one jitted call from Python each (new output buffers every call); on
    this CPU that adds a large fixed cost, so they overstate the in-loop cost.
    """
    n = state.particles.pos.shape[0]
    dtype = state.particles.pos.dtype
    build_fn = lambda c, p, b: neighbors.build(c, p, config, b)  # noqa: E731
    fresh = _block(jax.jit(build_fn)(state.contacts, state.particles, state.bonds))
    st = state._replace(contacts=fresh)  # just rebuilt: the common no-rebuild path
    stale = st._replace(contacts=fresh._replace(pos_at_build=jnp.full_like(fresh.pos_at_build, jnp.inf)))
    p, c, w = st.particles, st.contacts, st.walls
    r_cheap, r_build = repeats, max(3, repeats // 3)
    never = config.replace(skin=1e3)  # needs_rebuild is always false: cond never rebuilds
    tiny = 1e-30
    out = {}

    def rec(name, fn, *a, r=r_cheap, desc="", per=1):
        try:
            res, val = time_fn(fn, *a, repeats=r)
            res["best_ms"] /= per
            res["median_ms"] /= per
        except Exception as exc:  # the API may be changing under us; keep the rest
            log(f"  profile {name}: failed ({type(exc).__name__}: {exc})")
            out[name] = dict(error=f"{type(exc).__name__}: {exc}")
            return None
        res["what"] = desc
        res["per_call_in_loop"] = per > 1
        out[name] = res
        log(f"  profile {name:38s} best {res['best_ms']:9.3f} ms   median {res['median_ms']:9.3f} ms")
        return val

    def rec_loop(name, body, init, consts, iters, r, desc):
        """body(carry, consts) -> carry, run ``iters`` times in one jitted fori_loop."""
        fn = lambda init, consts: jax.lax.fori_loop(  # noqa: E731
            0, iters, lambda _, x: body(x, consts), init)
        return rec(name, fn, init, consts, r=r, per=iters, desc=desc + f" (per call, fori_loop of {iters})")

    def nudge(pp, by):
        return pp._replace(pos=pp.pos + by.astype(dtype) * tiny)

    # positions are nudged by the previous output so that the geometry cannot be hoisted
    def loop_contact(x, pr):
        cc, pp, f, t = x
        pp = nudge(pp, f[0, 0])
        cc, fo, to, _ = contact.contact_forces(cc, pp, pr, config)
        return cc, pp, f + fo, t + to

    def loop_walls(x, pr):
        ww, pp, f, t = x
        pp = nudge(pp, f[0, 0])
        ww, fo, to, _ = walls_mod.wall_forces(ww, pp, pr, config)
        return ww, pp, f + fo, t + to

    def loop_needs(x, k):
        pp, acc = x
        need = neighbors.needs_rebuild(k, pp, config).astype(jnp.int32)
        return nudge(pp, need), acc + need

    def loop_build(x, k):
        cc, pp = x
        pp = nudge(pp, cc.n_builds)
        return build_fn(cc, pp, k), pp

    def forced(s):
        return s._replace(contacts=s.contacts._replace(
            pos_at_build=jnp.full_like(s.contacts.pos_at_build, jnp.inf)))

    zf, zt = jnp.zeros_like(p.pos), jnp.zeros_like(p.angvel)
    li, lb = 20, 5  # iterations per timed loop: cheap parts, rebuilds
    rec("dispatch_overhead", lambda x: x + 1, jnp.zeros(()), desc="trivial jitted call")
    rec_loop("loop.contact_forces", loop_contact, (c, p, zf, zt), params, li, r_cheap,
             "(1) jdem.contact.contact_forces over the whole capacity")
    rec_loop("loop.wall_forces", loop_walls, (w, p, zf, zt), params, li, r_cheap,
             "(2) jdem.walls.wall_forces, W x N dense")
    rec_loop("loop.needs_rebuild", loop_needs, (p, jnp.zeros((), jnp.int32)), c, li, r_cheap,
             "(3) jdem.neighbors.needs_rebuild")
    rec_loop("loop.build", loop_build, (c, p), st.bonds, lb, r_build, "(4) jdem.neighbors.build")
    rec_loop("loop.step", lambda x, pr: integrate.step(x, pr, never), st, params, li, r_build,
             "(5) jdem.integrate.step, cond never takes the rebuild branch")
    if not quick:
        rec_loop("loop.step_with_rebuild", lambda x, pr: integrate.step(forced(x), pr, config), st,
                 params, lb, r_build, "(5b) integrate.step, cond takes the rebuild branch every step")
        rec_loop("loop.physics_step", lambda x, pr: integrate.physics_step(x, pr, config), st, params,
                 li, r_build, "integrate.physics_step (no neighbour test, no cond)")
        # the same functions called once from Python (fresh output buffers each call)
        rec("contact_forces", lambda c, p, pr: contact.contact_forces(c, p, pr, config), c, p, params,
            desc="(1) standalone call")
        rec("wall_forces", lambda w, p, pr: walls_mod.wall_forces(w, p, pr, config), w, p, params,
            desc="(2) standalone call")
        rec("needs_rebuild", lambda c, p: neighbors.needs_rebuild(c, p, config), c, p,
            desc="(3) standalone call")
        rec("build", build_fn, c, p, st.bonds, r=r_build, desc="(4) standalone call")
        rec("step", lambda s, pr: integrate.step(s, pr, config), st, params,
            desc="(5) standalone call, list fresh (cond skips the rebuild)")
        rec("step_with_rebuild", lambda s, pr: integrate.step(s, pr, config), stale, params,
            r=r_build, desc="(5b) standalone call, cond takes the rebuild branch")
    if quick or not detail:
        return out

    # --- inside contact_forces: the gathers and the scatter-adds on their own
    i, j = c.i, c.j
    rec("contact.gathers", lambda p: (p.pos[i], p.pos[j], p.vel[i], p.vel[j], p.angvel[i],
                                      p.angvel[j], p.radius[i], p.radius[j], p.mass[i], p.mass[j],
                                      p.material[i], p.material[j]), p,
        desc="the 12 per-pair gathers of contact_forces (standalone call)")
    fi = jnp.ones((i.shape[0],) + p.pos.shape[1:], p.pos.dtype)
    ti = jnp.ones((i.shape[0],) + p.angvel.shape[1:], p.pos.dtype)
    touching = contact.pair_geometry(c, p).touching  # contact_forces sums touching rows only
    add = lambda rows, index: segment_add(rows, index, n, where=touching)
    rec("contact.scatter_adds", lambda f, t, v: (add(f, i) - add(f, j), add(t, i) + add(t, j),
                                                 add(v, i) + add(v, j)),
        fi, ti, touching.astype(jnp.int32), desc="the 6 segment_add scatters of contact_forces (standalone call)")

    # --- inside build (private helpers; skipped if they change), each in a fori_loop
    def rec_part(name, fn, k, desc, iters=lb):
        """fn(particles, k) -> pytree; the loop nudges the positions by one element of
        the previous output so that nothing can be hoisted."""
        shapes = jax.eval_shape(fn, p, k)
        init = (p, jax.tree_util.tree_map(lambda sd: jnp.zeros(sd.shape, sd.dtype), shapes))

        def body(x, k):
            pp, prev = x
            pp = nudge(pp, jax.tree_util.tree_leaves(prev)[-1].reshape(-1)[0])
            return pp, fn(pp, k)

        return rec_loop(name, body, init, k, iters, r_build, desc)

    try:
        cand, _ = jax.jit(lambda p: neighbors.candidates(p, config))(p)

        def cand_mask(p, cand):
            pos_pad = jnp.concatenate([p.pos, jnp.zeros_like(p.pos[:1])])
            rad_pad = jnp.concatenate([p.radius, jnp.zeros_like(p.radius[:1])])
            ii = jnp.arange(n, dtype=jnp.int32)[:, None]
            real = (cand < n) & (cand > ii) & p.valid[:, None]
            delta = pos_pad[cand] - p.pos[:, None, :]
            reach = rad_pad[cand] + p.radius[:, None] + config.skin
            return real & (dot(delta, delta) < reach * reach)

        mask = _block(jax.jit(cand_mask)(p, cand))
        out["build_candidates_shape"] = list(cand.shape)
        out["build_candidates_filled"] = float(jnp.mean(cand < n))
        out["build_candidates_kept"] = int(jnp.sum(mask))
        rec_part("loop.build.cell_table", lambda pp, k: neighbors.cell_table(pp, config), 0,
                 "sort particles into cells (one int32 key), fill the (cells, K) table")
        rec_part("loop.build.candidates", lambda pp, k: neighbors.candidates(pp, config), 0,
                 "cell table + (N, 3^d K) candidate gather (includes cell_table)")
        rec_part("loop.build.mask", lambda pp, k: cand_mask(pp, k), cand,
                 "distance test of every candidate (gather of candidate positions and radii)")

        def history(x, cc):
            acc, prev = x
            cc = cc._replace(shear=cc.shear + acc)  # depends on the carry: not hoistable
            shear = neighbors.carry_history(cc, cc.i, cc.j, cc.valid, n)
            return shear[0, 0], shear

        rec_loop("loop.build.history_search", history, (jnp.zeros((), dtype), c.shear), c, lb,
                 r_build, "each new pair scans the old rows of its particle i for the tangential history")
        parts = [out.get(k, {}).get("best_ms") for k in
                 ("loop.build", "loop.build.candidates", "loop.build.mask", "loop.build.history_search")]
        if None not in parts:
            rest = max(0.0, parts[0] - parts[1] - parts[2] - parts[3])
            out["loop.build.compact_and_order"] = dict(
                best_ms=rest, median_ms=rest, repeats=0, compile_s=0.0, per_call_in_loop=True,
                what="derived: build - candidates - mask - history_search (compaction of the "
                     "candidate mask into the pair list through bit sets and binary searches, "
                     "sort of the kept pairs, bookkeeping)")
            log(f"  profile {'loop.build.compact_and_order (derived)':38s} best {rest:9.3f} ms")
    except Exception as exc:
        log(f"  build breakdown skipped ({type(exc).__name__}: {exc})")
        out["build_breakdown_error"] = f"{type(exc).__name__}: {exc}"
    return out


def cost_model(res):
    """Split the measured per-step time of the timed window into its parts.

    Uses the in-loop figures: ms/step = contact + walls + rebuild test + rest of
    the no-rebuild step + (one rebuild) x (rebuilds per step).
    """
    prof = res["profile"]
    best = lambda k: prof.get(k, {}).get("best_ms")  # noqa: E731
    steps = res["steps_timed"]
    per_step = res["throughput"]["aggregate"]["ms_per_step"]
    rb_per_step = res["rebuilds_timed"] / steps
    keys = ("loop.contact_forces", "loop.wall_forces", "loop.needs_rebuild", "loop.build", "loop.step")
    if None in [best(k) for k in keys]:
        return dict(measured_ms_per_step=per_step, rebuilds_per_step=rb_per_step)
    cf, wf, nr, bd, st = (best(k) for k in keys)
    parts = {
        "contact_forces": cf,
        "wall_forces": wf,
        "needs_rebuild": nr,
        "rest of the no-rebuild step (integration, cond, copies)": max(0.0, st - cf - wf - nr),
        "build (amortised)": bd * rb_per_step,
    }
    predicted = sum(parts.values())
    out = dict(measured_ms_per_step=per_step, rebuilds_per_step=rb_per_step,
               parts_ms_per_step=parts, predicted_ms_per_step=predicted,
               shares={k: v / predicted for k, v in parts.items()},
               no_rebuild_step_ms=st, build_ms=bd)
    if res["rebuilds_timed"]:
        out["implied_build_ms_from_window"] = (per_step - st) / rb_per_step
    # what this loop would give at other rebuild intervals: ms/step = step + build / interval
    res["throughput_vs_rebuild_interval"] = {
        str(iv): res["n"] / ((st + (bd / iv if iv else 0.0)) * 1e-3) for iv in (5, 10, 20, 50, 100, 0)}
    return out


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


# ----------------------------------------------------------------------------- report
def _m(x):
    return "n/a" if x is None else f"{x / 1e6:.3f} M"


def _ms(x):
    return "n/a" if x is None else f"{x:.3f}"


def summary_table(cases):
    head = ("| case | N | particle-steps/s (median / best / window) | steps/s (median) | ms/step "
            "| listed pairs (mean) | capacity | touching (mean) | coord. | pair-updates/s listed "
            "| touching-updates/s | rebuilds in window (steps/rebuild) | target |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for c in cases:
        tp = c["throughput"]
        tgt = c.get("target")
        tgt_s = "-"
        if tgt:
            ratio = tp["median"]["particle_steps_per_s"] / tgt["target"]
            tgt_s = f">= {tgt['target'] / 1e6:.1f} M ({ratio:.2f}x of target)"
        spr = c["steps_per_rebuild"]
        lines.append(
            f"| {c['dim']}D {c['packing']['lattice']} | {c['n']:,} | "
            f"{_m(tp['median']['particle_steps_per_s'])} / {_m(tp['best']['particle_steps_per_s'])} / "
            f"{_m(tp['aggregate']['particle_steps_per_s'])} | {tp['median']['steps_per_s']:.1f} | "
            f"{tp['median']['ms_per_step']:.2f} | {c['listed_pairs_mean']:,.0f} | {c['neighbour_capacity']:,} | "
            f"{c['touching_contacts_mean']:,.0f} | {c['coordination']['timed_mean']:.2f} | "
            f"{_m(tp['median']['listed_pair_updates_per_s'])} | "
            f"{_m(tp['median']['touching_contact_updates_per_s'])} | "
            f"{c['rebuilds_timed']} ({'-' if spr is None else f'{spr:.1f}'}) | {tgt_s} |")
    return "\n".join(lines)


def profile_table(c):
    prof = c.get("profile")
    if not prof:
        return "(profile skipped)"
    per_step = c["throughput"]["aggregate"]["ms_per_step"]
    lines = ["Times per call, best and median of repeats.  `loop.*`: inside a jitted `fori_loop` (as in the "
             "real step loop); plain names: one jitted call from Python (fresh output buffers every call, "
             "which costs extra here).", "",
             "| part | timed | best ms | median ms | % of measured ms/step | what |",
             "|---|---|---|---|---|---|"]
    for name, r in prof.items():
        if not isinstance(r, dict):
            continue
        if "error" in r:
            lines.append(f"| {name} | | error | | | {r['error']} |")
            continue
        how = "in loop" if r.get("per_call_in_loop") else "standalone"
        lines.append(f"| {name} | {how} | {r['best_ms']:.3f} | {r['median_ms']:.3f} | "
                     f"{100 * r['best_ms'] / per_step:.0f}% | {r['what']} |")
    cm = c.get("cost_model", {})
    tvi = c.get("throughput_vs_rebuild_interval")
    if tvi:
        lines += ["", "Particle-steps/s this loop would reach at other rebuild intervals "
                  "(ms/step = loop.step + loop.build / interval; 0 = never):", "",
                  "| steps per rebuild | " + " | ".join(tvi) + " |", "|---|" + "---|" * len(tvi),
                  "| particle-steps/s | " + " | ".join(_m(v) for v in tvi.values()) + " |"]
    if cm.get("parts_ms_per_step"):
        lines += ["", f"Cost model per step (in-loop best times; build amortised over "
                  f"{c['rebuilds_timed']} rebuilds / {c['steps_timed']} steps):", "",
                  "| part | ms/step | share |", "|---|---|---|"]
        for k, v in cm["parts_ms_per_step"].items():
            lines.append(f"| {k} | {v:.3f} | {100 * cm['shares'][k]:.0f}% |")
        lines.append(f"| **predicted** | {cm['predicted_ms_per_step']:.3f} | |")
        lines.append(f"| **measured (timed window)** | {cm['measured_ms_per_step']:.3f} | |")
        if "implied_build_ms_from_window" in cm:
            lines.append(f"\nOne rebuild as implied by the window, (measured - loop.step) / rebuilds per step: "
                         f"{cm['implied_build_ms_from_window']:.1f} ms (loop.build: {cm['build_ms']:.1f} ms).")
    if "build_candidates_shape" in prof:
        lines += ["", f"Rebuild: candidate array {prof['build_candidates_shape']} "
                  f"({100 * prof['build_candidates_filled']:.0f}% of slots hold a particle), "
                  f"{prof['build_candidates_kept']:,} pairs kept "
                  f"({100 * prof['build_candidates_kept'] / np.prod(prof['build_candidates_shape']):.1f}% "
                  f"of the candidates)."]
    return "\n".join(lines)


def sweep_table(rows):
    lines = ["| setting | XLA_FLAGS added | CPUs | case | particle-steps/s median (best) | rebuilds/steps "
             "| cores busy | contact ms | wall ms | build ms | step ms |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['label']} | `{r['xla_flags']}` | {r['cpus'] or 'all'} | failed | | | | | | | |")
            continue
        for c in r["cases"]:
            lines.append(
                f"| {r['label']} | `{r['xla_flags'] or '-'}` | {r['cpus'] or 'all'} | {c['dim']}D {c['n']:,} | "
                f"{_m(c['particle_steps_per_s_median'])} ({_m(c['particle_steps_per_s_best'])}) | "
                f"{c['rebuilds_timed']}/{c['steps_timed']} | {c['cpu_cores_busy']:.2f} | "
                f"{_ms(c['contact_forces_ms'])} | {_ms(c['wall_forces_ms'])} | {_ms(c['build_ms'])} | "
                f"{_ms(c['step_ms'])} |")
    return "\n".join(lines)


def write_markdown(path, report):
    env = report["environment"]
    lines = [
        "# jdem step-loop benchmark", "",
        f"Produced by `{env['command']}` on {env['date_utc']}"
        + (f" ({env['device_label']})" if env["device_label"] else "") + ".",
        "This file and `benchmark.json` are overwritten on every run.", "",
        "## Environment", "",
        "| | |", "|---|---|",
        f"| device label | {env['device_label'] or '-'} |",
        f"| backend / device | {env['backend']} / {env['device']} |",
        f"| CPU | {env['cpu_model']} ({', '.join(env['cpu_isa']) or 'no AVX info'}) |",
        f"| cores | {env['cpu_count']} ({env['cpus_usable']} usable by this process) |",
        f"| jax / jaxlib / jdem | {env['jax_version']} / {env['jaxlib_version']} / {env['jdem_version']} "
        f"(sha1 of jdem/*.py: {env['jdem_source_sha1']}) |",
        f"| dtype | {env['dtype']} |",
        f"| XLA_FLAGS | `{env['xla_flags'] or '-'}` |",
        f"| load average (1 min) at start / end | {env['load_average_start'][0]:.2f} / "
        f"{env['load_average_end'][0]:.2f} |",
        "",
        *([f"**Warning: the machine was shared** (1-min load average {env['load_average_start'][0]:.1f} at the "
           f"start, {env['load_average_end'][0]:.1f} at the end, on {env['cpu_count']} cores): other processes took "
           "CPU time during the measurements, so these figures are lower bounds and vary run to run.", ""]
          if max(env["load_average_start"][0], env["load_average_end"][0]) > env["cpu_count"] - 0.5 else []),
        "Throughput of the jitted `lax.fori_loop` over `jdem.integrate.step`, compile time "
        "excluded; neighbour-list rebuilds inside the step via `lax.cond`.  *median* / *best*: "
        "the median / fastest timed chunk; *window*: all timed steps over all timed time. "
        "Pair-updates/s = listed pairs x steps/s; touching-updates/s = touching contacts x steps/s.",
        "",
        "## Results", "",
        summary_table(report["cases"]), "",
    ]
    for c in report["cases"]:
        pk = c["packing"]
        lines += [
            f"## {c['dim']}D, {c['n']:,} particles", "",
            f"- packing: {pk['lattice']} lattice, spacing {pk['spacing_m'] * 1e3:.4g} mm "
            f"({pk['spacing_over_mean_diameter']} x mean diameter), jitter {pk['jitter_over_spacing']} x spacing, "
            f"radii uniform in [{pk['radius_range_m'][0] * 1e3:.1f}, {pk['radius_range_m'][1] * 1e3:.1f}] mm, "
            f"{pk['n_walls']} walls, no gravity, {pk['contact_model']} law, kn = ks = {pk['kn']:.3g} N/m, "
            f"friction {pk['friction']}, density {pk['density']:.0f}, initial velocity spread "
            f"{pk['v0_m_per_s']} m/s, seed {pk['seed']}",
            f"- dt = {pk['dt_s']:.4g} s = `{pk['dt_rule']}` (critical {pk['critical_dt_s']:.4g} s, "
            f"nominal {pk['nominal_critical_dt_s']:.4g} s)",
            f"- neighbour list: capacity {c['neighbour_capacity']:,}, listed pairs mean {c['listed_pairs_mean']:,.0f} "
            f"(min {c['listed_pairs_min']:,}, max {c['listed_pairs_max']:,}), max_per_cell "
            f"{c['config']['max_per_cell']}, grid {c['config']['grid_shape']}, cell {c['config']['cell_size_m'] * 1e3:.4g} mm, "
            f"skin {c['config']['skin_m'] * 1e3:.4g} mm, re-allocations {c['regrows']}",
            f"- coordination number (jdem.measure.coordination_number): initial {c['coordination']['initial']:.2f}, "
            f"timed window mean {c['coordination']['timed_mean']:.2f} "
            f"(min {c['coordination']['timed_min']:.2f}, max {c['coordination']['timed_max']:.2f})",
            f"- rebuilds (`state.contacts.n_builds`): {c['n_builds_before']} before, {c['n_builds_after']} after the "
            f"timed window = {c['rebuilds_timed']} in {c['steps_timed']} steps; per chunk {c['chunk_rebuilds']}",
            f"- compile {c['compile_s']:.1f} s, warm-up chunk {c['warmup_s']:.2f} s, chunk of {c['chunk_steps']} steps: "
            f"{', '.join(f'{t:.3f}' for t in c['chunk_times_s'])} s; CPU cores busy on average "
            f"{c['cpu_cores_busy']:.2f}; load average {c['load_average_1min'][0]:.2f} -> {c['load_average_1min'][1]:.2f}",
            f"- final state finite: {c['final_finite']}; list overflowed: {c['overflowed']}",
            "",
            "### Where the step time goes", "",
            profile_table(c), "",
        ]
    if report.get("sweep"):
        lines += ["## XLA flag / core-count sweep (child processes, fewer chunks)", "",
                  sweep_table(report["sweep"]), "",
                  "`intra_op_parallelism_threads` is not an XLA flag (XLA rejects `--intra_op_parallelism_threads`; "
                  "a bare token is ignored); the CPU thread pool follows the process's CPU affinity, "
                  "which `--cpus` sets.", ""]
    Path(path).write_text("\n".join(lines))


def print_summary(report):
    print()
    print("=" * 100)
    env = report["environment"]
    print(f"jdem benchmark  {env['date_utc']}  jax {env['jax_version']}  {env['dtype']}  "
          f"{env['backend']}:{env['device']}  CPU '{env['cpu_model']}' x{env['cpu_count']}"
          + (f"  [{env['device_label']}]" if env["device_label"] else ""))
    print(f"XLA_FLAGS='{env['xla_flags']}'")
    hdr = (f"{'case':>12} {'N':>9} {'Mpst/s med':>11} {'best':>8} {'window':>8} {'steps/s':>8} "
           f"{'pairs':>9} {'cap':>9} {'touch':>9} {'Mpair/s':>8} {'Mtouch/s':>8} {'rebuilds':>9} {'target':>22}")
    print(hdr)
    for c in report["cases"]:
        tp = c["throughput"]
        tgt = c.get("target")
        ts = "-"
        if tgt:
            ts = f">={tgt['target'] / 1e6:.1f}M ({tp['median']['particle_steps_per_s'] / tgt['target']:.2f}x)"
        print(f"{str(c['dim']) + 'D ' + c['packing']['lattice']:>12} {c['n']:>9,} "
              f"{tp['median']['particle_steps_per_s'] / 1e6:>11.3f} {tp['best']['particle_steps_per_s'] / 1e6:>8.3f} "
              f"{tp['aggregate']['particle_steps_per_s'] / 1e6:>8.3f} {tp['median']['steps_per_s']:>8.1f} "
              f"{c['listed_pairs_mean']:>9,.0f} {c['neighbour_capacity']:>9,} {c['touching_contacts_mean']:>9,.0f} "
              f"{tp['median']['listed_pair_updates_per_s'] / 1e6:>8.2f} "
              f"{tp['median']['touching_contact_updates_per_s'] / 1e6:>8.2f} "
              f"{c['rebuilds_timed']:>4}/{c['steps_timed']:<4} {ts:>22}")
        if tgt:
            print(f"{'':>12} reference: {tgt['reference']}")
    for c in report["cases"]:
        prof = c.get("profile")
        if not prof:
            continue
        print(f"\n{c['dim']}D N={c['n']:,}: profile (best of repeats, ms); measured "
              f"{c['throughput']['aggregate']['ms_per_step']:.3f} ms/step over the window")
        for name, r in prof.items():
            if isinstance(r, dict) and "best_ms" in r:
                print(f"  {name:26s} {r['best_ms']:10.3f}  (median {r['median_ms']:.3f})")
        cm = c.get("cost_model", {})
        if c.get("throughput_vs_rebuild_interval"):
            print("  M particle-steps/s at rebuild every 5/10/20/50/100/never steps: " + " / ".join(
                f"{v / 1e6:.2f}" for v in c["throughput_vs_rebuild_interval"].values()))
        if cm.get("parts_ms_per_step"):
            print("  cost model per step: " + ", ".join(
                f"{k} {v:.2f} ms ({100 * cm['shares'][k]:.0f}%)" for k, v in cm["parts_ms_per_step"].items())
                + f"; predicted {cm['predicted_ms_per_step']:.2f} vs measured {cm['measured_ms_per_step']:.2f}")
    if report.get("sweep"):
        print("\nsweep:")
        for r in report["sweep"]:
            for c in r.get("cases", []):
                print(f"  {r['label']:26s} {c['dim']}D {c['n']:>8,}  {c['particle_steps_per_s_median'] / 1e6:7.3f} M "
                      f"particle-steps/s  build {_ms(c['build_ms'])} ms  step {_ms(c['step_ms'])} ms  "
                      f"contact {_ms(c['contact_forces_ms'])} ms  walls {_ms(c['wall_forces_ms'])} ms")
    print("=" * 100)


# ----------------------------------------------------------------------------- main
def main(args):
    env = environment(args)
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
