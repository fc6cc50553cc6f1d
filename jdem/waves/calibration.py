"""Calibration of the absorbing boundary's factor beta (001 §2.2, Fig 5).

Citations ("001 Fig 5") refer to the documents listed in REFERENCES.md.

Two ways: the ratio iteration of 001 (:func:`ratio_iteration`,
:func:`calibrate_ratio`), which rescales beta by the ratio of the output to
the input peak, and gradient descent on the reflected energy through the
differentiable rollout (:func:`reflected_energy`, :func:`calibrate_gradient`).
"""
from __future__ import annotations

import functools
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem.bond import bond_strain_energy
from jdem.measure import kinetic_energy
from jdem.simulate import rollout
from jdem.validate import InputError, require_positive
from jdem.waves.bar import BarModel, motion_direction, peak, run_bar, with_betas
from jdem.waves.boundaries import apply_conditions

Array = jnp.ndarray


class Calibration(NamedTuple):
    """Result of a calibration: ``beta``; ``history`` a list of dicts, one per
    iteration (``beta``, ``m_out``, ``ratio`` for the ratio iteration; ``beta``,
    ``loss``, ``grad`` for gradient descent); ``converged``."""

    beta: float
    history: list
    converged: bool



def ratio_iteration(peak_of: Callable[[float], float], m_input, *, beta0=1.0, tol=1e-3,
                    max_iter=15, mode="absorbing") -> Calibration:
    """The ratio iteration of 001 §2.2, Fig 5.

    ``peak_of(beta)`` runs the short test with calibration factor beta and returns
    the peak velocity M_out at the boundary; ``m_input`` is the input peak M_in.
    Each iteration runs the test; it stops when |M_out / M_in - 1| < ``tol``,
    else beta is multiplied by M_out / M_in (``mode="absorbing"``: an
    under-absorbing boundary moves too fast, so beta grows) or by M_in / M_out
    (``mode="input"``, 001 §2.3.3: an input boundary moves too slowly when beta
    is too small).  At most ``max_iter`` runs.
    """
    if mode not in ("absorbing", "input"):
        raise InputError(f"mode must be 'absorbing' or 'input', got {mode!r}")
    beta = float(require_positive("beta0", beta0))
    require_positive("m_input", m_input)
    require_positive("tol", tol)
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise InputError(f"max_iter must be a positive integer, got {max_iter!r}")
    history = []
    for k in range(1, int(max_iter) + 1):
        m_out = float(peak_of(beta))
        if not (np.isfinite(m_out) and m_out > 0):
            raise RuntimeError(f"ratio_iteration: the test returned M_out = {m_out} at beta = {beta}")
        ratio = m_out / float(m_input)
        history.append(dict(iteration=k, beta=beta, m_out=m_out, ratio=ratio))
        if abs(ratio - 1.0) < tol:
            return Calibration(beta=beta, history=history, converged=True)
        beta = beta * (ratio if mode == "absorbing" else 1.0 / ratio)
    return Calibration(beta=beta, history=history, converged=False)



def arriving_peak(pair, reference_history=None) -> float:
    """Peak velocity [m/s] along the motion at the truncated bar's boundary discs
    (P5) in the extended reference of ``pair`` (:func:`jdem.waves.bar_pair`):
    the amplitude that reaches the boundary when nothing comes back.  On a
    random packing the pulse loses some of its peak to scattering on the way
    (measured, radii 4-6 m over 1000 m: P 0.463, S 0.477 of an input 0.5 m/s),
    so this, not the input amplitude, is the M_in that an absorbing boundary's
    discs should reach.  ``reference_history``: a :func:`run_bar` history of
    ``pair.reference`` if already run."""
    h = run_bar(pair.reference) if reference_history is None else reference_history
    return peak(h, 4, motion_direction(pair.truncated))


def calibrate_ratio(model: BarModel, *, boundary="right", beta0=1.0, tol=1e-3, max_iter=15,
                    beta_other=None, target=None) -> Calibration:
    """Ratio iteration (001 Fig 5) on the bar ``model``, running it each time.

    The factor calibrated is the one of the bar's wave: beta_2P on a P bar,
    beta_2S on an S bar (``bar_model(..., polarisation="S")``), so that the two
    are found apart (001 eq 4: they differ on a random packing); the other keeps
    its value.  ``boundary="right"``: the absorbing boundary; M_out is the peak
    velocity along the motion (x for P, y for S) of the right boundary discs
    (P5), M_in the input pulse amplitude.  ``boundary="left"``: the viscous input
    boundary of a model built with ``input="viscous"``; M_out is the peak velocity
    of the left boundary discs (P1), and beta is scaled by M_in / M_out.
    ``beta_other`` fixes the factor of the other boundary (default: as built).
    ``target`` [m/s] replaces M_in: 001 uses the input amplitude, which on a
    random packing overestimates what arrives (:func:`arriving_peak`), so the
    iteration under-absorbs.  Measured (experiments/results/beta_s): on the bar
    of radii 4-6 m matching the arriving peak cuts the reflection at P3 from
    7.9 % to 2.1 % (P) and from 5.8 % to 2.6 % (S); at radii 2-3 m neither
    target gets below 10 %, while the best beta of a scan reflects 1.7-1.9 %:
    there the peak of the cut face's discs is a poor proxy for absorption.
    """
    if boundary not in ("left", "right"):
        raise InputError(f"boundary must be 'left' or 'right', got {boundary!r}")
    if boundary == "left" and model.input != "viscous":
        raise InputError("calibrating the left (input) boundary needs a model built with "
                         f"input='viscous', got input={model.input!r}")

    wave, along = model.polarisation, motion_direction(model)

    def peak_of(beta):
        if boundary == "right":
            cond = with_betas(model, beta_right=beta, beta_left=beta_other, wave=wave)
            return peak(run_bar(model, cond), 4, along)
        cond = with_betas(model, beta_left=beta, beta_right=beta_other, wave=wave)
        return peak(run_bar(model, cond), 0, along)

    m_input = model.amplitude if target is None else target
    return ratio_iteration(peak_of, m_input, beta0=beta0, tol=tol, max_iter=max_iter,
                           mode="absorbing" if boundary == "right" else "input")



def bar_energy(state, params) -> Array:
    """Kinetic plus bond strain energy of the assembly [J per m thickness]."""
    return kinetic_energy(state) + bond_strain_energy(state.bonds, state.particles, params, 2)



def _energy_observe(state, params, config):
    return dict(energy=bar_energy(state, params))



@functools.lru_cache(maxsize=8)
def _reflected_energy_fn(config, n_records, record_every, i_full):
    """Jitted value-and-grad of the reflected energy fraction w.r.t. log beta."""

    def loss(log_beta, state, params, cond):
        right = cond.boundaries[1]
        beta = jnp.exp(log_beta)
        right = right._replace(beta_p=beta, beta_s=beta)
        cond = cond._replace(boundaries=(cond.boundaries[0], right))
        _, hist = rollout(state, params, config, n_records, record_every, _energy_observe,
                          boundary=(apply_conditions, cond))
        e = hist["energy"]
        return e[-1] / e[i_full]

    return jax.jit(jax.value_and_grad(loss))



def reflected_energy(model: BarModel, beta, *, t_end=None, record_every=50):
    """Reflected energy fraction E(t_end) / E(t_full) of the bar with the right
    factor ``beta`` and its derivative d/d(log beta), through the differentiable
    rollout.  E is the kinetic plus bond energy in the bar; t_full = 1.2 T (the
    pulse is all in), t_end (default (length + c T) / c + 0.5 length / c) when
    the incident pulse has left through the right end and the reflection is on
    its way back.  Returns ``(fraction, d fraction / d log beta)``."""
    dt = float(model.params.dt)
    if t_end is None:
        t_end = 1.5 * model.length / model.c_p + model.duration
    n_records = int(math.ceil(t_end / dt / record_every))
    i_full = int(math.ceil(1.2 * model.duration / dt / record_every))
    fn = _reflected_energy_fn(model.config, n_records, record_every, i_full)
    value, grad = fn(jnp.log(jnp.asarray(beta, model.params.dt.dtype)), model.state,
                     model.params, model.conditions)
    return float(value), float(grad)



def calibrate_gradient(model: BarModel, *, beta0=1.0, steps=15, learning_rate=1.0,
                       t_end=None, record_every=50, tol=1e-3) -> Calibration:
    """Calibrate the right boundary's beta by gradient descent on the reflected
    energy fraction (:func:`reflected_energy`), differentiating through the
    rollout: ``optax.sgd`` on log beta.  Near the optimum the fraction is about
    R^2 with R = (1 - x) / (1 + x) ~ -ln(x) / 2 (x = beta / beta_opt), i.e.
    (ln x)^2 / 4, whose curvature 1/2 makes ``learning_rate`` = 1 halve the
    error each step.  Stops after ``steps`` evaluations or when the step in
    log beta falls below ``tol``.  Returns the beta with the smallest loss seen
    and the history (beta, loss, grad)."""
    import optax

    require_positive("beta0", beta0)
    require_positive("learning_rate", learning_rate)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise InputError(f"steps must be a positive integer, got {steps!r}")
    opt = optax.sgd(learning_rate)
    log_beta = jnp.log(jnp.asarray(beta0, model.params.dt.dtype))
    opt_state = opt.init(log_beta)
    history = []
    converged = False
    for k in range(int(steps)):
        value, grad = reflected_energy(model, float(jnp.exp(log_beta)), t_end=t_end,
                                       record_every=record_every)
        history.append(dict(iteration=k + 1, beta=float(jnp.exp(log_beta)), loss=value, grad=grad))
        updates, opt_state = opt.update(jnp.asarray(grad, log_beta.dtype), opt_state)
        log_beta = optax.apply_updates(log_beta, updates)
        if abs(float(updates)) < tol:
            converged = True
            break
    best = min(history, key=lambda h: h["loss"])
    return Calibration(beta=best["beta"], history=history, converged=converged)
