"""Benchmark cases: dense, deterministic packings in a box of walls, and a
description of the machine they run on."""
from __future__ import annotations

import datetime as _dt
import hashlib
import os
import platform
import shlex
import sys
from pathlib import Path

import numpy as np
import jax
import jax.numpy as jnp

import jdem
from jdem import timestep
from jdem.specimen import lattice

RADIUS = 1e-3  # r [m]; radii uniform in [0.8 r, r]
DENSITY = 2500.0
FRICTION = 0.5
TARGETS = {  # (backend, dim) -> particle-steps/s to compare against
    ("cpu", 3): dict(target=1.5e6, reference="YADE ~0.7 M particle-steps/s on one core",
                     note="target: >= 1.5 M particle-steps/s for 20,000 spheres on this 2-core CPU"),
    ("gpu", 3): dict(target=100e6, reference="CPU target 1.5 M particle-steps/s (2 cores)",
                     note="target: >= 100 M particle-steps/s at 1,000,000 spheres on one GPU"),
}

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
