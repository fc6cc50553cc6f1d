"""Damping for dynamic relaxation (000 §3.2).

Citations ("000 eq 3-19") refer to the documents listed in REFERENCES.md.

* Local non-viscous damping (000 eq 3-19, Cundall's local adaptive damping): each
  degree of freedom's unbalanced force F is reduced by alpha |F| sign(v), i.e.
  opposite to the current velocity, so the damping force vanishes at rest and
  does not act as a body force on steady motion.  0 <= alpha < 1.
* Mass-proportional viscous damping (the alpha [M] part of Rayleigh damping,
  000 eq 3-9): F -= c m v with c [1/s] = ``Params.viscous_damping``.

Both act per particle on the unbalanced force and torque, before the velocity
update.  Contact dashpots (the stiffness-proportional part) live in
:mod:`jdem.contact`.
"""
from __future__ import annotations

import jax.numpy as jnp


def local_damping(force, velocity, alpha):
    """000 eq 3-19: F - alpha |F| sign(v), per component.  Shapes (N, ...)."""
    return force - alpha * jnp.abs(force) * jnp.sign(velocity)


def viscous_damping(force, velocity, mass, coeff):
    """Mass-proportional viscous damping F - c m v; ``mass`` broadcasts as (N,)."""
    m = mass.reshape(mass.shape + (1,) * (velocity.ndim - 1))
    return force - coeff * m * velocity


def apply(force, torque, particles, params):
    """Damped force and torque of every particle."""
    p = particles
    force = viscous_damping(force, p.vel, p.mass, params.viscous_damping)
    torque = viscous_damping(torque, p.angvel, p.inertia, params.viscous_damping)
    force = local_damping(force, p.vel, params.local_damping)
    torque = local_damping(torque, p.angvel, params.local_damping)
    return force, torque
