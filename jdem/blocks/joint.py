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

The continuously yielding joint (000 §3.4.1 item 5, Hart–Cundall):
:func:`yielding_point` lowers the shear stiffness as the shear force nears a
strength whose friction angle falls with the plastic shear displacement
(:func:`yielding_friction`), with dilation, peak and residual strength and
hysteresis on reversal; the contact law uses it where the joint's
``cy_friction0`` > 0.

Barton's rough-joint friction (000 eq 3-43, with the log10 of the Barton–Choubey
form): phi = phi_b + JRC log10(JCS / sigma_n); :func:`barton_friction`
returns tan(phi) for a normal stress; the contact law uses it point by point
where the joint's ``jrc`` > 0 (:class:`jdem.blocks.cycle.BlockParams`).
"""
from __future__ import annotations

import jax
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


def yielding_friction(plastic, mu, mu_initial, roughness):
    """tan(phi_e) of the continuously yielding joint (000 §3.4.1 item 5, Hart–Cundall):
    phi_e = phi + R / (u_p + R / (phi_0 - phi)), falling from phi_0 at u_p = 0
    towards phi as the plastic shear displacement u_p [m] grows.

    The book writes pi/2 for phi_0: the strength at u_p = 0 is then infinite, the
    stiffness factor F below is 1 and u_p never grows, so the joint stays elastic
    for good.  Here phi_0 = atan(``mu_initial``) is a parameter (finite, so below
    pi/2), as in the code the model comes from.  ``roughness`` R [m] = 0 gives
    phi_e = phi (no decay).
    """
    phi, phi0 = jnp.arctan(mu), jnp.arctan(mu_initial)
    gap = jnp.maximum(phi0 - phi, 0.0)
    rough = roughness > 0
    # phi + R / (u_p + R / gap) written as phi + gap R / (gap u_p + R): no 0 / 0 at R = 0
    denom = jnp.where(rough, gap * plastic + roughness, 1.0)
    phi_e = phi + jnp.where(rough, gap * roughness / denom, 0.0)
    return jnp.tan(phi_e)


def yielding_point(fn, d_shear, shear_old, plastic_old, ratio_old, sign_old, ks, mu,
                   mu_initial, roughness):
    """One step of the continuously yielding joint (000 §3.4.1 item 5) at a point.

    The book's stresses become point forces (area 1): sigma_n = F_n and the shear
    "stress" along the slip, s = -F_s (``F_s`` is the force on the far body,
    opposing its displacement ``d_shear``, as in :func:`coulomb_point`).

    fn          F_n [N] this step, compression positive (the dilation included)
    d_shear     du_s [m] this step
    shear_old   F_s [N] of the last step
    plastic_old u_s^(p) [m], the accumulated plastic shear displacement
    ratio_old   gamma, the stress ratio s / s_max at the last reversal (0 at start)
    sign_old    sign of the last nonzero du_s (0 before the first)
    ks          initial shear stiffness k_s^(0) [N/m];  mu = tan(phi);
    mu_initial  tan(phi_0);  roughness R [m]  (:func:`yielding_friction`)

    Per the book: s_max = sigma_n tan(phi_e) sign(du_s); on a reversal of du_s
    gamma := s / s_max; F = (s_max - s) / (s_max (1 - gamma)) (at most 1);
    s += F k_s du_s; u_p += |du_s| (1 - F) (plus any force the guard below
    takes off, over k_s); the dilation angle
    i = max(0, atan(|s| / sigma_n) - phi) adds |du_s| tan(i) to the normal
    displacement (the book's sigma_n += k_n |du_s| tan i).  |s| never exceeds
    |s_max|.  No cohesion, no tension: a point without compression carries nothing.

    Returns ``(F_s, plastic, ratio, sign, d_dilation, yielding)``, ``yielding``
    where the point is at or past its strength (F <= 0).
    """
    step_sign = jnp.sign(d_shear)
    sign = jnp.where(step_sign != 0, step_sign, sign_old)
    loaded = fn > 0
    s_old = -shear_old
    s_max = jnp.maximum(fn, 0.0) * yielding_friction(plastic_old, mu, mu_initial, roughness)
    s_max_signed = s_max * jnp.where(sign != 0, sign, 1.0)
    safe = jnp.where(s_max > 0, s_max_signed, 1.0)
    reversed_ = (sign_old != 0) & (sign != sign_old)
    ratio = jnp.where(reversed_, s_old / safe, ratio_old)
    ratio = jnp.minimum(ratio, 1.0 - 1e-6)
    # F < 0 where the strength has fallen below the force (u_p grew, F_n fell):
    # the force then comes down, and u_p grows by more than |du| (the book's
    # max(0, 1 - F)); so du_p + ds / k_s = du holds in monotonic slip
    factor = jnp.minimum((1.0 - s_old / safe) / (1.0 - ratio), 1.0)
    trial = s_old + factor * ks * d_shear
    s = jnp.clip(trial, -s_max, s_max)            # a guard for steps too coarse for F
    over = jnp.abs(trial - s) / jnp.where(ks > 0, ks, 1.0)
    plastic = plastic_old + jnp.abs(d_shear) * (1.0 - factor) + over
    yielding = (factor <= 0.0) | (over > 0)
    # safe denominators where unloaded: jnp.where would pass on a NaN gradient
    dilation = jnp.maximum(0.0, jnp.arctan2(jnp.abs(s), jnp.where(loaded, fn, 1.0))
                           - jnp.arctan(mu))
    d_dilation = jnp.where(loaded, jnp.abs(d_shear) * jnp.tan(dilation), 0.0)
    fs = jnp.where(loaded, -s, 0.0)
    return (fs, jnp.where(loaded, plastic, plastic_old), jnp.where(loaded, ratio, ratio_old),
            sign, d_dilation, yielding & loaded)


def yielding_shear_path(u, fn, ks, mu, mu_initial, roughness, *, kn=0.0):
    """A direct shear test of one continuously yielding point: the law driven along
    the prescribed shear displacements ``u`` (N,) [m] (u[0] the start).

    fn  the normal force [N] at the start; ``kn`` [N/m] > 0 adds kn times the
        dilation to it (a box whose lid cannot rise: constant normal stiffness),
        0 keeps it constant (constant normal stress, 000 fig 3-16 to 3-18)
    Other arguments as :func:`yielding_point`.  Returns a dict of (N - 1,) arrays
    after each increment: ``shear`` s = -F_s [N], ``plastic`` u_p [m], ``ratio``,
    ``dilation`` [m], ``normal`` F_n [N] the increment used.
    """
    u = jnp.asarray(u)
    zero = jnp.zeros((), u.dtype)

    def one(carry, du):
        fs, plastic, ratio, sign, dil = carry
        f = fn + kn * dil
        fs, plastic, ratio, sign, d_dil, _ = yielding_point(
            f, du, fs, plastic, ratio, sign, ks, mu, mu_initial, roughness)
        dil = dil + d_dil
        return (fs, plastic, ratio, sign, dil), dict(shear=-fs, plastic=plastic, ratio=ratio,
                                                     dilation=dil, normal=f)

    _, out = jax.lax.scan(one, (zero,) * 5, jnp.diff(u))
    return out
