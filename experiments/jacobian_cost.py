"""Cost of a Jacobian of the UCS curve by forward and by reverse mode, against
one forward run (float64, the 104-disc specimen of tests/test_calibrate.py at
8x the quasi-static rate, 206 records).

    python experiments/jacobian_cost.py

Prints and writes experiments/results/jacobian_cost/jacobian_cost.json:
seconds for the forward curve, one JVP, ``jax.jacfwd`` over k = 3 parameters
(E, strength, kappa in log space), ``jax.linearize`` + the k tangents (one
forward run more than ``jacfwd`` through the simulation's while loop) and a
reverse-mode gradient of the sum of squares; each the best of 3 timed calls
after a compiling one.  Then the calibration itself: the residual function of
:func:`jdem.calibrate.calibrate` (a stress-strain target from the curve at
these values) forward and its forward-mode Jacobian
(:func:`jdem.calibrate.solvers.jacobian_at`), and the wall time of one
Levenberg-Marquardt iteration, from the difference of a 1- and an
``LM_ITERATIONS``-iteration fit from (E +40 %, strength -30 %, kappa +50 %)
after a compiling fit: an iteration should cost one Jacobian.
"""
import json
import pathlib
import time

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

from jdem import calibrate as cb  # noqa: E402
from jdem import lab, materials  # noqa: E402
from jdem.calibrate.problem import make_terms, residual_problem  # noqa: E402
from jdem.calibrate.solvers import jacobian_at  # noqa: E402
from jdem.calibrate.transform import bounds_for, to_internal  # noqa: E402
from jdem.specimen import generate  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results" / "jacobian_cost"
LM_ITERATIONS = 7


def best_of(fn, *args, n=3):
    jax.block_until_ready(fn(*args))          # compile
    times = []
    for _ in range(n):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return min(times)


def main():
    spec = generate("rectangle", (0.004, 0.008), 0.2e-3, 0.35e-3, seed=2, target_coordination=4.5)
    setup = lab.UCS.setup(spec, materials.rock_params(2, kappa=3e-3), max_strain=1.2e-3,
                          loading_rate=3.2e-5, stiffness_margin=2.0)
    names = ["E", "strength", "kappa"]
    x0 = jnp.log(jnp.array([30e9, 3e6, 3e-3]))

    def curve(x):
        vals = dict(zip(names, jnp.exp(x)))
        return lab.curve(setup, materials.material(setup.params, vals)).history["axial_stress"] / 1e6

    def linearized(x):
        _, lin = jax.linearize(curve, x)
        return jax.vmap(lin, out_axes=1)(jnp.eye(3))

    t = {"forward": best_of(jax.jit(curve), x0),
         "jvp_one_tangent": best_of(jax.jit(lambda x: jax.jvp(curve, (x,), (jnp.eye(3)[0],))), x0),
         "jacfwd_k3": best_of(jax.jit(jax.jacfwd(curve)), x0),
         "linearize_k3": best_of(jax.jit(linearized), x0),
         "reverse_gradient": best_of(jax.jit(jax.grad(lambda x: jnp.sum(curve(x) ** 2))), x0)}
    t.update(lm_costs(setup, dict(zip(names, [30e9, 3e6, 3e-3]))))
    res = dict(discs=int(spec.info["n_particles"]),
               steps=int(setup.plan.n_records * setup.plan.record_every), k=3,
               seconds=t, ratio_to_forward={k: v / t["forward"] for k, v in t.items()},
               lm_iteration_over_jacobian=t["lm_iteration"] / t["residuals_jacobian_k3"],
               device=str(jax.devices()[0]), date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "jacobian_cost.json").write_text(json.dumps(res, indent=1) + "\n")
    for k, v in t.items():
        print(f"{k:22s} {v:8.3f} s   {v / t['forward']:6.1f} x forward")
    print(f"one Levenberg-Marquardt iteration = "
          f"{t['lm_iteration'] / t['residuals_jacobian_k3']:.2f} Jacobians of the residuals")
    print(f"-> {OUT / 'jacobian_cost.json'}")


def lm_costs(setup, true):
    """Seconds of the calibration's residual function, its Jacobian and one
    Levenberg-Marquardt iteration (see the module docstring)."""
    hist, _ = lab.checked_curve(setup, materials.material(setup.params, true))
    target = dict(strain=hist["axial_strain"], stress=hist["axial_stress"])
    start = dict(E=1.4 * true["E"], strength=0.7 * true["strength"], kappa=1.5 * true["kappa"])
    names = list(start)
    lims = {n: bounds_for(n, start[n], None) for n in names}
    fn, args = residual_problem(names, lims, make_terms(setup, target, cb.LossWeights()),
                                [setup.params])
    u = jnp.asarray([to_internal(start[n], *lims[n]) for n in names])
    out = {"residuals_forward": best_of(jax.jit(lambda v, a: fn(v, a)[0]), u, args),
           "residuals_jacobian_k3": best_of(lambda v, a: jacobian_at(fn, v, a, "forward"),
                                            u, args)}
    kw = dict(params=setup.params, progress=False, require_quasi_static=False)
    cb.calibrate(setup, target, start, steps=2, **kw)            # compiles
    wall = {}
    for n in (1, LM_ITERATIONS):
        t = time.perf_counter()
        cb.calibrate(setup, target, start, steps=n, **kw)
        wall[n] = time.perf_counter() - t
    out["lm_iteration"] = (wall[LM_ITERATIONS] - wall[1]) / (LM_ITERATIONS - 1)
    return out


if __name__ == "__main__":
    main()
