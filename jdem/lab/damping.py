"""Damping of the lab tests: one quasi-static damping for every way of running.

Citations ("000 eq 3-19") refer to the documents listed in REFERENCES.md.

Two kinds (:class:`Damping`), chosen per set-up and recorded in its plan:

* :func:`smooth` (the default, used by the host loop, the pure curve, sweeps
  and calibration alike): dashpots on the relative motion of bonds and contacts
  (``bond_damping`` = ``contact_damping`` = ``ratio``, a fraction of critical,
  000 eq 3-1 on the bar stiffnesses) for the particle-scale modes, plus a
  *background* mass-proportional damping that acts on the deviation of each
  particle's velocity from the affine motion imposed by the platens (or grips):
  F -= c m (v - v_affine(x)), M -= c I omega, with c = 2 xi omega_1, xi =
  ``low_mode`` and omega_1 = pi c_p / (2 H) the lowest axial mode of a bar of
  height H fixed at one end (c_p = sqrt(E / rho)).  Damping the deviation
  rather than the velocity itself (000 eq 3-9) means steady loading feels no
  body force: plain mass-proportional damping resists the platen's motion with
  a stress ~ rho H c v / 2 that grows with the loading rate (0.4 MPa, 4 % of the
  peak, on the 104-disc demo at 1.25 nm per step).  Every term is smooth, so
  gradients through long runs stay well behaved.
* :func:`local`: the seed's local non-viscous damping (000 eq 3-19,
  F - alpha |F| sign(v)), alpha = 0.8 in 002 §1.3 and §2.1.  What the 002
  reproduction studies use.  Its tangent dynamics multiply every force by
  (1 +- alpha) as the signs of F and v switch, which makes reverse-mode
  gradients grow exponentially with the number of steps (164-disc UCS test:
  d sigma / d E off by 1e5 after 500 steps): do not calibrate with it.

Only the axial component and the spins feel the background damping; the
reference is the *prescribed* motion of the platens or grips (a servo wall's
speed is a control signal, and following it would drag the whole specimen
with the servo).
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jdem.state import Params
from jdem.validate import InputError

KINDS = ("smooth", "local")


class Damping(NamedTuple):
    """kind ``"smooth"`` or ``"local"``; ``ratio``: smooth -- bond and contact
    dashpots as a fraction of critical; local -- alpha of 000 eq 3-19;
    ``low_mode``: smooth only -- fraction of critical of the lowest axial mode
    given to the background damping."""

    kind: str
    ratio: float
    low_mode: float = 0.0

    def __str__(self):
        if self.kind == "local":
            return f"local alpha {self.ratio:g}"
        return f"smooth (dashpots {self.ratio:g}, background {self.low_mode:g})"


def smooth(ratio: float = 0.3, low_mode: float = 0.3) -> Damping:
    """The default quasi-static damping (module docstring)."""
    if not 0.0 <= ratio <= 1.0:
        raise InputError(f"smooth damping ratio must lie in [0, 1], got {ratio!r}")
    if not 0.0 <= low_mode <= 2.0:
        raise InputError(f"smooth damping low_mode must lie in [0, 2], got {low_mode!r}")
    return Damping("smooth", float(ratio), float(low_mode))


def local(alpha: float = 0.8) -> Damping:
    """The seed's local non-viscous damping (000 eq 3-19)."""
    if not 0.0 <= alpha < 1.0:
        raise InputError(f"local damping alpha must lie in [0, 1), got {alpha!r}")
    return Damping("local", float(alpha), 0.0)


def check(damping) -> Damping:
    if not isinstance(damping, Damping) or damping.kind not in KINDS:
        raise InputError(f"damping must be jdem.lab.smooth(...) or jdem.lab.local(...), "
                         f"got {damping!r}")
    return damping


def damped_params(params: Params, damping: Damping) -> Params:
    """``params`` with the particle-level damping of ``damping`` (the background
    term is not in ``Params``: it acts through the test's boundary function)."""
    like = lambda v: jnp.full(np.shape(params.local_damping), v,
                              jnp.asarray(params.local_damping).dtype)
    bond = lambda v: jnp.full(np.shape(params.bond_damping), v,   # () or per material
                              jnp.asarray(params.bond_damping).dtype)
    if damping.kind == "local":
        return params._replace(local_damping=like(damping.ratio), bond_damping=bond(0.0),
                               contact_damping=like(0.0), viscous_damping=like(0.0))
    return params._replace(local_damping=like(0.0), bond_damping=bond(damping.ratio),
                           contact_damping=like(damping.ratio), viscous_damping=like(0.0))


def background_coefficient(damping: Damping, youngs, density, height) -> float:
    """c = 2 xi omega_1 [1/s] of the background damping (0 for local damping)."""
    if damping.kind != "smooth":
        return 0.0
    omega1 = np.pi * np.sqrt(float(youngs) / float(density)) / (2.0 * float(height))
    return 2.0 * damping.low_mode * omega1


def affine_force(particles, coeff, axis, lo_pos, lo_vel, hi_pos, hi_vel, lateral=()):
    """Background damping force and torque (module docstring).

    ``axis``: loading axis; ``lo_*`` / ``hi_*``: positions and velocities [m],
    [m/s] of the two ends along it (platens or grips); ``lateral``: tuples
    ``(axis, lo_pos, lo_vel, hi_pos, hi_vel)`` of lateral walls.  Returns
    (force (N, d), torque (N,) or (N, 3)).
    """
    p = particles
    dim = p.pos.shape[-1]
    m = p.mass[:, None]
    ref = jnp.zeros_like(p.vel)
    damped = jnp.zeros((dim,), bool)

    def field(x, lo, vlo, hi, vhi):
        span = jnp.where(hi - lo != 0, hi - lo, 1.0)
        return vlo + (vhi - vlo) * (x - lo) / span

    ref = ref.at[:, axis].set(field(p.pos[:, axis], lo_pos, lo_vel, hi_pos, hi_vel))
    damped = damped.at[axis].set(True)
    for a, lo, vlo, hi, vhi in lateral:
        ref = ref.at[:, a].set(field(p.pos[:, a], lo, vlo, hi, vhi))
        damped = damped.at[a].set(True)
    force = jnp.where(damped & p.valid[:, None], -coeff * m * (p.vel - ref), 0.0)
    inertia = p.inertia.reshape(p.inertia.shape + (1,) * (p.angvel.ndim - 1))
    valid = p.valid.reshape(p.valid.shape + (1,) * (p.angvel.ndim - 1))
    torque = jnp.where(valid, -coeff * inertia * p.angvel, 0.0)
    return force, torque
