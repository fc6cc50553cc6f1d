"""Laboratory test drivers: set up a specimen, load it, return a history.

* The single linked-bar bond test of 002 §1.3 (uniaxial tension and direct
  shear of two bonded spheres / discs), run through the real engine
  (:func:`jdem.run`), together with the seed's theoretical curve
  (:func:`analytic_single_bond_curve`) and a small summary of a simulated curve
  (:func:`single_bond_summary`) -- described below.
* Rock specimen tests between rigid platens (second half of this module):
  :func:`rock_params` (rock + platen materials), :func:`ucs_test` (uniaxial or,
  with a confining stress, biaxial compression, 002 §2; batched sweeps, e.g.
  over the fracture strain), :func:`peak_summary`, :func:`brazilian_test`
  (and :func:`flatten_disc`), :func:`coordination_energy_ratio` (lambda of
  002 §1.4), :func:`failure_pattern` / :func:`damage_map` for plots, and
  :func:`save_checkpoint` / :func:`load_checkpoint` / :func:`platen_run` for
  restarts.

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
from jdem import timestep
from jdem.kinematics import safe_norm
from jdem.simulate import broadcast_batch, make_state, run
from jdem.state import Params, make_params, make_particles
from jdem.validate import InputError

MODES = ("tension", "shear")

#: Steps per jitted chunk of :func:`jdem.run`.  Every phase of every single-bond
#: run is a whole number of chunks, so all runs of one dimension (both modes,
#: any strain range) reuse one compiled chunk.
CHUNK_STEPS = 1000

#: Seed values of 002 §1.3.
SEED_PARAMS = dict(bond_youngs=10e9, bond_poisson=0.22, bond_tensile=3e6, bond_cohesion=3e6,
                   bond_friction_angle=float(np.deg2rad(30.0)), bond_tensile_strain=1e-3,
                   bond_shear_strain=3e-3)
DEFAULT_LOCAL_DAMPING = 0.8


def seed_params(dim: int = 3, **overrides) -> Params:
    """``Params`` with the 002 §1.3 bond values (E = 10 GPa, nu = 0.22,
    T0 = c0 = 3 MPa, phi = 30 deg, eps_lim = 0.1 %, gamma_lim = 0.3 %) and local
    damping 0.8; ``dt`` is a placeholder that :func:`single_bond_setup` replaces."""
    kw = dict(SEED_PARAMS, local_damping=DEFAULT_LOCAL_DAMPING)
    kw.update(overrides)
    return make_params(dim=dim, **kw)


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
    geo = bond_mod.bond_geometry(b, state.particles, params, config.dim)
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


def _is_batched(params) -> bool:
    return np.ndim(params.dt) == 1


def single_bond_setup(mode, *, dim=3, params=None, radius=0.5, density=2500.0,
                      normal_stress=3e6, strain_rate_per_step=2e-7, max_strain=None,
                      record_every=5, preload_steps=1000, dt=None, dt_factor=None,
                      chunk_steps=CHUNK_STEPS) -> SingleBondSetup:
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
    batched = _is_batched(params)
    n_batch = int(np.shape(params.dt)[0]) if batched else None
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
    return SingleBondSetup(mode=mode, state=state, params=params, config=config,
                           velocity=velocity, n_preload=n_preload, n_load=n_load,
                           record_every=record_every, batched=batched)


def single_bond_test(mode, *, dim=3, params=None, radius=0.5, density=2500.0,
                     normal_stress=3e6, strain_rate_per_step=2e-7, max_strain=None,
                     record_every=5, progress=False, preload_steps=1000, dt=None,
                     dt_factor=None, chunk_steps=CHUNK_STEPS):
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
                           chunk_steps=chunk_steps)
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


# =============================================================================
# Rock specimen tests: uniaxial / biaxial compression, Brazilian splitting,
# strain-energy ratio (002 §1.4, §2)
# =============================================================================
#
# Geometry.  The loading axis is the last axis (y in 2D, z in 3D).  A platen test
# puts rigid planar walls (:func:`jdem.state.make_walls`, material index
# ``PLATEN`` = 1) against the specimen: wall 0 is the bottom platen (fixed),
# wall 1 the top platen (moving towards the specimen by ``platen_step`` metres
# per step), and, for a biaxial test, walls 2, 3 (and 4, 5 in 3D) the lateral
# walls, servo-controlled to the confining stress (000 eq 4-69, see
# :mod:`jdem.walls`).  The platens start exactly at the outermost particle edges
# (no initial overlap).  Unbonded contacts (particle pairs whose bond broke,
# fresh contacts, particle-platen contacts) use the linear model with the
# stiffnesses of :func:`rock_params`.

PLATEN = 1               #: material index of platens and lateral walls
ROCK = 0                 #: material index of the rock particles
UCS_CHUNK_STEPS = 2000   #: default steps per jitted chunk of the platen tests
UCS_RECORD_EVERY = 50    #: default steps between records
N_SLICES = 32            #: horizontal slices of the lateral-extent measurement


def rock_params(dim: int = 2, *, E=30e9, nu=0.22, T0=3e6, c0=3e6, phi_deg=30.0, kappa=1e-3,
                local_damping=0.8, radius=None, friction=None, platen_stiffness=10.0,
                platen_friction=0.0, dt=1e-8, **kw) -> Params:
    """``Params`` of a bonded rock (material 0) and a platen (material 1, 002 §2).

    E, nu         Young's modulus [Pa] and Poisson ratio of the linked bars (002 eq 2)
    T0, c0        initial tensile strength and cohesion [Pa] (002 eq 6, 8)
    phi_deg       internal friction angle [deg] of the bonds (002 eq 8); the
                  unbonded rock contacts get ``friction = tan(phi)`` unless given
    kappa         fracture strain: ``bond_tensile_strain = bond_shear_strain = kappa``
                  (002 §2.1).  A sequence gives a *batched* ``Params`` (leading
                  axis, one member per value) for a vmapped sweep
    local_damping local non-viscous damping (000 eq 3-19), 0.8 in 002 §2.1
    radius        3D only: the particle radius R [m] of the contact stiffness below

    Unbonded contact stiffness, consistent with a bond between equal particles
    (002 eq 1-2): 2D ``kn = E A_c / L = E 2R / 2R = E`` [N/m per m of thickness];
    3D ``kn = E pi R^2 / 2R = E pi R / 2``; ``ks = kn G / E`` with
    ``G = E / (2 (1 + nu))``.  The platen (material 1) is ``platen_stiffness``
    times stiffer (linear model; the pair stiffness is the harmonic mean, 000
    eq 4-9, so a particle-platen contact has about 2 kn) and frictionless by
    default (``platen_friction = 0``: "normal constraint" of the platens, 002
    §2.1; the smaller friction coefficient of a pair is used).  ``dt`` is a
    placeholder: the tests replace it by ``jdem.timestep.recommended``.
    Further keywords go to :func:`jdem.state.make_params`.
    """
    if dim not in (2, 3):
        raise InputError(f"dim must be 2 or 3, got {dim!r}")
    g_over_e = 1.0 / (2.0 * (1.0 + float(nu)))
    if dim == 2:
        kn = float(E)
    else:
        if radius is None:
            raise InputError("rock_params(dim=3) needs radius (the particle radius R of "
                             "kn = E pi R / 2)")
        kn = float(E) * np.pi * float(radius) / 2.0
    mu = float(np.tan(np.deg2rad(phi_deg))) if friction is None else float(friction)
    kappas = np.atleast_1d(np.asarray(kappa, dtype=np.float64))
    base = make_params(dim=dim, n_materials=2, dt=dt, kn=[kn, platen_stiffness * kn],
                       ks=[kn * g_over_e, platen_stiffness * kn * g_over_e],
                       friction=[mu, platen_friction], youngs=[E, platen_stiffness * E],
                       poisson=[nu, nu], local_damping=local_damping, bond_youngs=E,
                       bond_poisson=nu, bond_tensile=T0, bond_cohesion=c0,
                       bond_friction_angle=float(np.deg2rad(phi_deg)),
                       bond_tensile_strain=float(kappas[0]), bond_shear_strain=float(kappas[0]),
                       **kw)
    if np.ndim(kappa) == 0:
        return base
    params = broadcast_batch(base, kappas.size)
    k = jnp.asarray(kappas, dtype=jnp.asarray(base.dt).dtype)
    params = params._replace(bond_tensile_strain=k, bond_shear_strain=k)
    from jdem.validate import check_params
    check_params(params)
    return jax.tree_util.tree_map(lambda a: jnp.array(a), params)  # own the memory


def member(tree, b: int):
    """Member ``b`` of a batched pytree (state, params or history dict)."""
    if isinstance(tree, dict):
        return {k: np.asarray(v)[b] for k, v in tree.items()}
    return jax.tree_util.tree_map(lambda a: a[b], tree)


class PlatenFrame(NamedTuple):
    """Reference geometry and loading of a platen test (plain values: it is
    saved as HDF5 attributes by :func:`save_checkpoint`).

    test             "ucs", "biaxial", "brazilian" or "energy"
    dim              2 or 3; the loading axis is ``dim - 1``
    h0               specimen height between the platens at the start of axial loading [m]
    w0               initial lateral extents [m] (one per lateral axis), measured as in
                     the ``width`` records (slices of the packing; biaxial: the lateral
                     walls' distance)
    area             platen area [m^2] of the axial stress: the particles' lateral extent
                     (2D: width x 1 m; 3D: width x depth; Brazilian: 1, so that the
                     axial stress is the load per metre)
    velocity         top platen speed [m/s] (platen_step / dt); a tuple, one per
                     batch member, when ``platen_step`` was a sequence
    confining_stress lateral servo stress [Pa] (0: free sides)
    diameter         Brazilian disc diameter D [m] (0 otherwise)
    n_lateral        number of lateral (servo) walls after the two platens
    """

    test: str
    dim: int
    h0: float
    w0: tuple
    area: float
    velocity: float
    confining_stress: float
    diameter: float
    n_lateral: int


def _slice_widths(particles, dim):
    """Lateral extent of the packing: the loading axis is cut into ``N_SLICES``
    equal slices between the lowest and highest particle centre; in each slice the
    extent along each lateral axis is max(x + r) - min(x - r) over its particles
    (its outermost particles); the widths are the mean over the non-empty slices.
    Returns (dim - 1,)."""
    p = particles
    valid = p.valid
    ax = dim - 1
    z = p.pos[:, ax]
    zmin = jnp.min(jnp.where(valid, z, jnp.inf))
    zmax = jnp.max(jnp.where(valid, z, -jnp.inf))
    span = jnp.where(zmax > zmin, zmax - zmin, 1.0)
    b = jnp.clip(jnp.floor((z - zmin) / span * N_SLICES), 0, N_SLICES - 1).astype(jnp.int32)
    b = jnp.where(valid, b, N_SLICES)
    out = []
    for a in range(dim - 1):
        lo = jax.ops.segment_min(jnp.where(valid, p.pos[:, a] - p.radius, jnp.inf), b,
                                 num_segments=N_SLICES + 1)[:N_SLICES]
        hi = jax.ops.segment_max(jnp.where(valid, p.pos[:, a] + p.radius, -jnp.inf), b,
                                 num_segments=N_SLICES + 1)[:N_SLICES]
        ok = jnp.isfinite(lo) & jnp.isfinite(hi)
        out.append(jnp.sum(jnp.where(ok, hi - lo, 0.0)) / jnp.maximum(jnp.sum(ok), 1))
    return jnp.stack(out)


def platen_observe(state, params, config):
    """What the platen tests record (module-level, so compiled chunks are reused).

    ``step``; per wall (W,): ``wall_pos`` (coordinate along its normal axis),
    ``wall_stress_force`` (compressive normal force [N]) and ``wall_area``;
    ``width`` (:func:`_slice_widths`); ``stress_sum``, the averaged-stress sum of
    :func:`jdem.measure.averaged_stress` with volume 1 (compression positive; the
    host divides by the current volume); bond counts (:func:`jdem.bond.bond_stats`),
    bond, contact and kinetic energies.  :func:`derive_platen_history` turns
    these into the history.
    """
    from jdem import measure

    w = state.walls
    stats = bond_mod.bond_stats(state.bonds)
    axis_of = jnp.argmax(jnp.abs(w.normal), axis=-1)
    return dict(
        step=state.step,
        wall_pos=jnp.take_along_axis(w.point, axis_of[:, None], axis=-1)[:, 0],
        wall_stress_force=-jnp.sum(w.force * w.normal, axis=-1),   # compressive force [N]
        wall_area=w.area,
        width=_slice_widths(state.particles, config.dim),
        stress_sum=measure.averaged_stress(state, params, config, 1.0),
        fracture_degree=stats["fracture_degree"],
        n_broken=stats["n_broken"], n_tension=stats["n_tension"], n_shear=stats["n_shear"],
        bond_energy=bond_mod.bond_strain_energy(state.bonds, state.particles, params,
                                                config.dim),
        contact_energy=measure.contact_energy(state, params, config),
        kinetic_energy=measure.kinetic_energy(state),
    )


def derive_platen_history(raw: dict, frame: PlatenFrame) -> dict:
    """History of a platen test from the raw records of :func:`platen_observe`
    (NumPy, optionally with a leading batch axis).  Every entry has one row per
    record (records on the last axis before any per-record shape):

    step               step number
    height             distance between the platens [m]
    axial_strain       (h0 - H) / h0 from the platen positions (compression positive)
    axial_stress       compressive force on the top platen / ``frame.area`` [Pa]
                       (nominal: the initial cross-section)
    bottom_stress      the same on the bottom platen (equal at equilibrium)
    width              lateral extent [m] per lateral axis (..., d-1): the lateral
                       walls' distance in a biaxial test, otherwise the mean over
                       ``N_SLICES`` slices of the extent of each slice's outermost
                       particles (:func:`_slice_widths`)
    lateral_strain     (w0 - w) / w0, compression positive like axial_strain (so
                       negative when the specimen bulges); mean over lateral axes
    volumetric_strain  axial_strain + sum of lateral strains (small strains)
    lateral_stress     biaxial: mean compressive stress on the lateral walls [Pa]
    volume             current H x ``frame.area`` x (w / w0) per lateral axis [m^3]
                       (the box the particles fill, scaled by the lateral strain;
                       Brazilian: the disc area pi D^2 / 4 x 1 m)
    avg_stress         averaged stress tensor (..., d, d) of the particles
                       (:func:`jdem.measure.averaged_stress` with ``volume``),
                       compression positive
    avg_stress_axial, avg_stress_lateral   its diagonal along the loading axis and
                       the mean of the lateral diagonal entries
    fracture_degree, n_broken, n_tension, n_shear   (:func:`jdem.bond.bond_stats`)
    bond_energy        bond strain energy L_p [J] (002 eq 16)
    contact_energy     elastic energy of unbonded contacts and platen contacts [J]
    kinetic_energy     [J]
    Brazilian tests also: load (top platen force P [N]) and
    tensile_strength_indirect sigma_t = 2 P / (pi D t), t = 1 m.
    """
    r = {k: np.asarray(v) for k, v in raw.items()}
    dim = frame.dim
    h = {"step": r["step"]}
    pos = r["wall_pos"]
    height = pos[..., 1] - pos[..., 0]
    h["height"] = height
    h["axial_strain"] = (frame.h0 - height) / frame.h0
    h["axial_stress"] = r["wall_stress_force"][..., 1] / frame.area
    h["bottom_stress"] = r["wall_stress_force"][..., 0] / frame.area
    w0 = np.asarray(frame.w0, dtype=np.float64)
    if frame.n_lateral:
        lat = pos[..., 2:2 + frame.n_lateral]
        width = np.stack([lat[..., 2 * a + 1] - lat[..., 2 * a] for a in range(dim - 1)], -1)
        lat_stress = r["wall_stress_force"][..., 2:2 + frame.n_lateral] / r["wall_area"][..., 2:2 + frame.n_lateral]
        h["lateral_stress"] = lat_stress.mean(axis=-1)
    else:
        width = r["width"]
    h["width"] = width
    lat_strain = (w0 - width) / w0
    h["lateral_strain"] = lat_strain.mean(axis=-1)
    h["volumetric_strain"] = h["axial_strain"] + lat_strain.sum(axis=-1)
    if frame.test == "brazilian":
        volume = np.pi * frame.diameter ** 2 / 4.0 * np.ones_like(height)
    else:
        volume = height * frame.area * np.prod(width / w0, axis=-1)
    h["volume"] = volume
    sig = r["stress_sum"] / volume[..., None, None]
    h["avg_stress"] = sig
    h["avg_stress_axial"] = sig[..., dim - 1, dim - 1]
    h["avg_stress_lateral"] = np.mean([sig[..., a, a] for a in range(dim - 1)], axis=0)
    for k in ("fracture_degree", "n_broken", "n_tension", "n_shear", "bond_energy",
              "contact_energy", "kinetic_energy"):
        h[k] = r[k]
    if frame.test == "brazilian":
        h["load"] = r["wall_stress_force"][..., 1]
        h["tensile_strength_indirect"] = 2.0 * h["load"] / (np.pi * frame.diameter * 1.0)
    return h


# ----------------------------------------------------------------------------- set-up
class PlatenSetup(NamedTuple):
    """A platen test ready to run: initial ``state`` (batched if ``params`` is),
    ``params`` (with the chosen ``dt``), ``config``, the ``frame`` and whether
    it is ``batched``."""

    state: object
    params: Params
    config: object
    frame: PlatenFrame
    batched: bool


def _specimen_arrays(specimen):
    """(particles, bonds, info) from a :class:`jdem.specimen.Specimen` or a
    ``(particles, bonds)`` pair or ``(particles, bonds, info)`` triple."""
    if hasattr(specimen, "particles") and hasattr(specimen, "bonds"):
        return specimen.particles, specimen.bonds, dict(getattr(specimen, "info", {}) or {})
    if len(specimen) == 3:
        particles, bonds, info = specimen
        return particles, bonds, dict(info or {})
    particles, bonds = specimen
    return particles, bonds, {}


def _extent(particles, axis):
    p = np.asarray(particles.pos, np.float64)
    r = np.asarray(particles.radius, np.float64)
    v = np.asarray(particles.valid, bool)
    return float(np.min(p[v, axis] - r[v])), float(np.max(p[v, axis] + r[v]))


def platen_setup(specimen, params, *, test="ucs", platen_step=1e-9, confining_stress=None,
                 servo_gain=0.5, servo_vmax=1.0, top_stress=None, dt=None,
                 platen_material=PLATEN) -> PlatenSetup:
    """Put platens (and lateral servo walls) around a bonded specimen.

    Walls: 0 bottom platen (fixed), 1 top platen (speed ``platen_step / dt``
    towards the specimen, or servo-controlled to ``top_stress`` if given), then
    with ``confining_stress`` the lateral walls (2D: left, right; 3D: -x, +x,
    -y, +y) servo-controlled to it (000 eq 4-69) over the area current height x
    1 m (2D; 3D: height x the other lateral extent), which :func:`platen_run`
    refreshes between chunks.  Every wall starts on the outermost particle edge.
    ``dt`` defaults to ``jdem.timestep.recommended`` of the critical step of the
    specimen with its bonds, with every wall pushed in by 1e-3 of the smallest
    radius (so that the platen contacts count), the smallest over a batch.
    """
    from jdem.state import make_walls

    particles, bonds, info = _specimen_arrays(specimen)
    dim = int(particles.pos.shape[1])
    ax = dim - 1
    if np.asarray(particles.pos).dtype != np.float64:
        warnings.warn("platen tests need float64 positions (jax_enable_x64): a platen step "
                      "of 1 nm on a 10 cm specimen is below float32 resolution", stacklevel=3)
    steps = np.atleast_1d(np.asarray(platen_step, dtype=np.float64))
    if steps.ndim != 1 or not np.all(np.isfinite(steps) & (steps >= 0)):
        raise InputError(f"platen_step must be a finite length >= 0 (or one per batch "
                         f"member), got {platen_step!r}")
    if confining_stress is not None and not (np.isfinite(confining_stress) and confining_stress > 0):
        raise InputError(f"confining_stress must be > 0 (or None), got {confining_stress!r}")
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=jnp.asarray(a).dtype), params)
    if np.shape(params.kn)[-1] <= platen_material:
        raise InputError(f"params has {np.shape(params.kn)[-1]} materials; the platens use "
                         f"material {platen_material} (see rock_params)")
    batched = _is_batched(params)
    n_batch = int(np.shape(params.dt)[0]) if batched else None
    if np.ndim(platen_step) and (not batched or steps.size != n_batch):
        raise InputError(f"platen_step has {steps.size} values; a sequence needs batched params "
                         f"with as many members (got {n_batch or 'unbatched'})")
    n = int(particles.pos.shape[0])

    lo_ax, hi_ax = _extent(particles, ax)
    points, normals = [], []
    e = np.eye(dim)
    points.append(e[ax] * lo_ax)
    normals.append(e[ax])
    points.append(e[ax] * hi_ax)
    normals.append(-e[ax])
    n_lat = 0
    if confining_stress is not None:
        for a in range(dim - 1):
            lo, hi = _extent(particles, a)
            points += [e[a] * lo, e[a] * hi]
            normals += [e[a], -e[a]]
        n_lat = 2 * (dim - 1)
    n_w = 2 + n_lat
    servo = np.zeros(n_w, bool)
    target = np.zeros(n_w)
    area = np.ones(n_w)
    servo[2:] = True
    target[2:] = confining_stress or 0.0
    ext = [_extent(particles, a) for a in range(dim - 1)]
    widths_box = [hi - lo for lo, hi in ext]
    area[:2] = float(np.prod(widths_box))
    if top_stress is not None:
        servo[1] = True
        target[1] = float(top_stress)
    h_box = hi_ax - lo_ax
    for k in range(n_lat):
        a = k // 2
        area[2 + k] = h_box * float(np.prod([w for b, w in enumerate(widths_box) if b != a]))
    walls = make_walls(np.asarray(points), np.asarray(normals), n_particles=n,
                       material=np.full(n_w, platen_material), servo=servo,
                       target_stress=target, area=area, servo_gain=servo_gain,
                       servo_vmax=servo_vmax)
    state, config = make_state(particles, walls=walls, bonds=bonds)

    members = [member(params, b) for b in range(n_batch)] if batched else [params]
    if dt is None:
        r_small = float(np.min(np.asarray(particles.radius)[np.asarray(particles.valid)]))
        push = 1e-3 * r_small
        probe = state._replace(walls=walls._replace(point=walls.point + push * walls.normal))
        crit = min(float(timestep.critical_timestep(probe, m, config)) for m in members)
        dt = timestep.recommended(crit)
    dt = float(dt)
    params = params._replace(dt=jnp.full(np.shape(params.dt), dt, jnp.asarray(params.dt).dtype))
    speeds = steps / dt
    velocity = float(speeds[0]) if speeds.size == 1 else tuple(float(v) for v in speeds)

    w0 = tuple(float(x) for x in np.asarray(_slice_widths(particles, dim)))
    if n_lat:
        w0 = tuple(float(w) for w in widths_box)
    diameter = 0.0
    if test == "brazilian":
        diameter = float(2.0 * info["radius"]) if "radius" in info else h_box
    frame = PlatenFrame(test=test, dim=dim, h0=float(h_box), w0=w0,
                        area=float(np.prod(widths_box)) if test != "brazilian" else 1.0,
                        velocity=velocity, confining_stress=float(confining_stress or 0.0),
                        diameter=diameter, n_lateral=n_lat)
    if batched:
        state = broadcast_batch(state, n_batch)
    if top_stress is None:
        state = _set_platen_speed(state, frame)
    return PlatenSetup(state=state, params=params, config=config, frame=frame, batched=batched)


def _set_platen_speed(state, frame: PlatenFrame):
    """Top platen (wall 1) moving towards the specimen at ``frame.velocity`` (one
    value, or one per batch member), not servo-controlled."""
    w = state.walls
    ax = frame.dim - 1
    v = jnp.asarray(frame.velocity, dtype=w.vel.dtype)
    vel = jnp.zeros_like(w.vel).at[..., 1, ax].set(-v)
    return state._replace(walls=w._replace(vel=vel, servo=w.servo.at[..., 1].set(False)))


def _update_servo_areas(state, frame: PlatenFrame):
    """Lateral servo walls: area = current height x the other lateral extents."""
    if not frame.n_lateral:
        return state
    w = state.walls
    ax = frame.dim - 1
    pos = w.point
    height = pos[..., 1, ax] - pos[..., 0, ax]
    widths = [pos[..., 3 + 2 * a, a] - pos[..., 2 + 2 * a, a] for a in range(frame.dim - 1)]
    area = w.area
    for k in range(frame.n_lateral):
        a = k // 2
        other = [widths[b] for b in range(frame.dim - 1) if b != a]
        val = height * (functools.reduce(lambda x, y: x * y, other) if other else 1.0)
        area = area.at[..., 2 + k].set(val)
    return state._replace(walls=w._replace(area=area))


# ----------------------------------------------------------------------------- bonds for plots
def _bond_points(state):
    """Contact point of every bond row (dividing the centre line R1 : R2), the unit
    branch vector and the half width min(R1, R2) of the bar; NumPy."""
    p = state.particles
    b = state.bonds
    pos = np.asarray(p.pos, np.float64)
    rad = np.asarray(p.radius, np.float64)
    i, j = np.asarray(b.i), np.asarray(b.j)
    r1, r2 = rad[i], rad[j]
    dx = pos[j] - pos[i]
    length = np.where(r1 + r2 > 0, r1 + r2, 1.0)
    point = pos[i] + (r1 / length)[:, None] * dx
    dist = np.linalg.norm(dx, axis=1)
    nrm = dx / np.where(dist > 0, dist, 1.0)[:, None]
    return point, nrm, np.minimum(r1, r2)


def _check_unbatched(state, name):
    if np.ndim(state.step) != 0:
        raise InputError(f"{name} takes one (unbatched) state; pick a member with "
                         f"jdem.labtests.member(state, b)")


def failure_pattern(state) -> dict:
    """The broken bonds of a state, for plotting a failure pattern (002 Fig. 12).

    index    (n,)       bond rows that are broken
    point    (n, d)     contact point of the bar (the centre line divided R1 : R2) [m]
    segment  (n, 2, d)  2D: the crack face, the bar's cross-section (length
                        A_c = 2 min(R1, R2), perpendicular to the bond) through
                        ``point``; 3D: the bond's centre line between the centres
    mode     (n,)       1 tension, 2 shear (``Bonds.break_mode``)
    step     (n,)       step at which it broke
    """
    _check_unbatched(state, "failure_pattern")
    b = state.bonds
    point, nrm, half = _bond_points(state)
    broken = np.asarray(b.valid) & np.asarray(b.broken)
    idx = np.nonzero(broken)[0]
    if point.shape[1] == 2:
        tang = np.stack([-nrm[:, 1], nrm[:, 0]], axis=1)
        seg = np.stack([point - half[:, None] * tang, point + half[:, None] * tang], axis=1)
    else:
        pos = np.asarray(state.particles.pos, np.float64)
        seg = np.stack([pos[np.asarray(b.i)], pos[np.asarray(b.j)]], axis=1)
    return dict(index=idx, point=point[idx], segment=seg[idx],
                mode=np.asarray(b.break_mode)[idx], step=np.asarray(b.break_step)[idx])


def first_breaks(pattern: dict, fraction: float = 0.1, minimum: int = 5) -> np.ndarray:
    """Where a failure starts: indices into the arrays of :func:`failure_pattern`
    of its earliest broken bonds, the first ``fraction`` of them by breaking step
    but at least ``minimum`` (all of them if fewer broke).  Bonds that broke in
    the same step keep their row order."""
    n = len(pattern["step"])
    count = max(int(minimum), int(np.floor(n * float(fraction) + 1e-9)))
    return np.argsort(pattern["step"], kind="stable")[:count]


def damage_map(state) -> dict:
    """Every valid bond's contact point and damage (002 eq 10), for a damage map
    (002 Fig. 13): ``point`` (B, d), ``chi``, ``alpha``, ``beta`` (B,),
    ``broken`` (B,) bool, ``mode`` (B,) and ``index`` (B,) of the rows."""
    _check_unbatched(state, "damage_map")
    b = state.bonds
    point, _, _ = _bond_points(state)
    valid = np.asarray(b.valid)
    idx = np.nonzero(valid)[0]
    dmg = {k: np.asarray(v) for k, v in bond_mod.damage(b).items()}
    return dict(index=idx, point=point[idx], chi=dmg["chi"][idx], alpha=dmg["alpha"][idx],
                beta=dmg["beta"][idx], broken=np.asarray(b.broken)[idx],
                mode=np.asarray(b.break_mode)[idx])


def _bond_record(state, prefix):
    """Per-bond arrays of a state (batched or not) for the history: the contact
    point, chi, break mode and break step of every bond row."""
    batched = np.ndim(state.step) == 1
    members = [member(state, k) for k in range(state.step.shape[0])] if batched else [state]
    out = {f"{prefix}point": [], f"{prefix}chi": [], f"{prefix}mode": [],
           f"{prefix}break_step": [], f"{prefix}valid": []}
    for s in members:
        point, _, _ = _bond_points(s)
        out[f"{prefix}point"].append(point)
        out[f"{prefix}chi"].append(np.asarray(bond_mod.damage(s.bonds)["chi"]))
        broken = np.asarray(s.bonds.broken)
        out[f"{prefix}mode"].append(np.where(broken, np.asarray(s.bonds.break_mode), 0))
        out[f"{prefix}break_step"].append(np.asarray(s.bonds.break_step))
        out[f"{prefix}valid"].append(np.asarray(s.bonds.valid))
    return {k: (np.stack(v) if batched else v[0]) for k, v in out.items()}


# ----------------------------------------------------------------------------- host loop
def _concat_raw(parts, batched):
    ax = 1 if batched else 0
    return {k: np.concatenate([p[k] for p in parts], axis=ax) for k in parts[0]}


def platen_run(state, params, config, frame: PlatenFrame, n_steps: int, *,
               record_every=UCS_RECORD_EVERY, chunk_steps=UCS_CHUNK_STEPS, progress=False,
               batched=None, stop_stress_ratio=None, keep_peak_state=False, desc="platen",
               check_dt=True):
    """Run a platen test for ``n_steps`` steps (rounded up to whole chunks of
    ``chunk_steps``) with :func:`jdem.run`, one call per chunk.  Returns
    ``(history, state, config)``, history as in :func:`derive_platen_history`
    plus the per-bond arrays of the final state (``end_point`` (B, d) contact
    points, ``end_chi``, ``end_mode`` (0 intact, 1 tension, 2 shear),
    ``end_break_step``, ``end_valid``; a leading batch axis when batched).

    Between chunks: the lateral servo walls get the current height as area
    (within a chunk the area is that of its start: at 1 nm per step and 2,000
    steps per chunk the height changes by 2e-5 of 10 cm, so the servo stress is
    off by at most that fraction); the run stops early when
    ``stop_stress_ratio`` is set and, for every member, the mean axial stress
    over a chunk after the one holding its peak is below that fraction of the
    peak.

    ``keep_peak_state``: also return the bonds at the peak of the axial stress
    (``peak_point``, ``peak_chi``, ``peak_mode``, ``peak_break_step``,
    ``peak_valid``, ``peak_step``): the (whole, batched) state at the start of
    the chunk holding a member's peak is kept and, at the end, advanced to the
    peak record with :func:`jdem.advance` (batched like the run, so the same
    trajectory; one extra compile of ``advance``).
    """
    from jdem.simulate import advance

    if record_every < 1 or chunk_steps % record_every:
        raise InputError(f"record_every = {record_every} must divide chunk_steps = {chunk_steps}")
    batched = _is_batched(params) if batched is None else bool(batched)
    n_chunks = max(1, int(math.ceil(n_steps / chunk_steps)))
    nb = int(np.shape(params.dt)[0]) if batched else 1
    parts = []
    peak_val = np.full(nb, -np.inf)
    peak_idx = np.zeros(nb, int)
    peak_start = [None] * nb
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n_chunks * chunk_steps, desc=desc, unit="step", leave=False)
    n_rec = 0
    try:
        for k in range(n_chunks):
            state = _update_servo_areas(state, frame)
            start, start_cfg = state, config
            res = run(state, params, config, chunk_steps, record_every=record_every,
                      observe=platen_observe, chunk_steps=chunk_steps, progress=False,
                      batched=batched, check_dt=check_dt and k == 0)
            state, config = res.state, res.config
            raw = {key: np.asarray(v) for key, v in res.history.items()}
            parts.append(raw)
            stress = derive_platen_history(raw, frame)["axial_stress"].reshape(nb, -1)
            for b in range(nb):
                j = int(np.argmax(stress[b]))
                if stress[b, j] > peak_val[b]:
                    peak_val[b], peak_idx[b] = stress[b, j], n_rec + j
                    if keep_peak_state:   # the whole (batched) state at the chunk start
                        peak_start[b] = (start, start_cfg,
                                         int(raw["step"].reshape(nb, -1)[b, j]))
            n_rec += stress.shape[1]
            if bar is not None:
                bar.update(chunk_steps)
                bar.set_postfix(stress=f"{float(np.max(stress[:, -1])) / 1e6:.3g} MPa")
            if stop_stress_ratio is not None:
                # the chunk's mean, not its last record: the post-peak load rings
                recent = stress.mean(axis=1)
                if np.all((recent < stop_stress_ratio * peak_val)
                          & (peak_idx < n_rec - stress.shape[1])):
                    break
    finally:
        if bar is not None:
            bar.close()
    history = derive_platen_history(_concat_raw(parts, batched), frame)
    history.update(_bond_record(state, "end_"))
    if keep_peak_state:
        recs = []
        for b in range(nb):
            s0, cfg0, step = peak_start[b]
            start_step = int(np.max(np.asarray(s0.step)))
            s = advance(s0, params, cfg0, step - start_step, batched=batched)
            recs.append(_bond_record(member(s, b) if batched else s, "peak_"))
            recs[-1]["peak_step"] = np.asarray(step)
        peak = {key: np.stack([r[key] for r in recs]) if batched else recs[0][key]
                for key in recs[0]}
        history.update(peak)
    return history, state, config


def _n_steps_for(max_strain, h0, platen_step, chunk_steps):
    if not (np.isfinite(max_strain) and max_strain > 0):
        raise InputError(f"max_strain must be > 0, got {max_strain!r}")
    slowest = float(np.min(platen_step))
    if not slowest > 0:
        raise InputError(f"platen_step must be > 0, got {platen_step!r}")
    return _round_up(max_strain * h0 / slowest, chunk_steps)


# ----------------------------------------------------------------------------- UCS / biaxial
def ucs_setup(specimen, params, *, platen_step=1e-9, confining_stress=None,
              platen_material=PLATEN, dt=None, preload_steps=20_000, progress=False,
              chunk_steps=UCS_CHUNK_STEPS, record_every=UCS_RECORD_EVERY) -> PlatenSetup:
    """The specimen between its platens, ready for axial loading (see
    :func:`ucs_test`).  With ``confining_stress`` the specimen is first brought
    to the isotropic stress: every wall (the top platen too) is servo-controlled
    to it for ``preload_steps`` steps (rounded up to chunks); then the top platen
    is switched to its constant speed and ``frame.h0`` / ``frame.w0`` are taken
    from the walls at that moment."""
    su = platen_setup(specimen, params, test="ucs" if confining_stress is None else "biaxial",
                      platen_step=platen_step, confining_stress=confining_stress, dt=dt,
                      top_stress=confining_stress, platen_material=platen_material)
    if confining_stress is None:
        return su
    state, config, frame = su.state, su.config, su.frame
    _, state, config = platen_run(state, su.params, config, frame, preload_steps,
                                  record_every=record_every, chunk_steps=chunk_steps,
                                  progress=progress, batched=su.batched, desc="preload")
    state = _set_platen_speed(state, frame)
    dim = frame.dim
    ax = dim - 1
    pos = np.asarray(state.walls.point)
    pos0 = pos[0] if su.batched else pos   # the members start alike; use member 0's geometry
    h0 = float(pos0[1, ax] - pos0[0, ax])
    w0 = tuple(float(pos0[3 + 2 * a, a] - pos0[2 + 2 * a, a]) for a in range(dim - 1))
    frame = frame._replace(h0=h0, w0=w0)
    return su._replace(state=state, config=config, frame=frame)


def ucs_test(specimen, params, *, platen_step=1e-9, max_strain=3e-3,
             record_every=UCS_RECORD_EVERY, confining_stress=None, platen_material=PLATEN,
             progress=False, chunk_steps=UCS_CHUNK_STEPS, dt=None, batched=None,
             preload_steps=20_000, stop_stress_ratio=None, keep_peak_state=False):
    """Uniaxial (or, with ``confining_stress``, biaxial) compression of a bonded
    specimen (002 §2).  Returns ``(history, state, config)``.

    specimen        :class:`jdem.specimen.Specimen` (or ``(particles, bonds)``);
                    particles of material 0, loading axis = last axis
    params          e.g. :func:`rock_params` (two materials: rock 0, platen 1); a
                    leading batch axis (e.g. ``rock_params(kappa=[...])``) runs
                    the members as one vmapped call (``jdem.run(batched=True)``)
    platen_step     top platen displacement per step [m] (speed platen_step / dt);
                    the bottom platen is fixed, the sides are free (uniaxial).  With
                    batched params it may be a sequence, one per member (e.g. to
                    compare loading rates in one vmapped run)
    max_strain      axial strain to load to (rounded up to whole chunks); with
                    several platen steps, the slowest member reaches it
    confining_stress  lateral servo walls at this stress [Pa] (000 eq 4-69; the
                    servo area is the current height x 1 m, refreshed between
                    chunks), after an isotropic pre-load (:func:`ucs_setup`)
    dt              time step; default ``jdem.timestep.recommended`` of the
                    critical step of the specimen with bonds and platen contacts
    stop_stress_ratio  stop early once every member's stress fell below this
                    fraction of its peak after the peak (None: run to max_strain)
    keep_peak_state add the bonds at the peak (``peak_*``, see :func:`platen_run`)

    History: :func:`derive_platen_history` (one row per record; batched: a
    leading batch axis) plus ``end_*`` (and ``peak_*``) per-bond arrays.
    Summaries: :func:`peak_summary`.  Restart: :func:`save_checkpoint`,
    :func:`load_checkpoint`, :func:`platen_run`.
    """
    su = ucs_setup(specimen, params, platen_step=platen_step, confining_stress=confining_stress,
                   platen_material=platen_material, dt=dt, preload_steps=preload_steps,
                   progress=progress, chunk_steps=chunk_steps, record_every=record_every)
    if batched is not None and bool(batched) != su.batched:
        raise InputError(f"batched={batched!r} but params "
                         f"{'have' if su.batched else 'have no'} leading batch axis")
    n_steps = _n_steps_for(max_strain, su.frame.h0, platen_step, chunk_steps)
    return platen_run(su.state, su.params, su.config, su.frame, n_steps,
                      record_every=record_every, chunk_steps=chunk_steps, progress=progress,
                      batched=su.batched, stop_stress_ratio=stop_stress_ratio,
                      keep_peak_state=keep_peak_state, desc=su.frame.test)


# ----------------------------------------------------------------------------- checkpoints
def save_checkpoint(path, state, params, config, frame: PlatenFrame, history=None,
                    attrs=None):
    """Save a platen test mid-run (``jdem.io.save_run``: state, params, config,
    history; the frame as root attributes ``frame_*``)."""
    from jdem import io

    a = {f"frame_{k}": v for k, v in frame._asdict().items()}
    a.update(attrs or {})
    return io.save_run(path, state=state, params=params, config=config, history=history,
                       attrs=a)


def load_checkpoint(path):
    """``(state, params, config, frame, history)`` written by :func:`save_checkpoint`."""
    from jdem import io

    rd = io.load_run(path)
    attrs = rd.attrs or {}
    try:
        fields = {k: attrs[f"frame_{k}"] for k in PlatenFrame._fields}
    except KeyError as e:
        raise InputError(f"{path} holds no platen-test frame (missing attribute {e})") from None
    fields["w0"] = tuple(fields["w0"])
    fields["dim"] = int(fields["dim"])
    fields["n_lateral"] = int(fields["n_lateral"])
    return rd.state, rd.params, rd.config, PlatenFrame(**fields), rd.history


# ----------------------------------------------------------------------------- summary
def _fit_modulus(strain, stress, peak, k_peak, lo=0.1, hi=0.4):
    """Least-squares slope of stress vs strain over the pre-peak records with
    lo x peak <= stress <= hi x peak."""
    s, e = stress[:k_peak + 1], strain[:k_peak + 1]
    sel = (s >= lo * peak) & (s <= hi * peak)
    if sel.sum() < 3:
        return float("nan")
    return float(np.polyfit(e[sel], s[sel], 1)[0])


def peak_summary(history: dict, *, lo=0.1, hi=0.4) -> dict:
    """Key figures of a compression curve (batched histories: arrays over members).

    peak_stress                  largest axial stress [Pa]
    critical_strain              axial strain at the peak (002 §2.2)
    youngs_modulus               least-squares slope of stress vs strain over the
                                 pre-peak records with 10 % .. 40 % of the peak
                                 stress (``lo``, ``hi``): the linear stage,
                                 clear of the initial seating transient
    poisson_ratio                -d(lateral_strain)/d(axial_strain) over the same records
    fracture_degree_at_peak, fracture_degree_end
    final_stress                 axial stress of the last record
    peak_index, peak_step
    """
    stress = np.asarray(history["axial_stress"])
    if stress.ndim == 2:
        rows = [peak_summary(member(history, b), lo=lo, hi=hi) for b in range(stress.shape[0])]
        return {k: np.asarray([r[k] for r in rows]) for k in rows[0]}
    strain = np.asarray(history["axial_strain"])
    k = int(np.argmax(stress))
    peak = float(stress[k])
    lat = np.asarray(history["lateral_strain"])
    s = stress[:k + 1]
    sel = (s >= lo * peak) & (s <= hi * peak)
    nu = float(-np.polyfit(strain[:k + 1][sel], lat[:k + 1][sel], 1)[0]) if sel.sum() >= 3 \
        else float("nan")
    fd = np.asarray(history["fracture_degree"])
    return dict(peak_stress=peak, critical_strain=float(strain[k]),
                youngs_modulus=_fit_modulus(strain, stress, peak, k, lo, hi),
                poisson_ratio=nu, fracture_degree_at_peak=float(fd[k]),
                fracture_degree_end=float(fd[-1]), final_stress=float(stress[-1]),
                peak_index=k, peak_step=int(np.asarray(history["step"])[k]))


# ----------------------------------------------------------------------------- Brazilian
def brazilian_test(specimen_disc, params, *, platen_step=2e-9, max_strain=0.01,
                   record_every=UCS_RECORD_EVERY, chunk_steps=UCS_CHUNK_STEPS,
                   stop_stress_ratio=0.3, platen_material=PLATEN, progress=False, dt=None,
                   keep_peak_state=False):
    """Brazilian splitting test: diametral compression of a 2D disc between two
    flat rigid platens (bottom fixed, top moving down by ``platen_step`` per
    step).  ``specimen_disc``: :func:`jdem.specimen.generate` ``("disc", D, ...)``
    (D from ``info["radius"]``, else the vertical extent).  Returns
    ``(history, state, config)``.

    History: as :func:`derive_platen_history` (``axial_strain`` = platen
    displacement / initial platen gap (~ D), ``axial_stress`` = load [N] per m
    of thickness) plus ``load`` P [N]
    (top platen force) and ``tensile_strength_indirect`` sigma_t = 2P / (pi D t),
    t = 1 m; ``end_point`` / ``end_mode`` / ``end_break_step`` give the broken
    bonds at the end (contact points, 1 tension / 2 shear, step of breaking);
    see :func:`failure_pattern` for the same from a state.  Stops at ``max_strain``
    (platen displacement / D) or once the load fell below ``stop_stress_ratio``
    of its peak.
    """
    su = platen_setup(specimen_disc, params, test="brazilian", platen_step=platen_step,
                      dt=dt, platen_material=platen_material)
    if su.frame.dim != 2:
        raise InputError(f"brazilian_test needs a 2D disc specimen, got dim {su.frame.dim}")
    frame = su.frame   # strain = (H0 - H) / H0, H the platen gap (H0 ~ D)
    n_steps = _n_steps_for(max_strain, frame.h0, platen_step, chunk_steps)
    return platen_run(su.state, su.params, su.config, frame, n_steps,
                      record_every=record_every, chunk_steps=chunk_steps, progress=progress,
                      batched=su.batched, stop_stress_ratio=stop_stress_ratio,
                      keep_peak_state=keep_peak_state, desc="brazilian")


# ----------------------------------------------------------------------------- 002 §1.4
def continuum_strain_energy(stress, E, nu, volume, plane="strain"):
    """Strain energy of an elastic block under uniaxial stress ``stress`` with free
    sides, L_e = sigma^2 / (2 E') V (002 eq 16): plane stress E' = E, plane strain
    E' = E / (1 - nu^2) (the out-of-plane strain held at zero)."""
    if plane not in ("strain", "stress"):
        raise InputError(f"plane must be 'strain' or 'stress', got {plane!r}")
    e_eff = E if plane == "stress" else E / (1.0 - nu ** 2)
    return stress ** 2 / (2.0 * e_eff) * volume


def coordination_energy_ratio(specimen, params, *, stress=1e6, plane="strain",
                              record_every=UCS_RECORD_EVERY, chunk_steps=UCS_CHUNK_STEPS,
                              max_steps=200_000, min_steps=10_000, tol=2e-3, dt=None,
                              core_margin=0.2, progress=False):
    """lambda = L_p / L_e of 002 §1.4 (eq 15-16) for one bonded 2D block.

    The block sits between a fixed bottom platen and a top platen servo-controlled
    to ``stress`` (000 eq 4-69, compressive, area = block width x 1 m); the sides
    are free.  The run goes on in chunks until it is at rest: the top and bottom
    platen stresses within ``tol`` of ``stress`` and the kinetic energy below
    ``tol`` x the bond energy (at least ``min_steps``, at most ``max_steps``).

    L_p is the bond strain energy (:func:`jdem.bond.bond_strain_energy`, 002
    eq 16, normal + shear).  L_e is the energy of a continuum block of the
    same size and E, nu under the same uniaxial stress (002 eq 16), by default in
    plane strain: the seed's finite-element value, 0.151 J for 10 cm x 10 cm,
    E = 30 GPa, nu = 0.3, 1 MPa, is the plane-strain figure (1 - nu^2) sigma^2 V
    / (2E) = 0.1517 J (plane stress would give 0.1667 J).  V = width x height x
    1 m of the specimen box.

    Boundary effect: a random packing touches a flat platen at a few particles
    only, and the "seating" of the others takes a displacement comparable to the
    whole elastic one at 1 MPa on a small block; the bonds near the platens then
    store extra energy.  ``lam_core`` = L_p / L_e over the bulk only: the bonds
    whose contact point lies farther than ``core_margin`` x H from both platens,
    against sigma^2 / (2 E') times that slab's volume.

    Returns a dict: ``lam``, ``L_p``, ``L_e``, ``lam_core``, ``L_p_core``,
    ``L_e_core``, ``coordination`` (N-bar of the
    specimen), ``n_particles``, ``n_bonds``, ``steps``, ``top_stress``,
    ``bottom_stress``, ``avg_stress`` (d, d) (averaged stress tensor with the
    current volume), ``axial_strain``, ``E_macro`` = stress / axial strain,
    ``kinetic_energy``, ``contact_energy``, ``converged`` and the ``history``.
    """
    particles, bonds, info = _specimen_arrays(specimen)
    su = platen_setup(specimen, params, test="energy", platen_step=0.0, top_stress=stress,
                      dt=dt)
    if su.batched:
        raise InputError("coordination_energy_ratio takes unbatched params")
    state, config, frame = su.state, su.config, su.frame
    parts = []
    steps = 0
    converged = False
    while steps < max_steps:
        hist, state, config = platen_run(state, su.params, config, frame, chunk_steps,
                                         record_every=record_every, chunk_steps=chunk_steps,
                                         progress=False, check_dt=steps == 0)
        hist = {k: v for k, v in hist.items() if not k.startswith("end_")}
        parts.append(hist)
        steps += chunk_steps
        top, bot = float(hist["axial_stress"][-1]), float(hist["bottom_stress"][-1])
        ke, be = float(hist["kinetic_energy"][-1]), float(hist["bond_energy"][-1])
        if progress:
            print(f"  energy ratio: {steps} steps, top {top / 1e6:.4f} MPa, bottom "
                  f"{bot / 1e6:.4f} MPa, KE / L_p {ke / max(be, 1e-300):.2e}")
        if (steps >= min_steps and abs(top / stress - 1) < tol and abs(bot / stress - 1) < tol
                and ke < tol * be):
            converged = True
            break
    history = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    lo, hi = specimen.box if hasattr(specimen, "box") else (None, None)
    if lo is not None:
        volume = float(np.prod(np.asarray(hi) - np.asarray(lo)))
    else:
        volume = frame.h0 * float(np.prod(frame.w0))
    l_p = float(bond_mod.bond_strain_energy(state.bonds, state.particles, su.params, frame.dim))
    l_e = continuum_strain_energy(stress, float(su.params.bond_youngs),
                                  float(su.params.bond_poisson), volume, plane)
    # the bulk: bonds whose contact point lies farther than core_margin x H from
    # either platen, against the continuum energy of that slab
    point, _, _ = _bond_points(state)
    b = state.bonds
    e_bond = 0.5 * (-np.asarray(b.normal_force) * np.asarray(b.u_n)
                    - np.sum(np.asarray(b.shear_force) * np.asarray(b.u_s), axis=-1))
    live = np.asarray(b.valid) & ~np.asarray(b.broken)
    ax = frame.dim - 1
    wpos = np.asarray(state.walls.point)[:2, ax]
    height = float(wpos[1] - wpos[0])
    margin = core_margin * height
    core = live & (point[:, ax] > wpos[0] + margin) & (point[:, ax] < wpos[1] - margin)
    l_p_core = float(np.sum(np.where(core, e_bond, 0.0)))
    l_e_core = l_e * (height - 2 * margin) / height
    n_b = int(np.sum(np.asarray(bonds.valid)))
    n_p = int(np.sum(np.asarray(particles.valid)))
    coord = getattr(specimen, "coordination", None)
    return dict(lam=l_p / l_e, L_p=l_p, L_e=l_e, lam_core=l_p_core / l_e_core,
                L_p_core=l_p_core, L_e_core=l_e_core,
                coordination=float(coord) if coord is not None else 2.0 * n_b / n_p,
                n_particles=n_p, n_bonds=n_b, steps=steps, top_stress=top, bottom_stress=bot,
                avg_stress=history["avg_stress"][-1], axial_strain=float(history["axial_strain"][-1]),
                E_macro=stress / float(history["axial_strain"][-1]),
                kinetic_energy=ke, contact_energy=float(history["contact_energy"][-1]),
                converged=converged, history=history, state=state, config=config)


def flatten_disc(specimen_disc, flat_angle_deg):
    """A Brazilian disc with two flat loading faces ("flattened Brazilian disc"):
    the particles reaching beyond the chords at +-``flat_angle_deg`` / 2 from the
    loaded (vertical) diameter are removed, with their bonds.  Returns
    ``(particles, bonds, info)`` (info with ``radius``, ``centre``,
    ``flat_angle_deg``), usable as the specimen of :func:`brazilian_test`.
    A flat of 2 alpha ~ 20-30 deg spreads the platen load over several
    particles, so that the splitting crack starts in the disc's interior rather
    than by crushing under a one-particle point load."""
    from jdem.state import Particles, empty_bonds

    particles, bonds, info = _specimen_arrays(specimen_disc)
    pos = np.asarray(particles.pos, np.float64)
    rad = np.asarray(particles.radius, np.float64)
    valid = np.asarray(particles.valid, bool)
    if "radius" in info:
        big_r = float(info["radius"])
        centre = np.asarray(info.get("centre", (big_r, big_r)), np.float64)
    else:
        lo, hi = _extent(particles, 1)
        big_r = 0.5 * (hi - lo)
        centre = np.array([0.5 * sum(_extent(particles, 0)), 0.5 * (hi + lo)])
    half = np.deg2rad(float(flat_angle_deg)) / 2.0
    if not 0.0 <= half < np.pi / 4:
        raise InputError(f"flat_angle_deg must lie in [0, 90), got {flat_angle_deg!r}")
    y_flat = big_r * np.cos(half)
    keep = valid & (np.abs(pos[:, 1] - centre[1]) + rad <= y_flat)
    new_index = np.cumsum(keep) - 1
    parts = Particles(*[jnp.asarray(np.asarray(a)[keep]) for a in particles])
    bi, bj = np.asarray(bonds.i), np.asarray(bonds.j)
    bv = np.asarray(bonds.valid) & keep[bi] & keep[bj]
    nb = int(bv.sum())
    new_bonds = empty_bonds(2, nb, dtype=parts.pos.dtype)
    new_bonds = new_bonds._replace(i=jnp.asarray(new_index[bi[bv]], jnp.int32),
                                   j=jnp.asarray(new_index[bj[bv]], jnp.int32),
                                   valid=jnp.ones((nb,), bool))
    out_info = dict(info, radius=big_r, centre=tuple(float(c) for c in centre),
                    flat_angle_deg=float(flat_angle_deg))
    return parts, new_bonds, out_info
