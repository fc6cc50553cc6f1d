"""The solvers' steps: Levenberg-Marquardt and Gauss-Newton from optimistix,
Adam from optax, and the Jacobian by forward or reverse mode, each jitted once
per process (:func:`compiled_steps`)."""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jdem.calibrate.problem import grow_term, residual_problem
from jdem.validate import InputError


def forward_jacobian(fn, u, args):
    """``(r, aux, J)``: residuals (n,), aux and Jacobian (n, k) d r / d u of
    ``fn(u, args)`` by forward mode in one pass (``jax.jacfwd``: the run with k
    tangents, the primal computed once).  ``jax.linearize`` followed by the k
    tangents costs one forward run more: through the simulation's while loop it
    runs the primal, then the primal again with the tangents (measured by
    experiments/jacobian_cost.py)."""
    def with_residuals(v):
        r, aux = fn(v, args)
        return r, (r, aux)

    J, (r, aux) = jax.jacfwd(with_residuals, has_aux=True)(u)
    return r, aux, J


#: the default step of a finite-difference Jacobian, in the internal coordinate u:
#: about 1.6 % of a value in the middle of default bounds (start / 5 .. start x 5,
#: d ln(value) / du = ln(25) / 4 there)
FD_STEP = 0.02


def finite_difference_jacobian(fn, u, args, step=FD_STEP):
    """``(r, aux, J)`` as :func:`forward_jacobian`, J by central differences
    (fn(u + h e_i) - fn(u - h e_i)) / 2h: 2k + 1 runs.  The 2k shifted runs go
    one after another (``jax.lax.map``), not vmapped: under a vmap the
    simulation's un-batched conditionals (the neighbour rebuild of a batch, the
    bond law's branch, :func:`jdem.integrate.step_batched`) would take batched
    predicates and run both branches every step.

    What for.  Past the peak of a specimen of ~1,000 discs every bond break
    moves the ones after it, and the exact (pathwise) derivative grows with each
    break in the cascade: at the held-out check's size the forward-mode
    derivatives of the post-peak curve are ~1e5 times the parameters' own scale
    (experiments/results/heldout_calibration/NOTES.md), and Levenberg-Marquardt's
    steps shrink to nothing.  A difference over a step of a few per cent is the
    slope of the response that the next packing would also show.  The aux
    flags of the shifted runs join the base run's: ``overflowed`` if any
    overflowed, a member ``ok`` only if it ran in all of them."""
    r, aux = fn(u, args)
    shifts = step * jnp.eye(u.shape[0], dtype=u.dtype)
    rs, auxs = jax.lax.map(lambda v: fn(v, args), jnp.concatenate([u + shifts, u - shifts]))
    k = u.shape[0]
    J = ((rs[:k] - rs[k:]) / (2.0 * step)).T
    if isinstance(aux, dict) and "overflowed" in aux:
        aux = dict(aux, overflowed=aux["overflowed"] | jnp.any(auxs["overflowed"], axis=0),
                   ok=tuple(o & jnp.all(oo, axis=0) for o, oo in zip(aux["ok"], auxs["ok"])))
    return r, aux, J


#: how each Jacobian mode but "reverse" is computed: (fn, u, args, step) -> (r, aux, J)
MATERIALISED = {"forward": lambda fn, u, args, step: forward_jacobian(fn, u, args),
                "finite-difference": finite_difference_jacobian}


def _zero_cotangent(x):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, jax.dtypes.float0)


def _run_with_jacobian(fn, u, args, mode="forward", step=FD_STEP):
    import equinox as eqx

    # the arrays of fn (traced under jit) travel as an argument of the custom VJP
    dynamic, static = eqx.partition(fn, eqx.is_array)

    @jax.custom_vjp
    def run(dyn, v, a):
        return eqx.combine(dyn, static)(v, a)

    def run_fwd(dyn, v, a):
        r, aux, J = MATERIALISED[mode](eqx.combine(dyn, static), v, a, step)
        return (r, aux), (dyn, r, J, a)

    def run_bwd(res, ct):
        dyn, r, J, a = res
        ct_r, ct_aux = ct
        g = J.T @ ct_r
        if isinstance(ct_aux, dict) and "loss" in ct_aux:      # loss = sum r^2
            g = g + 2.0 * (J.T @ r) * ct_aux["loss"]
        zero = lambda tree: jax.tree_util.tree_map(_zero_cotangent, tree)
        return zero(dyn), g, zero(a)

    run.defvjp(run_fwd, run_bwd)
    return run(dynamic, u, args)


def with_materialised_jacobian(fn, mode="forward", step=FD_STEP):
    """``fn(u, args) -> (residuals, aux)`` whose reverse-mode derivative is the
    Jacobian computed once in the forward pass: one forward-mode pass
    (:func:`forward_jacobian`), or with ``mode`` "finite-difference"
    :func:`finite_difference_jacobian` with ``step``, kept as the matrix J: its
    VJP is J^T times the cotangent (and 2 J^T r times that of ``aux["loss"]``,
    the sum of squares, if aux has one).  Returned as a ``jax.tree_util.Partial``.

    Why.  optimistix's Gauss-Newton family with ``jac="fwd"`` linearises ``fn`` at
    every trial point and applies the linear map three times per iteration: to
    materialise the Jacobian for the damped solve (k tangents), to predict the
    trust region's reduction (one tangent) and, after a rejected step, to
    materialise the old point's Jacobian again.  Through the simulation's while
    loop each application is a whole run with tangents: 1.6-1.9 Jacobians per
    iteration (measured by experiments/jacobian_cost.py).  With ``jac="bwd"``
    optimistix materialises the Jacobian once per trial point by ``jax.jacrev``;
    with this wrapper that is one forward-mode pass and n small products, so an
    iteration costs one Jacobian."""
    if mode not in MATERIALISED:
        raise InputError(f"mode must be one of {sorted(MATERIALISED)}, got {mode!r}")
    return jax.tree_util.Partial(_run_with_jacobian, fn, mode=mode, step=float(step))


def _jacobian_impl(fn, u, args, mode, step=FD_STEP):
    if mode in MATERIALISED:
        r, aux, J = MATERIALISED[mode](fn, u, args, step)
        return r, J, aux
    r, vjp, aux = jax.vjp(lambda v: fn(v, args), u, has_aux=True)
    return r, jax.vmap(vjp)(jnp.eye(r.shape[0], dtype=r.dtype))[0], aux


def jacobian_at(fn, u, args, mode, *, step=FD_STEP, with_aux=False):
    """Residuals (n,) and Jacobian (n, k) d r / d u at ``u`` as NumPy, by
    ``mode`` "forward" (:func:`forward_jacobian`), "reverse" (``jax.vjp``) or
    "finite-difference" (:func:`finite_difference_jacobian` with ``step``);
    with ``with_aux``, also ``fn``'s aux (as NumPy)."""
    r, J, aux = compiled_steps()["jacobian"](fn, u, args, mode, float(step))
    if with_aux:
        return np.asarray(r), np.asarray(J), jax.tree_util.tree_map(np.asarray, aux)
    return np.asarray(r), np.asarray(J)


@functools.cache
def compiled_steps():
    """The jitted steps, built once per process and kept at module level, so a
    second ``calibrate`` call on the same set-up (a resumed fit, a notebook cell
    run again) reuses their compilation: ``fn`` is a ``jax.tree_util.Partial`` (a
    pytree), its arrays traced and the rest (names, bounds, plan) static."""
    import equinox as eqx

    return dict(
        jacobian=eqx.filter_jit(_jacobian_impl),
        init=eqx.filter_jit(lambda solver, fn, y, a, o, f_struct, aux_struct, tags:
                            solver.init(fn, y, a, o, f_struct, aux_struct, tags)),
        step=eqx.filter_jit(lambda solver, fn, y, s, a, o, tags:
                            solver.step(fn, y, a, o, s, tags)),
        terminate=eqx.filter_jit(lambda solver, fn, y, s, a, o, tags:
                                 solver.terminate(fn, y, a, o, s, tags)),
        value_and_grad=eqx.filter_jit(_value_and_grad_impl))


#: why a fit stopped: the solver's criterion (or ``tol``) met; no improvement by
#: ``min_improvement`` over ``patience`` accepted iterations, or ``MAX_REJECTED``
#: rejected steps in a row; the iteration budget spent
STOPS = ("converged", "stalled", "steps")
#: rejected Levenberg-Marquardt steps, with no accepted improvement by
#: ``min_improvement`` between them, after which a fit counts as stalled.  Each
#: rejection multiplies the trust region's step size by 0.25 (optimistix's
#: ClassicalTrustRegion), so five leave it at 0.25^5 ~ 1e-3 of where it was: the
#: linearised model no longer predicts a fall of the loss at any useful step.
#: Measured on the README demo (E and strength, 20 iterations): the loss reached
#: 9.897e-5 at iteration 8, then 8 rejections, one accepted step to 9.835e-5
#: (-0.6 %, E moved by 0.003 %) and 3 more rejections; ten in a row never stopped it.
MAX_REJECTED = 5


class Progress:
    """A fit's stall bookkeeping, shared by the solvers (host side).

    ``update(loss, accepted)`` after each iteration returns a reason string
    when the fit has stalled, else ``None``: ``patience`` accepted iterations
    in a row that did not lower the best loss by a fraction ``min_improvement``,
    or ``max_rejected`` rejected steps (``accepted`` False: the solver kept its
    point) with no such improvement between them.  Only an improvement by
    ``min_improvement`` resets both counts."""

    def __init__(self, best, patience, min_improvement, max_rejected=MAX_REJECTED):
        self.best, self.patience = best, patience
        self.min_improvement, self.max_rejected = min_improvement, max_rejected
        self.stall = self.rejected = 0

    def update(self, loss, accepted=True):
        if accepted and loss < self.best * (1.0 - self.min_improvement):
            self.stall = self.rejected = 0
        elif accepted:
            self.stall += 1
        else:
            self.rejected += 1
        if accepted:
            self.best = min(self.best, loss)
        if self.stall >= self.patience:
            return (f"no improvement by {self.min_improvement:g} over {self.patience} "
                    f"accepted iterations; the point may not be a minimum: try other "
                    f"start values")
        if self.rejected >= self.max_rejected:
            return (f"{self.max_rejected} steps rejected without an improvement by "
                    f"{self.min_improvement:g} in between (the trust region shrank "
                    f"{4 ** self.max_rejected:g}-fold): the linearised model predicts a "
                    f"fall the loss does not show, as near a minimum of a loss with kinks "
                    f"(bond breaks); check the fitted curves and the intervals.  Far "
                    f"from a minimum, past the peak of a large specimen, the exact "
                    f"derivative through the break cascade misleads: try "
                    f"jacobian='finite-difference'")
        return None


def least_squares(terms, plist, u, names, lims, record, history, steps, *, method, jacobian,
                   rtol, atol, tol, patience, min_improvement, fd_step=FD_STEP, **_):
    """Levenberg-Marquardt / Gauss-Newton (optimistix), one host step per iteration.

    Returns ``(stop, why, terms)``, ``stop`` one of :data:`STOPS` and ``why`` the
    :class:`Progress` reason of a stall.  An iteration whose trial step the solver
    rejects keeps the point and its loss; it counts towards ``MAX_REJECTED``, not
    towards ``patience`` (a rejection is the trust region shrinking, the normal
    course of Levenberg-Marquardt)."""
    import optimistix as optx

    solver = (optx.LevenbergMarquardt if method == "lm" else optx.GaussNewton)(rtol=rtol,
                                                                                atol=atol)
    # forward mode (and finite differences) go through optimistix's materialising
    # (jacrev) path with the Jacobian computed once inside (with_materialised_jacobian)
    options = dict(jac="bwd")
    tags = frozenset()
    progress = Progress(min(history["loss"]) if history["loss"] else np.inf, patience,
                        min_improvement)
    k = 0
    while k < steps:
        fn, args = residual_problem(names, lims, terms, plist)
        if jacobian in MATERIALISED:
            fn = with_materialised_jacobian(fn, jacobian, fd_step)
        f_struct, aux_struct = jax.eval_shape(fn, u, args)
        compiled = compiled_steps()
        # the state through the cached jit too, built as the cached step expects it
        state = compiled["init"](solver, fn, u, args, options, f_struct, aux_struct, tags)
        step = functools.partial(compiled["step"], solver, fn)
        terminate = functools.partial(compiled["terminate"], solver, fn)
        regrow = False
        while k < steps:
            u_before = np.asarray(u)
            u, state, _ = step(u, state, args, options, tags)
            aux = state.aux
            if bool(np.any(np.asarray(aux["overflowed"]))):
                terms = [grow_term(t) if bool(o) else t
                         for t, o in zip(terms, np.asarray(aux["overflowed"]))]
                regrow = True
                break
            loss = float(aux["loss"])
            if not np.isfinite(loss):
                raise RuntimeError(f"calibration iteration {len(history['loss'])}: the loss is "
                                   f"{loss!r} at {dict(zip(names, np.asarray(u)))} (internal "
                                   f"coordinates); narrow the bounds")
            if k == 0 and not all(bool(np.any(np.asarray(o))) for o in aux["ok"]):
                raise InputError("a test (every member of it) diverges at the start values; "
                                 "change them or the time step")
            record(u, loss, aux["ok"])
            k += 1
            # the first iteration evaluates the start point, which is accepted
            accepted = k == 1 or not np.array_equal(u_before, np.asarray(u))
            why = progress.update(loss, accepted)
            done, _result = terminate(u, state, args, options, tags)
            if bool(done) or loss < tol:
                return "converged", None, terms
            if why is not None:
                return "stalled", why, terms
        if not regrow:
            break
    return "steps", None, terms


def adam(terms, plist, u, names, lims, record, history, steps, *, jacobian, learning_rate,
          tol, patience, min_improvement, fd_step=FD_STEP, **_):
    """First-order fit: Adam (optax) on the sum of squares, gradient 2 J^T r by forward
    mode (or finite differences) or by ``jax.grad``; returns ``(stop, why, terms)`` as
    :func:`least_squares`."""
    import optax

    opt = optax.adam(optax.cosine_decay_schedule(learning_rate, max(int(steps), 1), alpha=0.05))
    state = opt.init(u)
    progress = Progress(min(history["loss"]) if history["loss"] else np.inf, patience,
                        min_improvement)
    k = 0
    vg_fn = None
    while k < steps:
        if vg_fn is None:   # built again after the neighbour list grew
            fn, args = residual_problem(names, lims, terms, plist)
            vg_fn = functools.partial(compiled_steps()["value_and_grad"], fn)
        loss, aux, g = vg_fn(u, args, jacobian, float(fd_step))
        if bool(np.any(np.asarray(aux["overflowed"]))):
            terms = [grow_term(t) if bool(o) else t
                     for t, o in zip(terms, np.asarray(aux["overflowed"]))]
            vg_fn = None
            continue
        loss = float(loss)
        if not np.isfinite(loss):
            raise RuntimeError(f"calibration iteration {len(history['loss'])}: the loss is "
                               f"{loss!r}; narrow the bounds")
        record(u, loss, aux["ok"])
        k += 1
        why = progress.update(loss)
        if loss < tol:
            return "converged", None, terms
        if why is not None:
            return "stalled", why, terms
        updates, state = opt.update(g, state, u)
        u = optax.apply_updates(u, updates)
    return "steps", None, terms


def _value_and_grad_impl(fn, u, args, mode, step=FD_STEP):
    if mode in MATERIALISED:
        r, aux, J = MATERIALISED[mode](fn, u, args, step)
        return jnp.sum(r ** 2), aux, 2.0 * J.T @ r

    def loss(v):
        r, aux = fn(v, args)
        return jnp.sum(r ** 2), aux

    (value, aux), g = jax.value_and_grad(loss, has_aux=True)(u)
    return value, aux, g
