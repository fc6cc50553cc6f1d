"""Input histories for wave problems: pulses, incident waves, driven discs and
point loads (001 eq 6, 12, 19).

Citations ("001 eq 12") refer to the documents listed in REFERENCES.md.

A :class:`History` is a tabulated time history, linearly interpolated by
:func:`at` inside a step (jit / vmap / grad friendly).  :func:`cosine_pulse`
(001 eq 12) and :func:`lamb_pulse` (001 eq 19) give the shapes as NumPy
arrays; :func:`incident_wave` turns them into the incident field of an input
boundary, :func:`make_driven` into a prescribed velocity on some discs (the
"fixed boundary with velocity input" of 001 §2.2) and :func:`make_point_load`
into a force history.  Host-side builders raise
:class:`jdem.validate.InputError` naming the field and the value.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem.validate import InputError, require_finite, require_positive

Array = jnp.ndarray


class History(NamedTuple):
    """A tabulated time history, linearly interpolated (held constant outside).

    time   (K,)    [s], increasing
    value  (K, d)  the quantity (velocity [m/s], displacement [m] or force [N])
    """

    time: Array
    value: Array



def at(history: History, t) -> Array:
    """The history's value (d,) at time ``t`` [s] (jit / grad friendly)."""
    return jax.vmap(lambda col: jnp.interp(t, history.time, col), in_axes=1)(history.value)



def _check_pulse(amplitude, duration, start, samples):
    require_finite("amplitude", amplitude)
    require_positive("duration", duration)
    require_positive("start", start, allow_zero=True)
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 3:
        raise InputError(f"samples must be an integer >= 3, got {samples!r}")



def cosine_pulse(amplitude, duration, *, start=0.0, samples=2001):
    """The harmonic pulse of 001 eq 12 and its integral, as NumPy arrays (K,).

    v(t) = 0.5 M (1 - cos(2 pi (t - t0) / T)) for 0 <= t - t0 <= T, else 0;
    u(t) = 0.5 M ((t - t0) - T / (2 pi) sin(2 pi (t - t0) / T)), 0.5 M T afterwards.
    ``amplitude`` M is the peak velocity [m/s], ``duration`` T [s], ``start`` t0 [s].
    Returns ``(time, velocity, displacement)``.
    """
    _check_pulse(amplitude, duration, start, samples)
    s = np.linspace(0.0, float(duration), int(samples))
    phase = 2.0 * np.pi * s / duration
    vel = 0.5 * amplitude * (1.0 - np.cos(phase))
    disp = 0.5 * amplitude * (s - duration / (2.0 * np.pi) * np.sin(phase))
    return s + float(start), vel, disp



def lamb_pulse(duration, *, start=0.0, samples=2001):
    """The load shape f(t) of 001 eq 19 (K,), peak 1 at t0 + T0 / 2:

    f(t) = 16 [G(t/T0) - 4 G(t/T0 - 1/4) + 6 G(t/T0 - 1/2) - 4 G(t/T0 - 3/4) + G(t/T0 - 1)],
    G(x) = x^3 H(x).  Returns ``(time, f)``; f = 0 outside [t0, t0 + T0].
    """
    _check_pulse(1.0, duration, start, samples)
    s = np.linspace(0.0, float(duration), int(samples))
    x = s / duration
    g = lambda y: np.where(y > 0, y, 0.0) ** 3
    f = 16.0 * (g(x) - 4 * g(x - 0.25) + 6 * g(x - 0.5) - 4 * g(x - 0.75) + g(x - 1.0))
    return s + float(start), f



def _history(time, scalar, direction, dtype) -> History:
    direction = np.asarray(direction, np.float64)
    return History(time=jnp.asarray(time, dtype),
                   value=jnp.asarray(np.outer(scalar, direction), dtype))



def zero_history(dim, dtype) -> History:
    """A history that is zero at all times (d = ``dim``): the incident field of a
    boundary that is not an input boundary."""
    return History(time=jnp.asarray([0.0, 1.0], dtype), value=jnp.zeros((2, dim), dtype))



class Incident(NamedTuple):
    """Incident wave at an input boundary (001 eq 6, 18), global frame.

    vel   History (K, d) incident particle velocity v_i [m/s]
    disp  History (K, d) incident displacement u_i [m] (viscoelastic input only)
    """

    vel: History
    disp: History



class Driven(NamedTuple):
    """Prescribed velocity history on K discs (the "fixed boundary with velocity
    input" of 001 §2.2).  The driven components must be ``fixed_vel`` in the state
    (:func:`fix_driven`).

    index  (K,)  int32 particle rows
    vel    History (T, d) velocity [m/s], evaluated at mid-step t + dt/2
    mask   (d,)  bool: which components are driven
    """

    index: Array
    vel: History
    mask: Array



class PointLoad(NamedTuple):
    """A force history applied to each of K discs (the Lamb load of 001 eq 19).

    index  (K,)  int32 particle rows
    force  History (T, d) force [N] on each disc
    """

    index: Array
    force: History



def incident_wave(time, velocity, displacement, direction, dtype=None) -> tuple[History, History]:
    """Incident velocity and displacement histories (K, 2) along the unit vector
    ``direction`` (global frame), e.g. from :func:`cosine_pulse`.  For a P wave
    entering through a boundary the direction is the inward normal; for SV the
    tangent."""
    d = require_finite("direction", direction).reshape(-1)
    if d.shape != (2,) or np.linalg.norm(d) == 0:
        raise InputError(f"direction must be a non-zero 2D vector, got {direction!r}")
    d = d / np.linalg.norm(d)
    dtype = dtype or jnp.zeros(()).dtype
    return _history(time, velocity, d, dtype), _history(time, displacement, d, dtype)



def _indexed_history(index, time, values, direction, *, name, verb, dtype):
    """Checked particle indices (int32) and the history ``values`` (K,) along
    ``direction`` at ``time`` (K,), shared by driven discs and point loads."""
    d = require_finite("direction", direction).reshape(-1)
    require_finite(name, values)
    dtype = dtype or jnp.zeros(()).dtype
    idx = np.asarray(index, np.int64).reshape(-1)
    if idx.size == 0:
        raise InputError(f"index selects no particle to {verb}")
    return jnp.asarray(idx, jnp.int32), _history(time, values, d, dtype)



def make_driven(index, time, velocity, direction, *, mask=None, dtype=None) -> Driven:
    """Prescribed velocity ``velocity`` (K,) [m/s] along ``direction`` at ``time``
    (K,) [s] on the discs ``index``; ``mask`` (2,) bool the driven components
    (default: both)."""
    idx, vel = _indexed_history(index, time, velocity, direction, name="velocity", verb="drive",
                                dtype=dtype)
    m = np.ones(vel.value.shape[-1:], bool) if mask is None else np.asarray(mask, bool)
    return Driven(index=idx, vel=vel, mask=jnp.asarray(m))



def make_point_load(index, time, force, direction, dtype=None) -> PointLoad:
    """Force ``force`` (K,) [N] along ``direction`` at ``time`` (K,) [s] on each
    disc of ``index`` (e.g. ``P0 * lamb_pulse(T0)``, 001 eq 19)."""
    idx, hist = _indexed_history(index, time, force, direction, name="force", verb="load",
                                 dtype=dtype)
    return PointLoad(index=idx, force=hist)



def fix_driven(state, driven: Driven):
    """Mark the driven components of the driven discs as prescribed (``fixed_vel``)."""
    p = state.particles
    fixed = p.fixed_vel.at[driven.index].set(p.fixed_vel[driven.index] | driven.mask[None])
    return state._replace(particles=p._replace(fixed_vel=fixed))
