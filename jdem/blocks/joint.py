"""Joint laws of the block method (000 §2.2, §3.4.1), pure per contact point.

Citations ("000 eq 2-1") refer to the documents listed in REFERENCES.md.

Point contacts as in 000 ch. 2: the normal force follows the total normal
displacement, F_n = k_n u_n (000 eq 2-1, compression positive: the sign
convention of 002), the shear force its increments, dF_s = -k_s du_s
(000 eq 2-2).  Stiffnesses are per contact point [N/m]; for an edge–edge
contact of length L (two points) on a joint of stiffness k [Pa/m] per unit
thickness, k_n = k L / 2 (000 eq 3-36, 3-37 with L_1 = L_2 = L / 2; the
contact law does this per contact where the joint has a face stiffness,
``BlockParams.kn_face``).  000 eq
3-32, 3-33 estimate k_n = E a / (2 b), k_s = k_n / (2 (1 + nu)) from the
blocks' modulus and size.

Strength (000 §2.2 and eq 3-39): a joint point that is *intact* (glued when
the joint was made, :func:`jdem.blocks.cycle.glue_joints`) holds a tensile
force up to ``tension`` and a shear force up to ``cohesion + mu F_n``; when
either is exceeded it breaks for good and keeps only friction, |F_s| <= mu F_n,
and no tension (the "elastic-plastic no-tension" contact of 000 §3.4.1).  A
slipping point's shear force sits on the limit with the sign of the trial
force.

Barton's rough-joint friction (000 eq 3-43, with the log10 of the Barton–Choubey
form): phi = phi_b + JRC log10(JCS / sigma_n); :func:`barton_friction`
returns tan(phi) for a normal stress; the contact law uses it point by point
where the joint's ``jrc`` > 0 (:class:`jdem.blocks.cycle.BlockParams`).
"""
from __future__ import annotations

import jax.numpy as jnp


def coulomb_point(overlap, d_shear, shear_old, intact, kn, ks, mu, cohesion, tension):
    """Mohr–Coulomb point contact with a tension cut-off (000 eq 2-1, 2-2, 3-39).

    overlap    u_n [m], positive in compression (the negative gap)
    d_shear    du_s [m], this step's shear displacement of the far body relative
               to the near one, along the contact tangent
    shear_old  F_s [N] of the last step
    intact     bool: the point still has its cohesion and tensile strength
    kn, ks     [N/m];  mu = tan(phi);  cohesion, tension [N]
    All broadcast together.  Returns ``(F_n, F_s, intact, sliding)`` [N].
    """
    fn = kn * overlap
    breaks_in_tension = intact & (fn < -tension)
    intact = intact & ~breaks_in_tension
    fn = jnp.where(intact, fn, jnp.maximum(fn, 0.0))
    trial = shear_old - ks * d_shear
    friction = mu * jnp.maximum(fn, 0.0)
    limit = jnp.where(intact, cohesion, 0.0) + friction
    sliding = jnp.abs(trial) > limit
    # a shear failure breaks the glue: the point keeps only its friction
    intact = intact & ~sliding
    limit = jnp.where(sliding, friction, limit)
    fs = jnp.where(sliding, jnp.sign(trial) * limit, trial)
    return fn, fs, intact, sliding


def barton_friction(sigma_n, phi_basic, jrc, jcs, *, max_angle=jnp.deg2rad(70.0)):
    """tan(phi) of a rough joint (000 eq 3-43, Barton): phi = phi_b + JRC log10(JCS /
    sigma_n), capped at ``max_angle`` where sigma_n -> 0 (the log diverges).

    sigma_n [Pa] normal stress (> 0), phi_basic [rad], jrc (0..20), jcs [Pa].
    """
    s = jnp.maximum(sigma_n, 1e-12 * jcs)
    phi = phi_basic + jnp.deg2rad(jrc * jnp.log10(jcs / s))
    return jnp.tan(jnp.clip(phi, 0.0, max_angle))
