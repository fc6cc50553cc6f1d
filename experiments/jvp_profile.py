"""Where a forward-mode tangent (JVP) of the bonded step spends its time, kernel by
kernel, against the forward step (XLA:CPU, jax.profiler).

    python experiments/jvp_profile.py                 # 0.012 m x 0.024 m block, 200 steps
    python experiments/jvp_profile.py --width 0.004   # the 104-disc block of jacobian_cost.py

The UCS set-up of ``experiments/jacobian_cost.py`` on a wider block (float64 params
cast to the set-up's precision); ``jdem.integrate.physics_step`` repeated ``--steps``
times with the parameters (E, strength, kappa) in log space as input, once forward
and once as ``jax.jvp`` along E.  Each is compiled, run once, then run once under
``jax.profiler.trace``; the trace's per-kernel (XLA thunk) times are summed.

Prints the wall time of both, their ratio and the ten costliest kernels of each,
and writes ``experiments/results/jvp_profile/jvp_profile.json``.
"""
from __future__ import annotations

import argparse
import collections
import gzip
import json
import pathlib
import tempfile
import time

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

from jdem import integrate, lab, materials  # noqa: E402
from jdem.specimen import generate  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results" / "jvp_profile"


def kernel_times(fn, x):
    """{kernel name: (total microseconds, calls)} of one profiled call of ``fn(x)``."""
    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d, create_perfetto_trace=True):
            jax.block_until_ready(fn(x))
        trace = next(pathlib.Path(d).rglob("*.trace.json.gz"))
        events = json.load(gzip.open(trace))
    events = events["traceEvents"] if isinstance(events, dict) else events
    total, calls = collections.Counter(), collections.Counter()
    for e in events:
        name = e.get("name", "")
        # kernels only: not the executor's own spans nor Python frames
        if e.get("ph") == "X" and not name.startswith(("$", "ThunkExecutor")):
            total[name] += e.get("dur", 0)
            calls[name] += 1
    return {k: (total[k], calls[k]) for k in total}


def best_of(fn, x, n=3):
    jax.block_until_ready(fn(x))
    times = []
    for _ in range(n):
        t = time.perf_counter()
        jax.block_until_ready(fn(x))
        times.append(time.perf_counter() - t)
    return min(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=float, default=0.012, help="block width [m] (height 2x)")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--out", type=pathlib.Path, default=OUT)
    a = ap.parse_args(argv)

    spec = generate("rectangle", (a.width, 2 * a.width), 0.2e-3, 0.35e-3, seed=2,
                    target_coordination=4.5)
    setup = lab.UCS.setup(spec, materials.rock_params(2, kappa=3e-3), max_strain=1.2e-3,
                          loading_rate=3.2e-5, stiffness_margin=2.0)
    names = ["E", "strength", "kappa"]
    x0 = jnp.log(jnp.array([30e9, 3e6, 3e-3]))
    tangent = jnp.eye(3)[0]
    state0, config = setup.state, setup.plan.config

    def steps(x):
        p = materials.material(setup.params, dict(zip(names, jnp.exp(x))))
        s, _ = jax.lax.scan(lambda s, _: (integrate.physics_step(s, p, config), None),
                            state0, None, length=a.steps)
        return s.particles.pos

    forward = jax.jit(steps)
    jvp = jax.jit(lambda x: jax.jvp(steps, (x,), (tangent,)))
    res = dict(discs=int(spec.info["n_particles"]), bonds=int(jnp.sum(state0.bonds.valid)),
               steps=a.steps, device=str(jax.devices()[0]),
               date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    for name, fn in (("forward", forward), ("jvp", jvp)):
        res[name + "_s"] = best_of(fn, x0)
        kernels = kernel_times(fn, x0)
        res[name + "_kernels_us"] = sum(t for t, _ in kernels.values())
        res[name + "_top"] = sorted(([k, t, c] for k, (t, c) in kernels.items()),
                                    key=lambda r: -r[1])[:10]
    res["ratio"] = res["jvp_s"] / res["forward_s"]
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "jvp_profile.json").write_text(json.dumps(res, indent=1) + "\n")
    print(f"{res['discs']} discs, {res['bonds']} bonds, {a.steps} steps: forward "
          f"{res['forward_s']:.3f} s, JVP {res['jvp_s']:.3f} s ({res['ratio']:.2f} x)")
    for name in ("forward", "jvp"):
        tot = res[name + "_kernels_us"]
        print(f"\n{name}: kernels {tot / 1e3:.1f} ms in the profiled call; costliest:")
        for k, t, c in res[name + "_top"]:
            print(f"  {t / 1e3:8.2f} ms {100 * t / tot:5.1f} %  x{c:<5d} {k}")
    print(f"-> {a.out / 'jvp_profile.json'}")


if __name__ == "__main__":
    main()
