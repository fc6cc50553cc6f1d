"""Energy tracker: kinetic and stored energies, work in and dissipation, step by
step, with a balance that closes on the leapfrog integrator.

Citations ("000 eq 2-15", "002 eq 5") refer to the documents listed in REFERENCES.md.

The step (:func:`jdem.integrate.physics_step`, 000 eq 2-15..2-17) takes forces
F_n from the positions x_n and the half-step velocities v_{n-1/2}, then
v_{n+1/2} = v_{n-1/2} + F_n dt / m and x_{n+1} = x_n + v_{n+1/2} dt.
:func:`energy_step` performs exactly that update (it calls ``physics_step``)
and, from the same state, evaluates each force family again on its own to
accumulate a :class:`Ledger`.  All energies are in J (2D: J per metre of
thickness); dissipations are positive when energy leaves the system.

The instant of the ledger
-------------------------
The ledger returned with the state after step n describes the instant t_n of
that step's forces (the positions x_n the step started from), not the instant
of the returned positions x_{n+1}: contact and bond histories in the state are
those of x_n (they are built from the increments v_{n-1/2} dt), and the
kinetic energy at t_n needs v_{n+1/2}.  Definitions at t_n:

* kinetic energy, the leapfrog's own:  K_n = sum 1/2 m v_{n-1/2} . v_{n+1/2}
  + 1/2 I w_{n-1/2} . w_{n+1/2}  (translational and rotational reported apart).
  It differs from 1/2 m v(t_n)^2 by O(dt^2); with it, K + 1/2 k x^2 of a linear
  spring is conserved exactly by the central-difference step.
* stored energies from the forces of step n (the state's histories at x_n):
  contact normal spring 1/2 F_n delta (linear; Hertz 2/5 F_n delta), tangential
  |F_s|^2 / (2 k_t) (pairs and walls together); bond normal F_n^2 / (2 K_n),
  shear |F_s|^2 / (2 K_s), bending |M_s|^2 / (2 K_b) with K_b = K_n I / A_c =
  E I / L and twisting M_n^2 / (2 K_t) with K_t = K_s J / A_c = G J / L
  (002 eq 2, 4; I and J of 002 eq 5).  Broken bonds are frictional contacts
  with no moments; their compression and shear springs are counted the same way.
* work of a force family over the interval [t_{n-1}, t_n]: the trapezoid
  1/2 (F_{n-1} + F_n) . v_{n-1/2} dt (and torques with w_{n-1/2}), which is
  exactly the displacement x_n - x_{n-1} the integrator made.  Step n
  contributes half of F_n . v_{n-1/2} dt to the interval that ends at t_n and
  holds the other half, F_n . v_{n+1/2} dt / 2, pending for the next interval
  (``Ledger.pending``).  Summed over a run this is F_n . (v_{n-1/2} +
  v_{n+1/2}) / 2 dt per step less the two end halves.

What closes exactly and what is O(dt^2)
---------------------------------------
* Kinetic theorem, exact up to round-off: for every free component
  m (v_{n+1/2} - v_{n-1/2}) = F_n dt, hence K_{n+1} - K_n = 1/2 (F_n +
  F_{n+1}) . v_{n+1/2} dt, the sum of the interval works of every family
  (contacts, bonds, walls, applied, gravity, boundary, damping).  Prescribed
  components (``fixed_vel`` / ``fixed_rot``) keep their velocity; the force on
  them goes to the support, whose work ``work_support`` is minus the work of
  the (undamped) force on those components plus the change of their kinetic
  energy (non-zero only when a boundary function sets their velocity).
  Because the kinetic energy is computed from the velocities and every work
  and damping term from its own force, the balance is a real check of the
  bookkeeping (drop a term, take the half-step kinetic energy 1/2 m
  v_{n-1/2}^2, forget the wall's velocity: it fails; see tests/test_energy.py).
* Each law against its stored energy, O(dt^2): the trapezoidal work of a linear
  spring equals the change of 1/2 k x^2 exactly in one dimension; the rotation
  of the contact normal, the Hertz law and the moving contact point make it
  second order in dt.  The local energy error of one step does not
  accumulate for an elastic system (it oscillates with the motion).
* Dissipation by its own force (exact, no definition): local and viscous
  damping (000 eq 3-19, 3-9), contact dashpots (000 eq 3-1; the part of the
  clamped normal force above the spring force) and bond dashpots, each
  -sum F_damp . v dt with the same trapezoid weighting.
* Dissipation defined per law as work minus the change of what the law stores
  (there is no other definition of them in an incremental elastic-plastic
  law): ``friction`` = work done on the contact springs (pairs and walls, the
  wall's own motion taken out) - change of the contact elastic energy;
  ``bond_inelastic`` = work done on the bond springs - change of the bond
  elastic energy (softening, breakage, moment loss of 002 ineq 11, slip of
  broken bonds).  They therefore carry that law's O(dt^2) error too (4e-8 of
  the energy in the elastic 3D bonded cluster of tests/test_energy.py, whose
  K + U holds to 4e-8; discs bouncing in a box under gravity at omega dt ~ 0.01
  hold K + U - work to 1e-4), and a Hertz tangential
  spring, whose k_t changes with F_n, is not a potential: its path dependence
  lands in ``friction``.  ``bond_break`` is part of ``bond_inelastic``, not an
  extra term: the elastic energy bonds held at the instant they broke, plus
  the moment energy of bonds that stopped carrying moments.
* Work of walls: the wall-contact force on the particles times the wall's
  velocity over the interval, -walls.force . v_wall (servo velocities
  included).  Work of external loads: ``ext_force`` / ``ext_torque`` and a
  boundary function's force (and torque) (``work_external``); gravity apart
  (``work_gravity``, no potential energy is booked).

Balance (:func:`balance`):
    residual = (K_n + U_n) - (K_0 + U_0) - (work in) + (dissipated)
with U the stored energies, K_0, U_0 those of the first tracked instant, the
work in = walls + external + gravity + support, and the dissipated = local +
viscous damping + contact dashpots + friction + bond dashpots + bond_inelastic;
``relative`` = |residual| / the largest of the terms.

Use: :func:`energy_step` (one step, neighbour list current, as
``physics_step``), :func:`step` (with the neighbour refresh, as
``integrate.step``), :func:`rollout` (``lax.scan``, the ledger per record),
:func:`run` (jitted; ``(state, history)``), :func:`balance`.  Costs about three
force evaluations a step (the step's own, the families apart, the families
without dashpots); meant for checks and studies, not production runs.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import bond as bond_mod
from jdem import contact, damping, integrate, neighbors, walls as walls_mod
from jdem.state import Config, Params, State
from jdem.validate import InputError

#: cumulative work and dissipation terms accumulated by the trapezoid of the module docstring
WORK_TERMS = ("work_walls", "work_external", "work_gravity", "work_support",
              "damping_local", "damping_viscous", "contact_dashpot", "contact_work",
              "bond_dashpot", "bond_work")
#: stored energies at the ledger's instant
STORED_TERMS = ("kinetic_translational", "kinetic_rotational", "contact_normal",
                "contact_tangential", "bond_normal", "bond_shear", "bond_bending",
                "bond_twisting")
#: work done on the particles from outside (J, positive in)
WORK_IN = ("work_walls", "work_external", "work_gravity", "work_support")
#: dissipated energy (J, positive out)
DISSIPATED = ("damping_local", "damping_viscous", "contact_dashpot", "friction",
              "bond_dashpot", "bond_inelastic")


class Work(NamedTuple):
    """One value per term of :data:`WORK_TERMS` [J]."""

    work_walls: jnp.ndarray
    work_external: jnp.ndarray
    work_gravity: jnp.ndarray
    work_support: jnp.ndarray
    damping_local: jnp.ndarray
    damping_viscous: jnp.ndarray
    contact_dashpot: jnp.ndarray
    contact_work: jnp.ndarray
    bond_dashpot: jnp.ndarray
    bond_work: jnp.ndarray


class Ledger(NamedTuple):
    """The energy ledger at the instant t_n of the last tracked step (see the
    module docstring); every field a () scalar, (B,) under ``vmap``.  Joules.

    stored at t_n:
      kinetic_translational, kinetic_rotational   K_n (leapfrog product form)
      contact_normal, contact_tangential          unbonded contacts, pairs and walls
      bond_normal, bond_shear, bond_bending, bond_twisting
    cumulative from the first tracked instant t_0 to t_n:
      work_walls, work_external, work_gravity, work_support   work in
      damping_local, damping_viscous, contact_dashpot, bond_dashpot  (own forces)
      friction, bond_inelastic                    (per law: work - change of storage)
      bond_break                                  (part of bond_inelastic)
      contact_work, bond_work                     work done on the contact / bond springs
    reference and bookkeeping:
      initial_kinetic, initial_stored, initial_contact, initial_bond   at t_0
      pending      :class:`Work`, the forward halves of the last step
      started      () bool, False before the first step
      step, time   the step number n and time t_n of the ledger's instant
    """

    kinetic_translational: jnp.ndarray
    kinetic_rotational: jnp.ndarray
    contact_normal: jnp.ndarray
    contact_tangential: jnp.ndarray
    bond_normal: jnp.ndarray
    bond_shear: jnp.ndarray
    bond_bending: jnp.ndarray
    bond_twisting: jnp.ndarray
    work_walls: jnp.ndarray
    work_external: jnp.ndarray
    work_gravity: jnp.ndarray
    work_support: jnp.ndarray
    damping_local: jnp.ndarray
    damping_viscous: jnp.ndarray
    contact_dashpot: jnp.ndarray
    contact_work: jnp.ndarray
    bond_dashpot: jnp.ndarray
    bond_work: jnp.ndarray
    friction: jnp.ndarray
    bond_inelastic: jnp.ndarray
    bond_break: jnp.ndarray
    initial_kinetic: jnp.ndarray
    initial_stored: jnp.ndarray
    initial_contact: jnp.ndarray
    initial_bond: jnp.ndarray
    pending: Work
    started: jnp.ndarray
    step: jnp.ndarray
    time: jnp.ndarray


#: the ledger fields recorded in a history (everything but the bookkeeping)
RECORDED = STORED_TERMS + WORK_TERMS + ("friction", "bond_inelastic", "bond_break",
                                        "initial_kinetic", "initial_stored", "step", "time")


def init(state: State) -> Ledger:
    """An empty ledger for ``state`` (one system; ``jax.vmap`` it for a batch)."""
    z = jnp.zeros((), state.time.dtype)
    scalars = {f: z for f in Ledger._fields if f not in ("pending", "started", "step")}
    return Ledger(**scalars, pending=Work(*([z] * len(Work._fields))),
                  started=jnp.zeros((), bool), step=jnp.zeros((), jnp.int32))


# ----------------------------------------------------------------------------- helpers
def _power(force, vel, mask):
    """sum over masked components of force * velocity (shapes (N, d) or (N,))."""
    return jnp.sum(jnp.where(mask, force * vel, 0.0))


def _mask(valid, like):
    return jnp.broadcast_to(valid.reshape(valid.shape + (1,) * (like.ndim - 1)), like.shape)


def _inv(k, ok):
    """1 / k where ``ok`` and k > 0, else 0."""
    good = ok & (k > 0)
    return jnp.where(good, 1.0 / jnp.where(good, k, 1.0), 0.0)


def _sq(v):
    return v * v if v.ndim == 1 else jnp.sum(v * v, axis=-1)


def contact_energies(contacts, walls, particles, params: Params, config: Config):
    """Elastic energy [J] of the unbonded contacts (pairs and walls) from the
    given histories and positions: ``(normal, tangential)``.  Normal: 1/2 F delta
    (linear), 2/5 F delta (Hertz, the integral of H delta^(3/2)); tangential
    |F_s|^2 / (2 k_t)."""
    model = config.contact_model
    frac = 0.5 if model == "linear" else 0.4

    def spring(fn, overlap, shear, kt, touching):
        normal = jnp.sum(jnp.where(touching, frac * fn * overlap, 0.0))
        tang = jnp.sum(0.5 * _sq(shear) * _inv(kt, touching))
        return normal, tang

    g, fn, _, kt = contact.pair_law(contacts, particles, params, config)
    kt = jnp.broadcast_to(kt, g.overlap.shape)
    normal, tang = spring(fn, g.overlap, contacts.shear, kt, g.touching)
    if walls.point.shape[0]:
        ov, touching, fnw, _, ktw = walls_mod.wall_law(walls, particles, params, config)
        ktw = jnp.broadcast_to(ktw, ov.shape)
        n_w, t_w = spring(fnw, ov, walls.shear, ktw, touching)
        normal, tang = normal + n_w, tang + t_w
    return normal, tang


def bond_energies(bonds, particles, params: Params, dim: int, section: str = "circular"):
    """Per-bond elastic energies [J], each (B,): ``(normal, shear, bending,
    twisting)`` = F_n^2 / 2K_n, |F_s|^2 / 2K_s, |M_s|^2 / 2K_b, M_n^2 / 2K_t with
    K_b = K_n I / A_c, K_t = K_s J / A_c (002 eq 4, 5; ``section`` the 2D bending
    section, ``Config.bond_section``); zero for invalid rows."""
    geo = bond_mod.bond_geometry(bonds, particles, params, dim, section)
    ok = bonds.valid
    area = jnp.where(geo.area > 0, geo.area, 1.0)
    normal = 0.5 * bonds.normal_force ** 2 * _inv(geo.kn, ok)
    shear = 0.5 * _sq(bonds.shear_force) * _inv(geo.ks, ok)
    bending = 0.5 * _sq(bonds.bend) * _inv(geo.kn * geo.I / area, ok)
    twisting = 0.5 * bonds.twist ** 2 * _inv(geo.ks * geo.J / area, ok)
    return normal, shear, bending, twisting


def _family_forces(state: State, params: Params, config: Config):
    """The step's forces family by family, from the state the step starts from
    (after the boundary function): contacts, bonds, walls, each with and without
    its dashpots (``Params.contact_damping`` / ``bond_damping`` = 0 leaves the
    histories unchanged, so the difference is the dashpot force)."""
    p = state.particles
    zero = jnp.zeros_like(params.contact_damping)
    still = params._replace(contact_damping=zero, bond_damping=jnp.zeros_like(params.bond_damping))
    contacts, fc, tc, _ = contact.contact_forces(state.contacts, p, params, config)
    _, fc0, tc0, _ = contact.contact_forces(state.contacts, p, still, config)
    out = dict(contacts=contacts, fc=fc, tc=tc, fc0=fc0, tc0=tc0)
    if state.bonds.i.shape[0] > 0:
        bonds, fb, tb = bond_mod.bond_forces(state.bonds, p, params, config.dim, state.step,
                                             config.bond_section)
        _, fb0, tb0 = bond_mod.bond_forces(state.bonds, p, still, config.dim, state.step,
                                           config.bond_section)
    else:
        bonds, fb, tb = state.bonds, None, None
        fb0, tb0 = None, None
    out.update(bonds=bonds, fb=fb, tb=tb, fb0=fb0, tb0=tb0)
    walls, fw, tw, _ = walls_mod.wall_forces(state.walls, p, params, config)
    walls0, fw0, tw0, _ = walls_mod.wall_forces(state.walls, p, still, config)
    out.update(walls=walls, fw=fw, tw=tw, fw0=fw0, tw0=tw0, wall_force0=walls0.force)
    return out


# ----------------------------------------------------------------------------- the step
def energy_step(state: State, params: Params, config: Config, ledger: Ledger,
                boundary=None):
    """One step, exactly :func:`jdem.integrate.physics_step` (neighbour list
    current; ``boundary = (fn, data)`` as there), and the ledger advanced to the
    instant of this step's forces.  Returns ``(state, ledger)``."""
    new_state = integrate.physics_step(state, params, config, boundary)
    sb, extra_f, extra_t = state, None, None
    if boundary is not None:
        fn, data = boundary
        sb, *extra = fn(state, params, data)
        extra_f = extra[0] if extra else None
        extra_t = extra[1] if len(extra) > 1 else None
    p = sb.particles
    fam = _family_forces(sb, params, config)
    # the undamped total, summed in the order of integrate._forces
    f, t = fam["fc"], fam["tc"]
    if fam["fb"] is not None:
        f, t = f + fam["fb"], t + fam["tb"]
    gravity = p.gravity_mass[:, None] * params.gravity
    f = f + fam["fw"] + p.ext_force + gravity
    t = t + fam["tw"] + p.ext_torque
    ext_f, ext_t = p.ext_force, p.ext_torque
    if extra_f is not None:
        f, ext_f = f + extra_f, ext_f + extra_f
    if extra_t is not None:
        t, ext_t = t + extra_t, ext_t + extra_t
    # damping forces (000 eq 3-9, 3-19) as damping.apply takes them
    fv = damping.viscous_damping(f, p.vel, p.mass, params.viscous_damping)
    tv = damping.viscous_damping(t, p.angvel, p.inertia, params.viscous_damping)
    fl = damping.local_damping(fv, p.vel, params.local_damping)
    tl = damping.local_damping(tv, p.angvel, params.local_damping)
    f_visc, t_visc, f_loc, t_loc = fv - f, tv - t, fl - fv, tl - tv

    valid_v, valid_w = _mask(p.valid, p.vel), _mask(p.valid, p.angvel)
    free_v, free_w = valid_v & ~p.fixed_vel, valid_w & ~p.fixed_rot
    held_v, held_w = valid_v & p.fixed_vel, valid_w & p.fixed_rot
    walls_new = fam["walls"]
    wall_force = jnp.where(walls_new.valid[:, None], walls_new.force, 0.0)  # on the walls
    wall_force0 = jnp.where(walls_new.valid[:, None], fam["wall_force0"], 0.0)
    zero_f, zero_t = jnp.zeros_like(f), jnp.zeros_like(t)
    fb, tb = (fam["fb"], fam["tb"]) if fam["fb"] is not None else (zero_f, zero_t)
    fb0, tb0 = (fam["fb0"], fam["tb0"]) if fam["fb0"] is not None else (zero_f, zero_t)

    def powers(v, w, v_wall):
        """The power of every term of WORK_TERMS at velocities (v, w, v_wall) [W]."""
        P = lambda ff, tt, mv, mw: _power(ff, v, mv) + _power(tt, w, mw)  # noqa: E731
        walls_pw = jnp.sum(-wall_force * v_wall)           # work of the walls on the particles
        walls_pw0 = jnp.sum(-wall_force0 * v_wall)
        return Work(
            work_walls=walls_pw,
            work_external=P(ext_f, ext_t, valid_v, valid_w),
            work_gravity=_power(gravity, v, valid_v),
            work_support=-P(f, t, held_v, held_w),
            damping_local=-P(f_loc, t_loc, free_v, free_w),
            damping_viscous=-P(f_visc, t_visc, free_v, free_w),
            contact_dashpot=(-P(fam["fc"] - fam["fc0"], fam["tc"] - fam["tc0"], valid_v, valid_w)
                             - P(fam["fw"] - fam["fw0"], fam["tw"] - fam["tw0"], valid_v, valid_w)
                             + (walls_pw - walls_pw0)),
            contact_work=(-P(fam["fc0"], fam["tc0"], valid_v, valid_w)
                          - P(fam["fw0"], fam["tw0"], valid_v, valid_w) + walls_pw0),
            bond_dashpot=-P(fb - fb0, tb - tb0, valid_v, valid_w),
            bond_work=-P(fb0, tb0, valid_v, valid_w))

    dt = params.dt
    q = new_state.particles
    v_m, w_m = state.particles.vel, state.particles.angvel     # v_{n-1/2} (before any boundary)
    v_p, w_p = q.vel, q.angvel                                  # v_{n+1/2}
    m = _mask(p.mass, p.vel) * jnp.ones_like(p.vel)
    inertia = _mask(p.inertia, p.angvel) * jnp.ones_like(p.angvel)
    # kinetic energy change of the held components (a boundary function may set
    # their velocity), split like the work: back half 1/2 m v- (v+ - v-), forward
    # half 1/2 m v+ (v+ - v-)
    held_ke = lambda a: (_power(0.5 * m * (v_p - v_m), a[0], held_v)  # noqa: E731
                         + _power(0.5 * inertia * (w_p - w_m), a[1], held_w))
    half = lambda wk: Work(*[0.5 * dt * x for x in wk])  # noqa: E731
    back = half(powers(v_m, w_m, state.walls.vel))
    fwd = half(powers(v_p, w_p, walls_new.vel))
    back = back._replace(work_support=back.work_support + held_ke((v_m, w_m)))
    fwd = fwd._replace(work_support=fwd.work_support + held_ke((v_p, w_p)))

    # stored energies at t_n
    ke_t = _power(0.5 * m * v_m, v_p, valid_v)
    ke_r = _power(0.5 * inertia * w_m, w_p, valid_w)
    c_n, c_t = contact_energies(fam["contacts"], walls_new, p, params, config)
    bonds_new = fam["bonds"]
    if bonds_new.i.shape[0] > 0:
        parts = bond_energies(bonds_new, p, params, config.dim, config.bond_section)
        b_n, b_s, b_b, b_t = [jnp.sum(x) for x in parts]
        old = state.bonds
        new_break = bonds_new.valid & bonds_new.broken & ~old.broken
        new_lost = bonds_new.valid & bonds_new.moment_lost & ~old.moment_lost & ~new_break
        _, _, old_b, old_t = bond_energies(old, p, params, config.dim, config.bond_section)
        released = (jnp.sum(jnp.where(new_break, parts[0] + parts[1] + parts[2] + parts[3], 0.0))
                    + jnp.sum(jnp.where(new_lost, old_b + old_t, 0.0)))
    else:
        b_n = b_s = b_b = b_t = released = jnp.zeros((), f.dtype)
    u_contact = c_n + c_t
    u_bond = b_n + b_s + b_b + b_t

    first = ~ledger.started
    pick = lambda new, old: jnp.where(first, new, old)  # noqa: E731
    cum = Work(*[jnp.where(first, 0.0, c + pe + b) for c, pe, b in
                 zip(Work(*[getattr(ledger, k) for k in Work._fields]), ledger.pending, back)])
    init_contact = pick(u_contact, ledger.initial_contact)
    init_bond = pick(u_bond, ledger.initial_bond)
    new = ledger._replace(
        kinetic_translational=ke_t, kinetic_rotational=ke_r, contact_normal=c_n,
        contact_tangential=c_t, bond_normal=b_n, bond_shear=b_s, bond_bending=b_b,
        bond_twisting=b_t, **cum._asdict(),
        friction=cum.contact_work - (u_contact - init_contact),
        bond_inelastic=cum.bond_work - (u_bond - init_bond),
        bond_break=jnp.where(first, 0.0, ledger.bond_break + released),
        initial_kinetic=pick(ke_t + ke_r, ledger.initial_kinetic),
        initial_stored=pick(u_contact + u_bond, ledger.initial_stored),
        initial_contact=init_contact, initial_bond=init_bond,
        pending=fwd, started=jnp.ones((), bool), step=state.step, time=state.time)
    return new_state, new


def step(state: State, params: Params, config: Config, ledger: Ledger, boundary=None):
    """:func:`energy_step` after the neighbour refresh, as :func:`jdem.integrate.step`."""
    return energy_step(integrate.refresh_neighbors(state, config), params, config, ledger,
                       boundary)


# ----------------------------------------------------------------------------- runs
def observe(ledger: Ledger) -> dict:
    """The recorded fields of a ledger (:data:`RECORDED`) as a dict."""
    return {k: getattr(ledger, k) for k in RECORDED}


def rollout(state: State, params: Params, config: Config, n_records: int, record_every: int,
            ledger: Ledger | None = None, boundary=None):
    """``n_records * record_every`` tracked steps (``lax.scan``, one system;
    ``jax.vmap`` it for a batch).  Returns ``(state, ledger, history)``; the
    history holds :func:`observe` of the ledger after every ``record_every``
    steps, stacked along axis 0.  The neighbour list must be large enough
    (:func:`run` checks it)."""
    ledger = init(state) if ledger is None else ledger

    def one(carry, _):
        s, led = carry
        return step(s, params, config, led, boundary), None

    def block(carry, _):
        carry, _ = jax.lax.scan(one, carry, None, length=record_every)
        return carry, observe(carry[1])

    (state, ledger), hist = jax.lax.scan(block, (state, ledger), None, length=n_records)
    return state, ledger, hist


@functools.lru_cache(maxsize=8)
def _compiled(config, n_records, record_every, boundary_fn, batched):
    def go(state, params, ledger, data):
        bnd = None if boundary_fn is None else (boundary_fn, data)
        return rollout(state, params, config, n_records, record_every, ledger, bnd)

    if batched:
        go = jax.vmap(go, in_axes=(0, 0, 0, 0 if boundary_fn is not None else None))
    return jax.jit(go)


def run(state: State, params: Params, config: Config, n_steps: int, record_every: int, *,
        ledger: Ledger | None = None, boundary=None, batched=False, return_ledger=False):
    """Run ``n_steps`` tracked steps in one jitted call; returns ``(state,
    history)``, the history a dict of NumPy arrays (n_records,) of the
    :data:`RECORDED` ledger fields (batched: (B, n_records)), or ``(state,
    history, ledger)`` with ``return_ledger`` (to go on from there with
    ``ledger=``).  ``boundary = (fn, data)`` as in
    :func:`jdem.integrate.physics_step` (``fn`` module-level, so that the
    compiled program is reused).  Raises ``RuntimeError`` when the neighbour
    list overflowed or the divergence guard tripped (re-allocate with
    :func:`jdem.neighbors.reallocate`, or use a smaller step)."""
    if n_steps % record_every:
        raise ValueError(f"n_steps = {n_steps} must be a multiple of record_every = {record_every}")
    if ledger is None:
        ledger = jax.vmap(init)(state) if batched else init(state)
    fn, data = boundary if boundary is not None else (None, None)
    new_state, ledger, hist = _compiled(config, n_steps // record_every, record_every, fn,
                                        batched)(state, params, ledger, data)
    over = jax.vmap(neighbors.overflowed, in_axes=(0, None))(new_state.contacts, config) \
        if batched else neighbors.overflowed(new_state.contacts, config)
    if bool(np.any(np.asarray(over))):
        raise RuntimeError("energy.run: the neighbour list overflowed; re-allocate it "
                           "(jdem.neighbors.reallocate) and run again")
    if bool(np.any(np.asarray(new_state.first_bad_step) >= 0)):
        raise RuntimeError(f"energy.run: the divergence guard tripped at step "
                           f"{np.asarray(new_state.first_bad_step)}")
    hist = {k: np.asarray(v) for k, v in hist.items()}   # batched: (B, n_records) already
    return (new_state, hist, ledger) if return_ledger else (new_state, hist)


def lab_run(setup, params: Params | None = None):
    """The ledger of a whole lab test (a :class:`jdem.lab.Setup`, unbatched):
    the same record block as :func:`jdem.lab.curve` / :func:`jdem.lab.run` (the
    record's loading, then ``record_every`` steps with the test's boundary), with
    every step tracked.  One jitted call; returns ``(state, history)`` as
    :func:`run` does (the ledger per record)."""
    if setup.plan.batched:
        raise InputError("energy.lab_run takes an unbatched set-up (one member)")
    params = setup.params if params is None else params
    state, hist = _compiled_lab(setup.plan)(setup.state, params, setup.frame)
    if bool(neighbors.overflowed(state.contacts, setup.plan.config)):
        raise RuntimeError("energy.lab_run: the neighbour list overflowed; grow it "
                           "(jdem.lab.grow) and run again")
    if int(state.first_bad_step) >= 0:
        raise RuntimeError(f"energy.lab_run: the divergence guard tripped at step "
                           f"{int(state.first_bad_step)}")
    return state, {k: np.asarray(v) for k, v in hist.items()}


@functools.lru_cache(maxsize=4)
def _compiled_lab(plan):
    test = plan.test

    def go(state, params, frame):
        def block(carry, k):
            s, led = carry
            s = test.load(s, k, frame, plan)
            s, led, _ = rollout(s, params, plan.config, 1, plan.record_every, led,
                                (test.boundary, frame))
            return (s, led), observe(led)

        (state, _), hist = jax.lax.scan(block, (state, init(state)),
                                        jnp.arange(plan.n_records))
        return state, hist

    return jax.jit(go)


# ----------------------------------------------------------------------------- balance
def balance(ledger) -> dict:
    """The energy balance of a :class:`Ledger` or of a history dict from
    :func:`run` / :func:`rollout` (arrays along the records).

    Returns a dict of NumPy values: ``kinetic``, ``stored`` (contacts + bonds),
    ``work_in`` (walls + external + gravity + support), ``dissipated`` (damping,
    dashpots, friction, bond_inelastic), ``residual`` = (kinetic + stored) -
    (initial kinetic + stored) - work_in + dissipated, ``largest`` the largest
    magnitude among the terms (the energies now and at the start, each work and
    each dissipation), and ``relative`` = |residual| / largest; plus every
    dissipation and work term by name."""
    get = (lambda k: np.asarray(ledger[k])) if isinstance(ledger, dict) \
        else (lambda k: np.asarray(getattr(ledger, k)))
    kinetic = get("kinetic_translational") + get("kinetic_rotational")
    stored = sum(get(k) for k in STORED_TERMS[2:])
    k0, u0 = get("initial_kinetic"), get("initial_stored")
    work_in = sum(get(k) for k in WORK_IN)
    dissipated = sum(get(k) for k in DISSIPATED)
    residual = kinetic + stored - (k0 + u0) - work_in + dissipated
    terms = [kinetic, stored, k0, u0] + [get(k) for k in WORK_IN + DISSIPATED]
    largest = np.max(np.abs(np.stack(terms)), axis=0)
    relative = np.abs(residual) / np.where(largest > 0, largest, 1.0)
    out = dict(kinetic=kinetic, stored=stored, work_in=work_in, dissipated=dissipated,
               residual=residual, largest=largest, relative=relative)
    out.update({k: get(k) for k in WORK_IN + DISSIPATED + ("bond_break",)})
    return out
