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
after a compiling fit: an iteration should cost one Jacobian.  The same
through ``optimistix.least_squares`` with the residual function wrapped
(:func:`jdem.calibrate.solvers.with_materialised_jacobian`, what calibrate does)
and with optimistix's own forward mode (``jac="fwd"``), for comparison.
"""
import functools
import json
import pathlib
import time

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

from jdem import calibrate as cb  # noqa: E402
from jdem import lab, materials  # noqa: E402
from jdem.calibrate.problem import make_terms, residual_problem  # noqa: E402
from jdem.calibrate.solvers import jacobian_at, with_materialised_jacobian  # noqa: E402
from jdem.calibrate.transform import bounds_for, to_internal  # noqa: E402
from jdem.specimen import generate  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results" / "jacobian_cost"
LM_ITERATIONS = 7


def interleaved(calls, rounds=3):
    """name -> the least of ``rounds`` timings of ``calls[name]()``, after one
    compiling call each; the calls take turns within each round, so that a slow
    spell of the machine (2x for a minute has been seen here) falls on all."""
    for fn in calls.values():
        jax.block_until_ready(fn())
    best = {k: float("inf") for k in calls}
    for _ in range(rounds):
        for k, fn in calls.items():
            t = time.perf_counter()
            jax.block_until_ready(fn())
            best[k] = min(best[k], time.perf_counter() - t)
    return best


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

    true = dict(zip(names, [30e9, 3e6, 3e-3]))
    fn, args, u, lm_calls = lm_problem(setup, true)
    jit = jax.jit
    calls = {"forward": lambda f=jit(curve): f(x0),
             "jvp_one_tangent": lambda f=jit(lambda x: jax.jvp(curve, (x,), (jnp.eye(3)[0],))): f(x0),
             "jacfwd_k3": lambda f=jit(jax.jacfwd(curve)): f(x0),
             "linearize_k3": lambda f=jit(linearized): f(x0),
             "reverse_gradient": lambda f=jit(jax.grad(lambda x: jnp.sum(curve(x) ** 2))): f(x0),
             "residuals_forward": lambda f=jit(lambda v, a: fn(v, a)[0]): f(u, args),
             "residuals_jacobian_k3": lambda: jacobian_at(fn, u, args, "forward")}
    t = interleaved(calls)
    # an iteration: the difference of an LM_ITERATIONS- and a 1-iteration fit
    walls = interleaved({f"{k}_{n}": functools.partial(c, n) for k, c in lm_calls.items()
                         for n in (1, LM_ITERATIONS)}, rounds=2)
    for k in lm_calls:
        t[k] = (walls[f"{k}_{LM_ITERATIONS}"] - walls[f"{k}_1"]) / (LM_ITERATIONS - 1)
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


def lm_problem(setup, true):
    """The calibration's residual function ``fn(u, args)`` at the start point
    ``u`` (a stress-strain target from the curve at ``true``, start E +40 %,
    strength -30 %, kappa +50 %), and n -> an n-iteration fit from there three
    ways: ``lm_iteration`` :func:`jdem.calibrate.calibrate`;
    ``optx_iteration_wrapped`` ``optimistix.least_squares`` on the residuals
    wrapped as calibrate wraps them; ``optx_iteration_jac_fwd`` the same with
    optimistix's own forward mode (``jac="fwd"``: linearise, then apply the
    linear map for the solve, the trust region's prediction and after a
    rejection)."""
    import optimistix as optx

    hist, _ = lab.checked_curve(setup, materials.material(setup.params, true))
    target = dict(strain=hist["axial_strain"], stress=hist["axial_stress"])
    start = dict(E=1.4 * true["E"], strength=0.7 * true["strength"], kappa=1.5 * true["kappa"])
    names = list(start)
    lims = {n: bounds_for(n, start[n], None) for n in names}
    fn, args = residual_problem(names, lims, make_terms(setup, target, cb.LossWeights()),
                                [setup.params])
    u = jnp.asarray([to_internal(start[n], *lims[n]) for n in names])
    kw = dict(params=setup.params, progress=False, require_quasi_static=False)
    solver = optx.LevenbergMarquardt(rtol=1e-4, atol=1e-8)
    # optimistix's solve carries its aux through its own custom JVP, which takes no
    # boolean aux: the residuals alone
    plain = lambda v, a: (fn(v, a)[0], None)

    def optx_fit(f, jac, n):
        return optx.least_squares(f, solver, u, args=args, has_aux=True,
                                  options=dict(jac=jac), max_steps=n, throw=False).value

    calls = {"lm_iteration": lambda n: cb.calibrate(setup, target, start, steps=n, **kw).loss,
             "optx_iteration_wrapped": functools.partial(optx_fit, with_materialised_jacobian(plain),
                                                         "bwd"),
             "optx_iteration_jac_fwd": functools.partial(optx_fit, plain, "fwd")}
    return fn, args, u, calls


if __name__ == "__main__":
    main()
