"""The single linked-bar bond test of 002 §1.3: uniaxial tension and direct
shear of two bonded spheres / discs, run through the real engine
(:func:`jdem.run`), with the seed's theoretical curve
(:func:`analytic_single_bond_curve`) and a summary of a simulated curve
(:func:`single_bond_summary`).  Damping: the seed's local damping (000 eq
3-19, alpha = 0.8 from :func:`jdem.materials.seed_params`); the shear test
needs it to keep the free normal degree of freedom quasi-static.
Citations ("002 §1.3") refer to the documents listed in REFERENCES.md.

Specimen (002 §1.3, Fig. 4): two particles of radius ``radius`` stacked along
``y`` and touching, bonded by one linked bar (``bond.create_bonds``).  Particle 0
(the lower one) is fixed (all velocity components prescribed at zero); the
rotations of both are fixed.  Particle 1 (the upper one) is loaded:

* ``"tension"``: every velocity component of the upper particle is prescribed,
  ``v_y = strain_rate_per_step * L / dt`` (``L = R1 + R2``), so the bond opens by
  exactly ``strain_rate_per_step * L`` per step.
* ``"shear"``: the upper particle's ``x`` velocity is prescribed (and ``z`` held
  at zero in 3D); its ``y`` degree of freedom is free and carries the external
  compressive force ``normal_stress * A_c``.  Local non-viscous damping
  (``params.local_damping``, default 0.8) keeps that degree of freedom
  quasi-static.  A pre-load phase (``preload_steps`` with ``v_x = 0``) lets the
  normal load settle; then ``v_x = strain_rate_per_step * L / dt``.  The bond
  turns by the small angle theta ~ u_x / L while it is sheared, so the bond's
  own normal force is F_n = (sigma A_c - |F_s| sin theta) / cos theta, about
  0.2 % below sigma A_c at the break with the seed values; the history records
  the engine's F_n (``normal_stress``).
"""
from __future__ import annotations

import functools
import math
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import bond as bond_mod
from jdem import precision as precision_mod, timestep
from jdem.batch import broadcast_batch, is_batched
from jdem.kinematics import safe_norm
from jdem.materials import per_material_bonds, seed_params
from jdem.simulate import make_state, run
from jdem.state import Params, make_particles
from jdem.validate import InputError

MODES = ("tension", "shear")

#: Steps per jitted chunk of :func:`jdem.run`.  Every phase of every single-bond
#: run is a whole number of chunks, so all runs of one dimension (both modes,
#: any strain range) reuse one compiled chunk.
CHUNK_STEPS = 1000

# ----------------------------------------------------------------------------- analytic
def _np(x):
    return np.asarray(x, dtype=np.float64)


def _per_member(value, like):
    """A params leaf as NumPy, with trailing axes added so that a batch axis
    (leading, shape (B,)) broadcasts against ``like`` of shape (B, ...)."""
    v = _np(value)
    like = np.asarray(like)
    if v.ndim == 1 and like.ndim >= 1 and like.shape[0] == v.shape[0]:
        v = v.reshape(v.shape + (1,) * (like.ndim - 1))
    return v


def analytic_single_bond_curve(mode, strain, params, normal_stress=3e6):
    """The seed's theoretical stress-strain curve of one linked bar (002 Fig. 5, 6).

    ``strain`` is the tensile strain eps = u_n / L (``"tension"``) or the shear
    strain gamma = |u_s| / L (``"shear"``; its sign is ignored); ``params`` may
    carry a leading batch axis (then ``strain`` has shape (B, ...)).
    ``normal_stress`` sigma_n [Pa] (compression positive; shear only) may be an
    array broadcasting against ``strain``.  Returns the stress [Pa]: the tensile
    stress -F_n / A_c, or the shear stress |F_s| / A_c.

    Derivation of the softening branches (002 eq 6-9).  Once the strength is
    reached the force sits on the current strength, and the plastic strain is the
    total strain less the elastic strain at that current strength:

    * tension (eq 6-7): eps_p = eps - T / E and T = T0 (1 - eps_p / eps_lim).
      Eliminating eps_p,

          T(eps) = T0 (eps_lim - eps) / (eps_lim - T0 / E),

      a straight line from the peak (T0 / E, T0) to zero at eps = eps_lim (the
      bond breaks there; the stress is 0 afterwards).  Before the peak sigma = E eps.
    * shear (eq 8-9): gamma_p = gamma - (c + sigma_n tan phi) / G and
      c = c0 (1 - gamma_p / gamma_lim).  Eliminating gamma_p,

          c(gamma) = c0 (gamma_lim + sigma_n tan phi / G - gamma) / (gamma_lim - c0 / G),

      and tau = c + sigma_n tan phi: a straight line from the peak
      (tau_p / G, tau_p = c0 + sigma_n tan phi) to the residual sigma_n tan phi,
      reached when gamma_p = gamma_lim, i.e. at gamma = gamma_lim + sigma_n tan phi / G.
      Before the peak tau = G gamma; afterwards tau = sigma_n tan phi (friction).

    G = E / (2 (1 + nu)).  Both lines need eps_lim > T0 / E and
    gamma_lim > c0 / G (otherwise the softening would snap back).
    """
    if mode not in MODES:
        raise InputError(f"mode must be one of {MODES}, got {mode!r}")
    strain = _np(strain)
    p = lambda v: _per_member(v, strain)
    e_mod = p(params.bond_youngs)
    if mode == "tension":
        t0, eps_lim = p(params.bond_tensile), p(params.bond_tensile_strain)
        eps = strain
        eps_pk = t0 / e_mod
        soft = t0 * (eps_lim - eps) / np.where(eps_lim - eps_pk > 0, eps_lim - eps_pk, np.nan)
        return np.where(eps <= eps_pk, e_mod * eps, np.where(eps < eps_lim, soft, 0.0))
    g_mod = e_mod / (2.0 * (1.0 + p(params.bond_poisson)))
    c0, gam_lim = p(params.bond_cohesion), p(params.bond_shear_strain)
    resid = _np(normal_stress) * np.tan(p(params.bond_friction_angle))
    gam = np.abs(strain)
    peak = c0 + resid
    gam_pk = peak / g_mod
    gam_end = gam_lim + resid / g_mod
    c = c0 * (gam_end - gam) / np.where(gam_lim - c0 / g_mod > 0, gam_lim - c0 / g_mod, np.nan)
    return np.where(gam <= gam_pk, g_mod * gam, np.where(gam < gam_end, c + resid, resid))


# ----------------------------------------------------------------------------- observe
def single_bond_observe(state, params, config):
    """What the single-bond runs record (module-level, so compiled chunks are
    reused): the quantities of bond row 0 for both modes.  ``tension_strain`` =
    u_n / L, ``tension_stress`` = -F_n / A_c, ``shear_strain`` = |u_s| / L signed
    along the drive (+x: ``u_s``, the displacement of the lower particle relative to
    the upper one, points to -x), ``shear_stress`` = |F_s| / A_c,
    ``normal_stress`` = F_n / A_c (compression positive)."""
    b = state.bonds
    geo = bond_mod.bond_geometry(b, state.particles, params, config.dim, config.bond_section)
    area, length = geo.area[0], geo.length[0]
    dmg = bond_mod.damage(b)
    u_s = b.u_s[0]
    gam = safe_norm(u_s) / length
    return dict(
        step=state.step,
        tension_strain=b.u_n[0] / length,
        tension_stress=-b.normal_force[0] / area,
        shear_strain=jnp.where(u_s[0] <= 0, gam, -gam),
        shear_stress=safe_norm(b.shear_force[0]) / area,
        normal_stress=b.normal_force[0] / area,
        alpha=dmg["alpha"][0], beta=dmg["beta"][0], chi=dmg["chi"][0],
        broken=b.broken[0], break_mode=b.break_mode[0], break_step=b.break_step[0],
        moment_lost=b.moment_lost[0],
        upper_pos=state.particles.pos[1],
    )


def derive_history(raw: dict, mode: str, params) -> dict:
    """Turn the raw records of :func:`single_bond_observe` (NumPy or JAX arrays,
    optionally with a leading batch axis) into the history of one mode:
    ``strain``, ``stress`` (see :func:`single_bond_test`), ``plastic_strain``
    (tension: eps - T / E with T = T0 (1 - alpha); shear: eq 9 with the current
    cohesion, gamma - (c + sigma_n tan phi) / G with c = c0 (1 - beta)) and the
    rest as recorded."""
    raw = {k: np.asarray(v) for k, v in raw.items()}
    h = {}
    h["step"] = raw["step"]
    h["strain"] = raw[f"{mode}_strain"]
    h["stress"] = raw[f"{mode}_stress"]
    h["normal_stress"] = raw["normal_stress"]
    h["shear_stress"] = raw["shear_stress"]
    for k in ("alpha", "beta", "chi", "broken", "break_mode", "break_step", "moment_lost",
              "upper_pos"):
        h[k] = raw[k]
    p = lambda v: _per_member(v, h["strain"])
    e_mod = p(params.bond_youngs)
    if mode == "tension":
        t = p(params.bond_tensile) * (1.0 - h["alpha"])
        h["plastic_strain"] = h["strain"] - t / e_mod
    else:
        g_mod = e_mod / (2.0 * (1.0 + p(params.bond_poisson)))
        c = p(params.bond_cohesion) * (1.0 - h["beta"])
        tanphi = np.tan(p(params.bond_friction_angle))
        h["plastic_strain"] = np.abs(h["strain"]) - (c + h["normal_stress"] * tanphi) / g_mod
    return h


# ----------------------------------------------------------------------------- set-up
class SingleBondSetup(NamedTuple):
    """Everything a single-bond run needs; ``state`` is the initial state (for
    ``"shear"`` the pre-load state, upper particle at rest in x).

    velocity      prescribed loading speed [m/s] of the upper particle (y in
                  tension, x in shear) = strain_rate_per_step * L / dt
    n_preload     steps of the pre-load phase (0 in tension)
    n_load        steps of the loading phase
    record_every  steps between records
    batched       params (and state) carry a leading batch axis
    """

    mode: str
    state: object
    params: Params
    config: object
    velocity: float
    n_preload: int
    n_load: int
    record_every: int
    batched: bool


def _round_up(n, m):
    return int(math.ceil(n / m)) * m


def single_bond_setup(mode, *, dim=3, params=None, radius=0.5, density=2500.0,
                      normal_stress=3e6, strain_rate_per_step=2e-7, max_strain=None,
                      record_every=5, preload_steps=1000, dt=None, dt_factor=None,
                      chunk_steps=CHUNK_STEPS, precision=precision_mod.DEFAULT) -> SingleBondSetup:
    """Build the specimen, the loads and the schedule of :func:`single_bond_test`
    without running it (e.g. to call the pure :func:`jdem.rollout` under
    ``jax.grad``).  Arguments as in :func:`single_bond_test`."""
    if mode not in MODES:
        raise InputError(f"mode must be one of {MODES}, got {mode!r}")
    if dim not in (2, 3):
        raise InputError(f"dim must be 2 or 3, got {dim!r}")
    if not (strain_rate_per_step > 0 and np.isfinite(strain_rate_per_step)):
        raise InputError(f"strain_rate_per_step must be > 0, got {strain_rate_per_step!r}")
    if record_every < 1 or chunk_steps % record_every:
        raise InputError(f"record_every = {record_every} must divide chunk_steps = {chunk_steps}")
    params = seed_params(dim) if params is None else params
    # strong dtypes: a weakly typed leaf (jnp.asarray(python float)) would give
    # jdem.run's cached chunk a new signature and recompile it
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=jnp.asarray(a).dtype), params)
    batched = is_batched(params)
    n_batch = int(np.shape(params.dt)[0]) if batched else None
    if per_material_bonds(params):
        raise InputError("single_bond_test bonds two particles of material 0 and takes one "
                         "value per bond field; params has them per material (shape "
                         f"{np.shape(params.bond_youngs)}): pass the rock's values")
    if mode == "shear" and np.any(_np(params.local_damping) <= 0):
        warnings.warn("single_bond_test('shear') with params.local_damping = 0: the free "
                      "normal degree of freedom will oscillate", stacklevel=3)

    pos = np.zeros((2, dim))
    pos[1, 1] = 2.0 * radius
    fixed_vel = np.ones((2, dim), bool)
    if mode == "shear":
        fixed_vel[1, 1] = False
    rs = (2,) if dim == 2 else (2, 3)
    parts = make_particles(pos, [radius, radius], density=density, fixed_vel=fixed_vel,
                           fixed_rot=np.ones(rs, bool))
    # The two spheres touch (gap 0); a tolerance of 1e-6 R bonds them and nothing else.
    bonds = bond_mod.create_bonds(parts, dim, gap_tolerance=1e-6 * radius)
    if int(np.sum(np.asarray(bonds.valid))) != 1:
        raise RuntimeError("single_bond_setup: expected exactly one bond")
    state, config = make_state(parts, bonds=bonds)

    # Time step: a fraction of the critical step of the specimen with the upper
    # particle free in every direction (tension prescribes everything, for which
    # the engine's estimate is infinite); the run checks it again.
    members = [jax.tree_util.tree_map(lambda a, b=b: a[b], params) for b in range(n_batch)] \
        if batched else [params]
    if dt is None:
        probe_fixed = np.zeros((2, dim), bool)
        probe_fixed[0] = True
        probe = state._replace(particles=parts._replace(fixed_vel=jnp.asarray(probe_fixed)))
        crit = min(float(timestep.critical_timestep(probe, m, config)) for m in members)
        dt = timestep.recommended(crit) if dt_factor is None else dt_factor * crit
    dt = float(dt)
    params = params._replace(dt=jnp.full(np.shape(params.dt), dt, jnp.asarray(params.dt).dtype))

    # geometry of the (one) bond, identical for every batch member
    geo = bond_mod.bond_geometry(bonds, parts, members[0], dim)
    area, length = float(geo.area[0]), float(geo.length[0])
    velocity = strain_rate_per_step * length / dt

    if max_strain is None:
        if mode == "tension":
            max_strain = 1.15 * float(np.max(_np(params.bond_tensile_strain)))
        else:
            e = _np(params.bond_youngs)
            g = e / (2.0 * (1.0 + _np(params.bond_poisson)))
            end = _np(params.bond_shear_strain) + normal_stress * np.tan(
                _np(params.bond_friction_angle)) / g
            max_strain = 1.2 * float(np.max(end))
    n_load = _round_up(max_strain / strain_rate_per_step, chunk_steps)
    n_preload = _round_up(preload_steps, chunk_steps) if mode == "shear" else 0

    p = state.particles
    if mode == "tension":
        p = p._replace(vel=p.vel.at[1, 1].set(velocity))
    else:
        p = p._replace(ext_force=p.ext_force.at[1, 1].set(-normal_stress * area))
    state = state._replace(particles=p)
    if batched:
        state = broadcast_batch(state, n_batch)
    dtype = precision_mod.dtype_of(precision)
    state, params = precision_mod.cast(state, dtype), precision_mod.cast(params, dtype)
    return SingleBondSetup(mode=mode, state=state, params=params, config=config,
                           velocity=velocity, n_preload=n_preload, n_load=n_load,
                           record_every=record_every, batched=batched)


def single_bond_test(mode, *, dim=3, params=None, radius=0.5, density=2500.0,
                     normal_stress=3e6, strain_rate_per_step=2e-7, max_strain=None,
                     record_every=5, progress=False, preload_steps=1000, dt=None,
                     dt_factor=None, chunk_steps=CHUNK_STEPS, precision=precision_mod.DEFAULT):
    """Single linked-bar bond in uniaxial tension or direct shear (002 §1.3),
    through :func:`jdem.run`.  Returns ``(history, state, config)``.

    mode                 ``"tension"`` or ``"shear"`` (see the module docstring)
    dim                  2 (discs, unit thickness) or 3 (spheres)
    params               ``Params`` (default: :func:`seed_params`); a leading batch
                         axis on every leaf runs the members as one vmapped call
                         (``jdem.run(..., batched=True)``); ``params.dt`` is
                         replaced by the chosen step (see ``dt``)
    radius, density      of both particles [m], [kg/m^3]
    normal_stress        compressive stress [Pa] on the upper particle (shear)
    strain_rate_per_step strain increment per step of the loading phase
    max_strain           strain to load to (default: 1.15 eps_lim in tension,
                         1.2 (gamma_lim + sigma_n tan phi / G) in shear; the
                         largest over a batch); rounded up to whole chunks
    record_every         steps between records (must divide ``chunk_steps``)
    preload_steps        shear: steps of the pre-load phase (rounded up to chunks)
    dt                   time step [s]; default ``timestep.recommended`` (pi / 10)
                         times the critical step with the upper particle free,
                         or ``dt_factor`` times that step
    precision            working precision, "float32" (default) or "float64"
                         (:mod:`jdem.precision`); the set-up is built in float64
                         when JAX runs with x64, then cast

    ``history`` (dict of NumPy arrays, one entry per record of the loading
    phase; a leading batch axis for batched params):

    step            step number (the shear pre-load steps included)
    strain          tension: u_n / L; shear: |u_s| / L, signed along the drive (+x)
    stress          tension: -F_n / A_c; shear: |F_s| / A_c  [Pa]
    normal_stress   F_n / A_c (compression positive) [Pa]
    shear_stress    |F_s| / A_c [Pa]
    plastic_strain  eps_p (tension) or gamma_p (shear), see :func:`derive_history`
    alpha, beta, chi  damage factors (002 eq 10)
    broken, break_mode, break_step, moment_lost   bond flags (``jdem.state.Bonds``)
    upper_pos       centre of the upper particle [m]
    """
    su = single_bond_setup(mode, dim=dim, params=params, radius=radius, density=density,
                           normal_stress=normal_stress, strain_rate_per_step=strain_rate_per_step,
                           max_strain=max_strain, record_every=record_every,
                           preload_steps=preload_steps, dt=dt, dt_factor=dt_factor,
                           chunk_steps=chunk_steps, precision=precision)
    kw = dict(record_every=su.record_every, observe=single_bond_observe,
              chunk_steps=chunk_steps, progress=progress, batched=su.batched)
    state, config = su.state, su.config
    if su.n_preload:
        res = run(state, su.params, config, su.n_preload, desc=f"{mode} pre-load", **kw)
        state, config = res.state, res.config
        p = state.particles
        vel = p.vel.at[..., 1, 0].set(su.velocity)
        state = state._replace(particles=p._replace(vel=vel))
    res = run(state, su.params, config, su.n_load, desc=mode, **kw)
    return derive_history(res.history, mode, su.params), res.state, res.config


# ----------------------------------------------------------------------------- summary
def single_bond_summary(history: dict, mode: str, params, normal_stress=3e6) -> dict:
    """Key figures of one (unbatched) single-bond history and the seed's values.

    peak_stress, strain_at_peak   the largest recorded stress and its strain
    break_step, break_mode        from the bond
    strain_at_break               strain at the end of the breaking step (the
                                  strength reached zero), interpolated between
                                  records (exact: the strain is linear in steps)
    plastic_strain_at_break       likewise for ``plastic_strain``
    residual_stress               mean stress over the records after the break
    expected_*                    the seed's values: peak T0 (tension) or
                                  c0 + sigma_n tan phi (shear); strain at break
                                  eps_lim (tension) / plastic strain gamma_lim
                                  (shear); residual 0 / sigma_n tan phi
    """
    h = {k: np.asarray(v) for k, v in history.items()}
    stress, strain, steps = h["stress"], h["strain"], h["step"].astype(np.float64)
    k = int(np.argmax(stress))
    out = dict(peak_stress=float(stress[k]), strain_at_peak=float(strain[k]))
    broken = h["broken"].astype(bool)
    if broken.any():
        bs = int(h["break_step"][-1])
        out["break_step"] = bs
        out["break_mode"] = int(h["break_mode"][-1])
        at = bs + 1.0       # state.step after the breaking step
        out["strain_at_break"] = float(np.interp(at, steps, strain))
        out["plastic_strain_at_break"] = float(np.interp(at, steps, h["plastic_strain"]))
        after = broken & (steps > at)
        out["residual_stress"] = float(np.mean(stress[after])) if after.any() else float("nan")
    else:
        out.update(break_step=-1, break_mode=0, strain_at_break=float("nan"),
                   plastic_strain_at_break=float("nan"), residual_stress=float("nan"))
    if mode == "tension":
        exp = dict(expected_peak_stress=float(params.bond_tensile),
                   expected_strain_at_break=float(params.bond_tensile_strain),
                   expected_residual_stress=0.0)
        out["rel_err_strain_at_break"] = (out["strain_at_break"] / exp["expected_strain_at_break"]
                                          - 1.0)
    else:
        resid = normal_stress * float(np.tan(params.bond_friction_angle))
        exp = dict(expected_peak_stress=float(params.bond_cohesion) + resid,
                   expected_plastic_strain_at_break=float(params.bond_shear_strain),
                   expected_residual_stress=resid)
        out["rel_err_plastic_strain_at_break"] = (
            out["plastic_strain_at_break"] / exp["expected_plastic_strain_at_break"] - 1.0)
        out["rel_err_residual_stress"] = out["residual_stress"] / resid - 1.0
    out.update(exp)
    out["rel_err_peak_stress"] = out["peak_stress"] / exp["expected_peak_stress"] - 1.0
    return out
