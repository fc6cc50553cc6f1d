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

def _jacobian_impl(fn, u, args, mode):
    if mode == "forward":
        r, lin = jax.linearize(lambda v: fn(v, args)[0], u)
        return r, jax.vmap(lin, out_axes=1)(jnp.eye(u.shape[0], dtype=u.dtype))
    r, vjp = jax.vjp(lambda v: fn(v, args)[0], u)
    return r, jax.vmap(vjp)(jnp.eye(r.shape[0], dtype=r.dtype))[0]


def jacobian_at(fn, u, args, mode):
    """Residuals (n,) and Jacobian (n, k) d r / d u at ``u`` as NumPy, by
    ``mode`` "forward" (``jax.linearize``) or "reverse" (``jax.vjp``)."""
    r, J = compiled_steps()["jacobian"](fn, u, args, mode)
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
                    f"(bond breaks); check the fitted curves and the intervals")
        return None


def least_squares(terms, plist, u, names, lims, record, history, steps, *, method, jacobian,
                   rtol, atol, tol, patience, min_improvement, **_):
    """Levenberg-Marquardt / Gauss-Newton (optimistix), one host step per iteration.

    Returns ``(stop, why, terms)``, ``stop`` one of :data:`STOPS` and ``why`` the
    :class:`Progress` reason of a stall.  An iteration whose trial step the solver
    rejects keeps the point and its loss; it counts towards ``MAX_REJECTED``, not
    towards ``patience`` (a rejection is the trust region shrinking, the normal
    course of Levenberg-Marquardt)."""
    import optimistix as optx

    solver = (optx.LevenbergMarquardt if method == "lm" else optx.GaussNewton)(rtol=rtol,
                                                                                atol=atol)
    options = dict(jac="fwd" if jacobian == "forward" else "bwd")
    tags = frozenset()
    progress = Progress(min(history["loss"]) if history["loss"] else np.inf, patience,
                        min_improvement)
    k = 0
    while k < steps:
        fn, args = residual_problem(names, lims, terms, plist)
        f_struct, aux_struct = jax.eval_shape(fn, u, args)
        compiled = compiled_steps()
        # through the cached jit too: the state holds the linearised function as a
        # jaxpr, which the step's cache compares by identity
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
          tol, patience, min_improvement, **_):
    """First-order fit: Adam (optax) on the sum of squares, gradient 2 J^T r by forward
    mode or by ``jax.grad``; returns ``(stop, why, terms)`` as :func:`least_squares`."""
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
        loss, aux, g = vg_fn(u, args, jacobian)
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


def _value_and_grad_impl(fn, u, args, mode):
    if mode == "forward":
        def with_residuals(v):
            r, aux = fn(v, args)
            return r, (r, aux)

        J, (r, aux) = jax.jacfwd(with_residuals, has_aux=True)(u)
        return jnp.sum(r ** 2), aux, 2.0 * J.T @ r

    def loss(v):
        r, aux = fn(v, args)
        return jnp.sum(r ** 2), aux

    (value, aux), g = jax.value_and_grad(loss, has_aux=True)(u)
    return value, aux, g
