"""Calibration of any differentiable model: the same bounded transform,
Levenberg-Marquardt solver and uncertainty as :func:`jdem.calibrate.calibrate`,
for a model that is not a lab test (rigid blocks, wave boundaries, a user's
own rollout).

``model(values) -> prediction`` maps a dict of named parameter values to an
array (or a tuple of arrays) of the shape of the data; it must be a JAX
function of the values (``jdem.simulate.rollout``, ``jdem.blocks.rollout``,
``jdem.lab.curve`` ...).  The residual of each data array is
(prediction - data) / scale, scale = max |data| unless given.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax.numpy as jnp
import numpy as np

from jdem.calibrate.result import uncertainty
from jdem.calibrate.solvers import jacobian_at, with_materialised_jacobian
from jdem.calibrate.transform import bounds_for, to_internal, to_value
from jdem.validate import InputError


class ModelFit(NamedTuple):
    """values, stderr, ci95 (dicts by name), correlation (k, k), undetermined
    (name -> reason), loss (sum of squared residuals), steps (solver
    iterations), converged (the solver's own criterion met)."""

    values: dict
    stderr: dict
    ci95: dict
    correlation: np.ndarray
    undetermined: dict
    loss: float
    steps: int
    converged: bool


def fit_model(model: Callable, data, start: dict, *, bounds: dict | None = None, scales=None,
              max_steps: int = 30, rtol: float = 1e-8, atol: float = 1e-12,
              jacobian: str = "forward") -> ModelFit:
    """Least-squares fit of ``model`` to ``data`` (module docstring).

    data      array, or tuple of arrays, shaped like the model's prediction
    start     name -> start value; bounds name -> (lo, hi) (default
              :func:`jdem.calibrate.transform.bounds_for`: start / 5 .. start x 5)
    scales    one residual scale per data array (default max |data| each)
    jacobian  "forward" (k <= ~8 parameters) or "reverse"
    """
    import optimistix as optx

    if not start:
        raise InputError("start must name at least one parameter")
    if jacobian not in ("forward", "reverse"):
        raise InputError(f"jacobian must be 'forward' or 'reverse', got {jacobian!r}")
    names = list(start)
    lims = {n: bounds_for(n, float(start[n]), bounds) for n in names}
    single = not isinstance(data, tuple)
    data = (data,) if single else tuple(data)
    data = tuple(jnp.asarray(d) for d in data)
    if scales is None:
        scales = tuple(float(jnp.max(jnp.abs(d))) for d in data)
    scales = tuple(float(s) for s in np.atleast_1d(scales))
    if len(scales) != len(data) or not all(np.isfinite(s) and s > 0 for s in scales):
        raise InputError(f"scales must be one positive number per data array, got {scales!r}")

    def values_of(u):
        return {n: to_value(u[i], *lims[n]) for i, n in enumerate(names)}

    def residuals(u, _):
        pred = model(values_of(u))
        pred = (pred,) if single else tuple(pred)
        if len(pred) != len(data):
            raise InputError(f"the model returned {len(pred)} arrays for {len(data)} data arrays")
        return jnp.concatenate([jnp.ravel((p - d) / s) for p, d, s in zip(pred, data, scales)])

    u0 = jnp.asarray([to_internal(float(start[n]), *lims[n]) for n in names])
    plain = lambda u, args: (residuals(u, args), None)
    # forward mode: one forward-mode pass per iteration (solvers.with_materialised_jacobian)
    fn = with_materialised_jacobian(plain) if jacobian == "forward" else plain
    sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=rtol, atol=atol), u0,
                             has_aux=True, options=dict(jac="bwd"), max_steps=max_steps,
                             throw=False)
    u = sol.value
    r, J = jacobian_at(plain, u, None, jacobian)      # residuals and Jacobian in one pass
    std, ci, corr, why, _ = uncertainty(J, r, np.asarray(u), names, lims, int(r.size))
    values = {n: float(v) for n, v in values_of(u).items()}
    return ModelFit(values, std, ci, corr, why, float(jnp.sum(r * r)),
                    int(sol.stats["num_steps"]), bool(sol.result == optx.RESULTS.successful))
