"""Calibration of micro-parameters against laboratory curves and figures.

:func:`calibrate` fits named parameters (:data:`jdem.materials.PARAMETERS`:
``E`` [Pa], ``nu``, ``T0``, ``c0`` [Pa], ``phi`` [rad], ``eps_lim``,
``gamma_lim`` and the tied pairs ``strength`` (T0 = c0) and ``kappa``
(eps_lim = gamma_lim, 002 §2.1)) so that the pure lab tests
(:func:`jdem.lab.curve`, the same definition a production run uses) reproduce
one or several targets (:mod:`jdem.targets`: curves and scalar figures).

* Least squares on the residual vector of every target, in a bounded
  transformed space (value = lo (hi/lo)^sigmoid(u), linear when lo <= 0).
* Solvers: Levenberg-Marquardt (default) or Gauss-Newton from optimistix, with
  the Jacobian by forward mode (``jax.linearize``; chosen for k <= 8 fitted
  parameters) or reverse mode; Adam from optax as a first-order alternative.
* The set-ups must be quasi-static (:func:`jdem.lab.certify`), or the fit
  describes the loading rate, not the rock.
* An ensemble set-up (several packings, one vmapped run) contributes each
  member's residuals; a member that diverges is reported and its residuals
  count as a 100 % misfit, so the solver steps back instead of stopping.
* Every iteration is written to a checkpoint; ``resume=`` continues from it.
* At the optimum: standard errors, 95 % intervals and the correlation matrix from
  the Gauss-Newton approximation, and the parameters the data do not determine.
"""
from __future__ import annotations

import functools
import math
import pathlib
import time
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import io, lab
from jdem.materials import PARAMETERS, check_names, material, rock_params, values_of  # noqa: F401
from jdem.specimen import generate
from jdem.state import Params
from jdem.targets import (LossWeights, Scalar, Target, check_scalar, curve_loss,  # noqa: F401
                          curve_residuals, load_target, scalar_residuals)
from jdem.validate import InputError

#: default bounds, absolute; other parameters get start / 5 .. start x 5 (log space)
DEFAULT_BOUNDS = {"nu": (0.0, 0.45), "phi": (0.0, np.deg2rad(60.0))}
DEFAULT_FACTOR = 5.0
#: forward-mode Jacobians up to this many fitted parameters, reverse mode beyond
FORWARD_MODE_MAX = 8
METHODS = ("lm", "gauss_newton", "adam")


# ----------------------------------------------------------------------------- bounded transform
def _bounds_for(name, start, bounds):
    if bounds and name in bounds:
        lo, hi = (float(b) for b in bounds[name])
    elif name in DEFAULT_BOUNDS:
        lo, hi = DEFAULT_BOUNDS[name]
    else:
        lo, hi = start / DEFAULT_FACTOR, start * DEFAULT_FACTOR
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise InputError(f"bounds of {name!r} must be finite with lo < hi, got ({lo!r}, {hi!r})")
    if not lo < start < hi:
        raise InputError(f"start value of {name!r} = {start!r} is outside its bounds "
                         f"({lo!r}, {hi!r})")
    return lo, hi


def _to_value(u, lo, hi):
    """Internal (unbounded) -> value: log-uniform between lo > 0 and hi, linear if lo <= 0."""
    s = jax.nn.sigmoid(u)
    if lo > 0:
        return jnp.exp(math.log(lo) + s * (math.log(hi) - math.log(lo)))
    return lo + s * (hi - lo)


def _to_internal(v, lo, hi):
    s = (math.log(v / lo) / math.log(hi / lo)) if lo > 0 else (v - lo) / (hi - lo)
    return math.log(s / (1.0 - s))


def _log_space(lo):
    return lo > 0


def _dscale_du(u, lo, hi):
    """d(ln value)/du for log-space bounds, d(value)/du for linear ones."""
    s = 1.0 / (1.0 + math.exp(-u))
    return (math.log(hi / lo) if lo > 0 else hi - lo) * s * (1.0 - s)


# ----------------------------------------------------------------------------- the problem
class Term(NamedTuple):
    """One simulated test and what it is compared with: a :class:`Target` curve
    or a tuple of :class:`Scalar` figures."""

    setup: lab.Setup
    target: object
    weights: LossWeights


def _terms(setup, target, weights) -> list[Term]:
    setups = list(setup) if isinstance(setup, (list, tuple)) else [setup]
    targets = list(target) if isinstance(target, list) else [target]
    if len(setups) != len(targets):
        raise InputError(f"{len(setups)} set-up(s) but {len(targets)} target(s): give one "
                         f"target per set-up")
    out = []
    for k, (su, t) in enumerate(zip(setups, targets)):
        if not isinstance(su, lab.Setup):
            raise InputError(f"set-up {k} must be a jdem.lab.Setup, got {type(su).__name__}")
        if isinstance(t, Scalar):
            t = (t,)
        if isinstance(t, tuple) and t and all(isinstance(x, Scalar) for x in t):
            t = tuple(check_scalar(x) for x in t)
        else:
            t = load_target(t)
        out.append(Term(su, t, weights))
    return out


def _member_residuals(hist, term: Term):
    if isinstance(term.target, Target):
        return curve_residuals(hist["axial_strain"], hist["axial_stress"], term.target,
                               term.weights, hist.get("lateral_strain"))
    return scalar_residuals(hist, term.target)


def term_residuals(hist: dict, term: Term):
    """Residuals of one term from its pure-run history, and (members,) flags of
    the members that ran without diverging.  An ensemble's residuals are each
    member's over sqrt(members) (so the loss is the mean over members); a
    diverged member's residuals are set to 1 (a 100 % misfit)."""
    if term.setup.plan.batched:
        r = jax.vmap(lambda h: _member_residuals(h, term))(
            {k: v for k, v in hist.items() if jnp.ndim(v) >= 2})
        ok = (hist["member_first_bad_step"] < 0) & jnp.all(jnp.isfinite(r), axis=1)
        r = jnp.where(ok[:, None], r, 1.0) / math.sqrt(r.shape[0])
        return r.ravel(), ok
    r = _member_residuals(hist, term)
    ok = (hist["first_bad_step"] < 0) & jnp.all(jnp.isfinite(r))
    return jnp.where(ok, r, 1.0), ok[None]


def _residual_fn(u, args, *, names, lims, terms):
    """fn(u, args) -> (residuals, aux) with args = ((setup, params), ...) per term."""
    vals = {n: _to_value(u[i], *lims[n]) for i, n in enumerate(names)}
    rs, over, ok = [], [], []
    for term, (setup, params) in zip(terms, args):
        hist = lab.curve(setup, material(params, vals)).history
        r, good = term_residuals(hist, term)
        rs.append(r)
        over.append(hist["overflowed"])
        ok.append(good)
    r = jnp.concatenate(rs)
    return r, dict(overflowed=jnp.stack(over), ok=tuple(ok), loss=jnp.sum(r ** 2))


def _problem(names, lims, terms, plist):
    """``(fn, args)`` for the solvers: ``fn(u, args)`` is :func:`_residual_fn`
    bound to the names, bounds and terms as a ``jax.tree_util.Partial`` (a
    pytree, so the module-level jits of :func:`_compiled` see its arrays as
    traced and reuse their compilation), ``args`` the (set-up, params) pairs."""
    fn = jax.tree_util.Partial(_residual_fn, names=tuple(names), lims=lims, terms=tuple(terms))
    return fn, tuple((t.setup, p) for t, p in zip(terms, plist))


def calibration_loss(params: Params, setup, target, weights=LossWeights()):
    """Sum of squared residuals of ``params`` on one lab-test set-up against one
    target (the mean over an ensemble's members), and the pure run's history."""
    term = _terms(setup, target, weights)[0]
    hist = lab.curve(setup, params).history
    r, _ = term_residuals(hist, term)
    return jnp.sum(r ** 2), hist


# ----------------------------------------------------------------------------- result
class CalibrationResult(NamedTuple):
    """values        fitted parameters (name -> float), the best iterate
    loss          its sum of squared residuals
    start         the starting values
    history       ``loss`` (S,) and ``<name>`` (S,) per iteration (the accepted point)
    steps         iterations; ``converged``: the solver's tolerance (or ``tol``) was met
    params        ``Params`` with the fitted values
    curves        ``target_strain``, ``target_stress``, ``strain``, ``start_stress``,
                  ``fit_stress`` of the first curve target (members x records for
                  an ensemble); further terms prefixed ``term<k>_``
    wall_time     seconds
    method, jacobian   the solver and the Jacobian mode ("forward" / "reverse")
    std_errors    name -> standard error (same unit as the value)
    intervals     name -> (lo, hi) 95 % interval
    correlation   (k, k) correlation matrix of the fitted parameters (names order)
    poorly_determined  name -> why the data do not determine it
    diverged      list of (iteration, term, member) of ensemble members that diverged
    warnings      what makes the fit doubtful, e.g. a test whose fitted curve has no
                  peak before its end (:func:`peakless`)"""

    values: dict
    loss: float
    start: dict
    history: dict
    steps: int
    converged: bool
    params: Params
    curves: dict
    wall_time: float
    method: str = "lm"
    jacobian: str = "forward"
    std_errors: dict = {}
    intervals: dict = {}
    correlation: np.ndarray = np.zeros((0, 0))
    poorly_determined: dict = {}
    diverged: list = []
    warnings: list = []


def _uncertainty(J, r, u, names, lims, n_fit):
    """Gauss-Newton standard errors, 95 % intervals and correlations at ``u``.

    J (n, k) = dr/du; converted to d r / d ln(value) (log-space parameters) or
    d r / d value (linear ones).  Covariance s^2 (J^T J)^-1 with s^2 = RSS / (n - k),
    n the residuals that carry data.  The curve points are correlated, so these
    intervals are a lower bound on the true uncertainty."""
    k = len(names)
    scale = np.array([_dscale_du(float(u[i]), *lims[n]) for i, n in enumerate(names)])
    Jp = np.asarray(J) / scale[None, :]
    rss = float(np.sum(np.asarray(r) ** 2))
    dof = max(n_fit - k, 1)
    s2 = rss / dof
    jtj = Jp.T @ Jp
    why = {}
    norms = np.sqrt(np.diag(jtj))
    for i, n in enumerate(names):
        if not norms[i] > 0:
            why[n] = "the residuals do not depend on it"
    try:
        cov = s2 * np.linalg.pinv(jtj, rcond=1e-12)
    except np.linalg.LinAlgError:
        cov = np.full((k, k), np.nan)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    values = {n: float(_to_value(float(u[i]), *lims[n])) for i, n in enumerate(names)}
    std, intervals = {}, {}
    for i, n in enumerate(names):
        v = values[n]
        if _log_space(lims[n][0]):
            std[n] = v * float(sd[i])
            intervals[n] = (v * math.exp(-1.96 * sd[i]), v * math.exp(1.96 * sd[i]))
            if n not in why and sd[i] > 0.25:
                why[n] = f"relative standard error {100 * sd[i]:.0f} % (> 25 %)"
        else:
            std[n] = float(sd[i])
            intervals[n] = (v - 1.96 * sd[i], v + 1.96 * sd[i])
            if n not in why and 1.96 * sd[i] > 0.5 * (lims[n][1] - lims[n][0]):
                why[n] = "its 95 % interval spans more than half its bounds"
    for i in range(k):
        for j in range(i + 1, k):
            if abs(corr[i, j]) > 0.98:
                for n in (names[i], names[j]):
                    why.setdefault(n, f"correlation {corr[i, j]:+.3f} between {names[i]} "
                                      f"and {names[j]}: only a combination is determined")
    return std, intervals, corr, why


# ----------------------------------------------------------------------------- calibrate
def calibrate(setup, target, start: dict, *, params=None, bounds=None, method="lm",
              jacobian="auto", steps=30, rtol=1e-4, atol=1e-8, learning_rate=0.1,
              weights=LossWeights(), tol=1e-8, patience=None, min_improvement=1e-3,
              progress=True, out=None, checkpoint=None, resume=None,
              require_quasi_static=True) -> CalibrationResult:
    """Fit the named parameters of ``start`` to ``target``.

    setup          a :class:`jdem.lab.Setup` (e.g. ``jdem.lab.UCS.setup(specimen,
                   params)``: one packing or an ensemble), or a list of them
    target         anything :func:`jdem.targets.load_target` takes (a curve), a
                   :class:`~jdem.targets.Scalar` or tuple of them; a list, one per set-up
    start          name -> starting value (names from ``PARAMETERS``)
    params         the other parameters; default each set-up's own ``params``
    bounds         name -> (lo, hi); default ``DEFAULT_BOUNDS`` or start / 5 .. start x 5
    method         "lm" (Levenberg-Marquardt), "gauss_newton" or "adam"
    jacobian       "forward", "reverse" or "auto" (forward for <= 8 parameters)
    steps          at most this many iterations
    rtol, atol     the least-squares solvers' tolerances (on u and on the loss)
    learning_rate  Adam's step in u (cosine decay to 5 % over ``steps``)
    tol, patience  stop when the loss falls below ``tol``, or has not improved by
                   a fraction ``min_improvement`` for ``patience`` iterations
                   (default 3 for the least-squares solvers, 20 for Adam)
    out            HDF5 path for the result (:func:`save_calibration`)
    checkpoint     HDF5 path written after every iteration (default: next to
                   ``out``); ``resume``: such a file to continue from
    require_quasi_static  certify each set-up at the start values first
                   (:func:`jdem.lab.certify`) and refuse one that is not
    """
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}, got {method!r}")
    if patience is None:
        patience = 20 if method == "adam" else 3
    check_names(start)
    terms = _terms(setup, target, weights)
    names = list(start)
    k = len(names)
    if jacobian == "auto":
        jacobian = "forward" if k <= FORWARD_MODE_MAX else "reverse"
    if jacobian not in ("forward", "reverse"):
        raise InputError(f"jacobian must be 'forward', 'reverse' or 'auto', got {jacobian!r}")
    lims = {n: _bounds_for(n, float(start[n]), bounds) for n in names}
    plist = [t.setup.params if params is None else params for t in terms]
    history = {"loss": [], **{n: [] for n in names}}
    done = 0
    values0 = {n: float(start[n]) for n in names}
    if resume is not None:
        back = load_calibration(resume)
        if sorted(back["values"]) != sorted(names):
            raise InputError(f"resume file {resume} fits {sorted(back['values'])}, not "
                             f"{sorted(names)}")
        history = {kk: list(v) for kk, v in back["history"].items()}
        done = back["steps"]
        values0 = {n: back["values"][n] for n in names}
    if require_quasi_static:
        for i, t in enumerate(terms):
            cert = lab.certify(t.setup, material(plist[i], start))
            if not cert.quasi_static:
                raise InputError(f"set-up {i} ({t.setup.plan.test.name}) is not quasi-static: "
                                 f"{cert}; lower loading_rate, or pass "
                                 f"require_quasi_static=False")
    if checkpoint is None and out is not None:
        checkpoint = pathlib.Path(out).with_suffix(".checkpoint.h5")
    t0 = time.time()
    curves0 = _curves(terms, plist, {n: float(start[n]) for n in names})
    terms = [t._replace(setup=c[1]) for t, c in zip(terms, curves0)]
    u = jnp.asarray([_to_internal(values0[n], *lims[n]) for n in names])
    n_data = sum(_n_data(t) for t in terms)

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, initial=min(done, steps), unit="it",
                   desc=f"calibrate ({method}, {jacobian} Jacobian)", leave=False)
    diverged, converged = [], False
    best = (min(history["loss"]) if history["loss"] else np.inf, dict(values0))

    def record(u_now, loss, ok):
        nonlocal best
        vals = {n: float(_to_value(float(u_now[i]), *lims[n])) for i, n in enumerate(names)}
        history["loss"].append(float(loss))
        for n in names:
            history[n].append(vals[n])
        for ti, flags in enumerate(ok):
            for m in np.flatnonzero(~np.asarray(flags)):
                diverged.append((len(history["loss"]) - 1, ti, int(m)))
        if float(loss) < best[0]:
            best = (float(loss), vals)
        if checkpoint is not None:
            _save(checkpoint, _partial_result(best, start, history, terms, plist, method,
                                              jacobian, time.time() - t0))
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{float(loss):.3g}")

    try:
        stepper = _adam if method == "adam" else _least_squares
        converged, terms = stepper(terms, plist, u, names, lims, record, history,
                                   steps - done, method=method, jacobian=jacobian, rtol=rtol,
                                   atol=atol, learning_rate=learning_rate, tol=tol,
                                   patience=patience, min_improvement=min_improvement)
    finally:
        if bar is not None:
            bar.close()
    # uncertainty and curves at the best point
    ub = jnp.asarray([_to_internal(best[1][n], *lims[n]) for n in names])
    fn, args = _problem(names, lims, terms, plist)
    r, J = _jacobian(fn, ub, args, jacobian)
    std, intervals, corr, why = _uncertainty(J, r, np.asarray(ub), names, lims, n_data)
    curves1 = _curves(terms, plist, best[1])
    doubts = peakless(terms, [h for h, _ in curves1])
    for msg in doubts:
        warnings.warn(msg, stacklevel=2)
    curves = _merge_curves(terms, curves0, curves1)
    fitted = material(plist[0], best[1])
    res = CalibrationResult(values=best[1], loss=best[0], start=dict(start),
                            history={kk: np.asarray(v) for kk, v in history.items()},
                            steps=len(history["loss"]), converged=converged, params=fitted,
                            curves=curves, wall_time=time.time() - t0, method=method,
                            jacobian=jacobian, std_errors=std, intervals=intervals,
                            correlation=corr, poorly_determined=why, diverged=diverged,
                            warnings=doubts)
    if out is not None:
        save_calibration(out, res)
    return res


def peakless(terms, histories) -> list:
    """Messages for the terms whose fitted run peaks at its last record: the
    "peak" stress of a curve or a peak / strength target is then only the
    stress where the loading stopped, not a failure (load further: a larger
    ``max_strain``).  ``histories``: one NumPy history per term."""
    out = []
    for k, (term, hist) in enumerate(zip(terms, histories)):
        needs_peak = isinstance(term.target, Target) or any(
            t.quantity in ("peak_stress", "tensile_strength") for t in term.target)
        if not needs_peak:
            continue
        key = "tensile_strength_indirect" if "tensile_strength_indirect" in hist \
            else "axial_stress"
        stress = np.atleast_2d(np.asarray(hist[key]))
        last = [m for m in range(stress.shape[0])
                if int(np.argmax(stress[m])) == stress.shape[1] - 1]
        if last:
            out.append(f"term {k} ({term.setup.plan.test.name}): the fitted curve of member(s) "
                       f"{last} has no peak before the end of loading, so its peak is the "
                       f"stress where loading stopped; raise max_strain")
    return out


def _n_data(term):
    n = len(term.target.strain) if isinstance(term.target, Target) else len(term.target)
    return n * term.setup.n_members


def _jacobian_impl(fn, u, args, mode):
    if mode == "forward":
        r, lin = jax.linearize(lambda v: fn(v, args)[0], u)
        return r, jax.vmap(lin, out_axes=1)(jnp.eye(u.shape[0], dtype=u.dtype))
    r, vjp = jax.vjp(lambda v: fn(v, args)[0], u)
    return r, jax.vmap(vjp)(jnp.eye(r.shape[0], dtype=r.dtype))[0]


def _jacobian(fn, u, args, mode):
    r, J = _compiled()["jacobian"](fn, u, args, mode)
    return np.asarray(r), np.asarray(J)


@functools.cache
def _compiled():
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


def _least_squares(terms, plist, u, names, lims, record, history, steps, *, method, jacobian,
                   rtol, atol, tol, patience, min_improvement, **_):
    """Levenberg-Marquardt / Gauss-Newton (optimistix), one host step per iteration."""
    import equinox as eqx
    import optimistix as optx

    solver = (optx.LevenbergMarquardt if method == "lm" else optx.GaussNewton)(rtol=rtol,
                                                                                atol=atol)
    options = dict(jac="fwd" if jacobian == "forward" else "bwd")
    tags = frozenset()
    stall, last = 0, (min(history["loss"]) if history["loss"] else np.inf)
    k = 0
    while k < steps:
        fn, args = _problem(names, lims, terms, plist)
        f_struct, aux_struct = jax.eval_shape(fn, u, args)
        compiled = _compiled()
        # through the cached jit too: the state holds the linearised function as a
        # jaxpr, which the step's cache compares by identity
        state = compiled["init"](solver, fn, u, args, options, f_struct, aux_struct, tags)
        step = functools.partial(compiled["step"], solver, fn)
        terminate = functools.partial(compiled["terminate"], solver, fn)
        regrow = False
        while k < steps:
            u, state, _ = step(u, state, args, options, tags)
            aux = state.aux
            if bool(np.any(np.asarray(aux["overflowed"]))):
                terms = [t._replace(setup=lab.grow(t.setup)) if bool(o) else t
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
            stall = 0 if loss < last * (1.0 - min_improvement) else stall + 1
            last = min(last, loss)
            done, _result = terminate(u, state, args, options, tags)
            if bool(done) or loss < tol:
                return True, terms
            if stall >= patience:
                return True, terms
        if not regrow:
            break
    return False, terms


def _adam(terms, plist, u, names, lims, record, history, steps, *, jacobian, learning_rate,
          tol, patience, min_improvement, **_):
    """First-order fit: Adam (optax) on the sum of squares, gradient 2 J^T r by forward
    mode or by ``jax.grad``."""
    import optax

    opt = optax.adam(optax.cosine_decay_schedule(learning_rate, max(int(steps), 1), alpha=0.05))
    state = opt.init(u)
    stall, last = 0, (min(history["loss"]) if history["loss"] else np.inf)
    k = 0
    vg_fn = None
    while k < steps:
        if vg_fn is None:   # built again after the neighbour list grew
            fn, args = _problem(names, lims, terms, plist)
            vg_fn = functools.partial(_compiled()["value_and_grad"], fn)
        loss, aux, g = vg_fn(u, args, jacobian)
        if bool(np.any(np.asarray(aux["overflowed"]))):
            terms = [t._replace(setup=lab.grow(t.setup)) if bool(o) else t
                     for t, o in zip(terms, np.asarray(aux["overflowed"]))]
            vg_fn = None
            continue
        loss = float(loss)
        if not np.isfinite(loss):
            raise RuntimeError(f"calibration iteration {len(history['loss'])}: the loss is "
                               f"{loss!r}; narrow the bounds")
        record(u, loss, aux["ok"])
        k += 1
        stall = 0 if loss < last * (1.0 - min_improvement) else stall + 1
        last = min(last, loss)
        if loss < tol or stall >= patience:
            return True, terms
        updates, state = opt.update(g, state, u)
        u = optax.apply_updates(u, updates)
    return False, terms




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


# ----------------------------------------------------------------------------- curves, files
def _curves(terms, plist, values):
    """[(history as NumPy, grown set-up)] per term at ``values``."""
    return [lab.checked_curve(t.setup, material(p, values)) for t, p in zip(terms, plist)]


def _merge_curves(terms, start, fit):
    out = {}
    for k, (t, (h0, _), (h1, _)) in enumerate(zip(terms, start, fit)):
        pre = "" if k == 0 else f"term{k}_"
        if isinstance(t.target, Target):
            out[pre + "target_strain"] = t.target.strain
            out[pre + "target_stress"] = t.target.stress
        out[pre + "strain"] = h0["axial_strain"]
        out[pre + "start_stress"] = h0["axial_stress"]
        out[pre + "fit_stress"] = h1["axial_stress"]
    return out


def _partial_result(best, start, history, terms, plist, method, jacobian, wall):
    return CalibrationResult(values=best[1], loss=best[0], start=dict(start),
                             history={k: np.asarray(v) for k, v in history.items()},
                             steps=len(history["loss"]), converged=False,
                             params=material(plist[0], best[1]), curves={}, wall_time=wall,
                             method=method, jacobian=jacobian)


def save_calibration(path, res: CalibrationResult):
    """Write a :class:`CalibrationResult` to HDF5 (``jdem.io.save_run``: params,
    history = iteration history and curves, attrs = fitted / start values, errors)."""
    return _save(path, res)


def _save(path, res):
    history = {f"iter_{k}": v for k, v in res.history.items()}
    history.update(res.curves)
    if np.size(res.correlation):
        history["correlation"] = np.asarray(res.correlation)
    attrs = {f"fit_{k}": v for k, v in res.values.items()}
    attrs.update({f"start_{k}": v for k, v in res.start.items()})
    attrs.update({f"stderr_{k}": v for k, v in res.std_errors.items()})
    attrs.update({f"ci95_{k}": list(v) for k, v in res.intervals.items()})
    attrs.update({f"undetermined_{k}": v for k, v in res.poorly_determined.items()})
    attrs.update(loss=res.loss, steps=res.steps, converged=res.converged,
                 wall_time=res.wall_time, method=res.method, jacobian=res.jacobian,
                 names=list(res.values), diverged=[list(d) for d in res.diverged],
                 warnings=list(res.warnings))
    return io.save_run(path, params=res.params, history=history, attrs=attrs)


def load_calibration(path) -> dict:
    """``{values, start, loss, steps, converged, history, curves, params, method,
    jacobian, std_errors, intervals, correlation, poorly_determined, warnings}`` from
    :func:`save_calibration` (or a checkpoint)."""
    rd = io.load_run(path)
    a = rd.attrs or {}
    hist = {k: np.asarray(v) for k, v in (rd.history or {}).items()}
    names = list(a.get("names", [k[4:] for k in a if k.startswith("fit_")]))
    return dict(values={n: float(a[f"fit_{n}"]) for n in names},
                start={k[6:]: float(v) for k, v in a.items() if k.startswith("start_")},
                loss=float(a["loss"]), steps=int(a["steps"]), converged=bool(a["converged"]),
                method=a.get("method"), jacobian=a.get("jacobian"),
                warnings=list(a.get("warnings", [])),
                std_errors={k[7:]: float(v) for k, v in a.items() if k.startswith("stderr_")},
                intervals={k[5:]: tuple(v) for k, v in a.items() if k.startswith("ci95_")},
                poorly_determined={k[13:]: v for k, v in a.items()
                                   if k.startswith("undetermined_")},
                correlation=hist.pop("correlation", np.zeros((0, 0))),
                history={k[5:]: v for k, v in hist.items() if k.startswith("iter_")},
                curves={k: v for k, v in hist.items() if not k.startswith("iter_")},
                params=rd.params)


def report(res: CalibrationResult, true_values=None) -> str:
    """A few lines: each fitted value with its standard error and 95 % interval,
    and the parameters the data leave undetermined."""
    lines = [f"{res.method}, {res.jacobian}-mode Jacobian: loss {res.loss:.3g} after "
             f"{res.steps} iterations ({res.wall_time:.0f} s)"]
    for n, v in res.values.items():
        se = res.std_errors.get(n, float("nan"))
        lo, hi = res.intervals.get(n, (float("nan"), float("nan")))
        line = (f"  {n:9s} {v:.5g} +- {se:.2g}  (95 %: {lo:.4g} .. {hi:.4g}; "
                f"start {res.start[n]:.4g})")
        if true_values and n in true_values:
            line += f"  true {true_values[n]:.4g} ({100 * (v / true_values[n] - 1):+.2f} %)"
        lines.append(line)
    for n, why in res.poorly_determined.items():
        lines.append(f"  not determined: {n}: {why}")
    for msg in res.warnings:
        lines.append(f"  warning: {msg}")
    if res.diverged:
        lines.append(f"  {len(res.diverged)} ensemble member run(s) diverged (iteration, "
                     f"term, member): {res.diverged[:5]}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- demo problem
#: true values of the demonstration problem (002 §2 material, kappa = 0.3 %)
DEMO_TRUE = dict(E=30e9, strength=3e6, kappa=3e-3)


def demo_problem(*, seed=2, size=(0.004, 0.008), radii=(0.2e-3, 0.35e-3), kappa_known=True,
                 loading_rate=None):
    """A small calibration problem with a known answer (used by ``jdem demo`` and
    notebooks/calibration.ipynb): a ~100-disc bonded specimen (4 mm x 8 mm) in
    the quasi-static UCS test, the target curve simulated with ``DEMO_TRUE`` and
    a start with E 40 % high and the strength 30 % low (and kappa 50 % high
    unless ``kappa_known``).  Returns ``(setup, params, target curve dict
    (strain, stress), true values, start values)``."""
    spec = generate("rectangle", size, *radii, seed=seed, target_coordination=4.5)
    setup = lab.UCS.setup(spec, rock_params(2, kappa=DEMO_TRUE["kappa"]), max_strain=1.2e-3,
                          stiffness_margin=2.0, loading_rate=loading_rate)
    params = setup.params
    hist, setup = lab.checked_curve(setup, material(params, DEMO_TRUE))
    curve = dict(strain=hist["axial_strain"], stress=hist["axial_stress"])
    start = dict(E=1.4 * DEMO_TRUE["E"], strength=0.7 * DEMO_TRUE["strength"])
    if not kappa_known:
        start["kappa"] = 1.5 * DEMO_TRUE["kappa"]
    true = {k: DEMO_TRUE[k] for k in start}
    return setup, params, curve, true, start
