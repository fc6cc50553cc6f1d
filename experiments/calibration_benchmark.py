"""Cost of gradients through a UCS test and throughput of a batched sweep.

    python experiments/calibration_benchmark.py [--steps 20000] [--batch 64]
                                                [--sweep-steps 2000] [--out DIR]

1. A ~1,000-disc bonded specimen (2D) in the differentiable UCS test
   (:data:`jdem.lab.UCS` run as the pure :func:`jdem.lab.curve`, the lab
   tests' default smooth damping, time step for twice the stiffness:
   ``stiffness_margin=2``) run for ``--steps`` steps: the forward time,
   the forward + backward time of ``jax.value_and_grad`` of the calibration loss
   with respect to all material parameters (compile time excluded, best of 2),
   and the memory of the gradient: XLA's own estimate for the compiled program
   (arguments + outputs + temporaries) and the growth of the process's peak
   resident memory while it ran; then the Jacobian of the stress curve with
   respect to k = 3 parameters (E, strength, kappa, in log space) by forward
   mode (``jax.jacfwd``: one pass with k tangents, what
   :func:`jdem.calibrate.calibrate` uses for Levenberg-Marquardt).
2. A sweep of ``--batch`` parameter sets of the same test as one vmapped call
   (an ensemble of copies of the specimen with one parameter set each),
   ``--sweep-steps`` steps: specimens x steps per second.

The platen speeds up over ``RAMP_TRANSITS`` wave transits through the specimen
(``SWEEP_RAMP_TRANSITS`` in the sweep), about the 8 (2) records of 100 steps
the benchmark used before the ramp was given in transits.

Writes ``calibration_benchmark.json`` and ``.md`` with the machine and date.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import platform
import resource
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jdem import calibrate, lab  # noqa: E402
from jdem.materials import material, rock_params  # noqa: E402
from jdem.specimen import generate  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
#: platen ramp [wave transits]; a transit of the 2.5 cm specimen is ~570 steps, so
#: these are about 8 and 2 records of 100 steps
RAMP_TRANSITS = 1.4
SWEEP_RAMP_TRANSITS = 0.35


def _rss_gib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20   # KiB -> GiB


def _best(fn, *args, repeat=2):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return min(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--sweep-steps", type=int, default=2000)
    ap.add_argument("--out", default=str(HERE / "results" / "calibration_benchmark"))
    ap.add_argument("--skip-gradient", action="store_true", help="only the sweep figure")
    a = ap.parse_args(argv)
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    spec = generate("rectangle", (0.0125, 0.025), 0.2e-3, 0.35e-3, seed=0, target_coordination=4.5)
    n = int(np.sum(np.asarray(spec.particles.valid)))
    record_every = 100
    platen_step = 2e-9
    strain = a.steps * platen_step / 0.025
    setup = lab.UCS.setup(spec, rock_params(2), platen_step=platen_step, max_strain=strain,
                          record_every=record_every, ramp_transits=RAMP_TRANSITS,
                          stiffness_margin=2.0)
    params = setup.params
    steps = setup.plan.n_records * record_every
    print(f"{n} discs, {steps} steps, {setup.plan.n_records} records, damping "
          f"{setup.plan.damping}")

    t_fwd = t_grad = t_jac = xla_bytes = rss1 = float("nan")
    if not a.skip_gradient:
        curve0, setup = lab.checked_curve(setup, params)
        target = calibrate.load_target(curve0)
        fwd = jax.jit(lambda p: lab.curve(setup, p).history["axial_stress"])
        t_fwd = _best(fwd, params)
        print(f"forward: {t_fwd:.2f} s ({n * steps / t_fwd / 1e6:.2f} M particle-steps/s)")

        start = material(params, dict(E=36e9, strength=2.5e6, kappa=4e-3))
        vg = jax.jit(jax.value_and_grad(lambda p: calibrate.calibration_loss(p, setup, target)[0]))
        compiled = vg.lower(start).compile()
        mem = compiled.memory_analysis()
        xla_bytes = None
        if mem is not None:
            xla_bytes = int(mem.argument_size_in_bytes + mem.output_size_in_bytes
                            + mem.temp_size_in_bytes)
        rss0 = _rss_gib()
        t_grad = _best(vg, start)
        rss1 = _rss_gib()
        print(f"forward+backward: {t_grad:.2f} s = {t_grad / t_fwd:.2f} x forward; XLA memory "
              f"{(xla_bytes or 0) / 2**30:.3f} GiB; peak RSS {rss1:.2f} GiB (+{rss1 - rss0:.2f})")
        names = ("E", "strength", "kappa")

        def curve_of(x):
            vals = dict(zip(names, jnp.exp(x)))
            return lab.curve(setup, material(params, vals)).history["axial_stress"]

        x0 = jnp.log(jnp.asarray([36e9, 2.5e6, 4e-3]))
        t_jac = _best(jax.jit(jax.jacfwd(curve_of)), x0)
        print(f"forward-mode Jacobian, k = 3: {t_jac:.2f} s = {t_jac / t_fwd:.2f} x forward "
              f"(ideal 1 + 1.5 k = 5.5)")

    # sweep: vmapped over parameter sets
    sweep_strain = a.sweep_steps * platen_step / 0.025
    ssetup = lab.UCS.setup([spec] * a.batch, rock_params(2), platen_step=platen_step,
                           max_strain=sweep_strain, record_every=record_every,
                           ramp_transits=SWEEP_RAMP_TRANSITS, stiffness_margin=2.0)
    sparams = ssetup.params
    s_steps = ssetup.plan.n_records * record_every
    rng = np.random.default_rng(0)
    values = dict(E=rng.uniform(20e9, 40e9, a.batch), strength=rng.uniform(2e6, 4e6, a.batch))
    batch = jax.vmap(lambda e, s: material(sparams, dict(E=e, strength=s)))(
        jnp.asarray(values["E"]), jnp.asarray(values["strength"]))
    # one parameter set per member of an ensemble of copies (batched neighbour refresh)
    swp = jax.jit(lambda p: lab.curve(ssetup, p).history["axial_stress"])
    t0 = time.perf_counter()
    jax.block_until_ready(swp(batch))
    t_compile = time.perf_counter() - t0
    t_sweep = _best(swp, batch, repeat=1)
    rate = a.batch * s_steps / t_sweep
    print(f"sweep: batch {a.batch} x {s_steps} steps in {t_sweep:.1f} s = {rate:.0f} "
          f"specimens x steps / s ({rate * n / 1e6:.2f} M particle-steps/s; compile {t_compile:.0f} s)")

    res = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="minutes"),
               machine=f"{platform.machine()} {os.cpu_count()} cores, {platform.platform()}",
               devices=[str(d) for d in jax.devices()], jax=jax.__version__, dtype="float64",
               command=" ".join(["python experiments/calibration_benchmark.py"]
                                + list(sys.argv[1:] if argv is None else argv)),
               n_particles=n, steps=steps, forward_s=t_fwd, forward_backward_s=t_grad,
               backward_over_forward=t_grad / t_fwd, jacobian_forward_k3_s=t_jac,
               jacobian_forward_over_forward=t_jac / t_fwd, gradient_xla_bytes=xla_bytes,
               peak_rss_gib=rss1, sweep_batch=a.batch, sweep_steps=s_steps, sweep_s=t_sweep,
               sweep_specimen_steps_per_s=rate)
    (out / "calibration_benchmark.json").write_text(json.dumps(res, indent=1))
    md = ["# Gradient cost and sweep throughput", "",
          f"{res['date']}, {res['machine']}, JAX {res['jax']}, {res['devices']}, float64", "",
          f"Command: `{res['command']}`", "",
          "| figure | value |", "|---|---|",
          f"| specimen | {n} discs, UCS, {steps} steps |",
          f"| forward | {t_fwd:.2f} s |",
          f"| forward + backward (value_and_grad, all parameters) | {t_grad:.2f} s ({t_grad / t_fwd:.2f} x forward) |",
          f"| forward-mode Jacobian, k = 3 (jacfwd) | {t_jac:.2f} s ({t_jac / t_fwd:.2f} x forward) |",
          f"| gradient memory, XLA estimate | {(xla_bytes or 0) / 2**30:.3f} GiB |",
          f"| process peak resident memory | {rss1:.2f} GiB |",
          f"| sweep, batch {a.batch} x {s_steps} steps | {t_sweep:.1f} s = {rate:.0f} specimens x steps / s |"]
    (out / "calibration_benchmark.md").write_text("\n".join(md) + "\n")
    print(f"-> {out}")


if __name__ == "__main__":
    main()
