"""Differentiable laboratory tests: a stress-strain curve as a pure function of ``Params``.

:func:`ucs_model` puts one specimen (or an ensemble of packings of the same
statistics) between platens; :func:`simulate_curve` runs the uniaxial test and
returns ``(strain, stress)``, and works under ``jax.jit``, ``jax.grad`` and
``jax.vmap``.  :mod:`jdem.calibrate` builds losses and the optimiser on it.

The rollout is a ``lax.scan`` over records; every record block (``record_every``
steps) is wrapped in ``jax.checkpoint``, so reverse-mode memory grows with the
number of records, not of steps.  The top platen speeds up linearly over the
first ``ramp_records`` records (half a cosine: a sudden start rings the specimen's lowest
mode, which only slowly decays under the damping below); the strain is read
from the platen positions, which do not depend on the parameters.

Damping and the meaning of gradients
------------------------------------
The seed's local non-viscous damping (000 eq 3-19, F - alpha |F| sign(v)) is
not usable under ``jax.grad``: its tangent dynamics multiplies every force by
(1 +- alpha) as the signs of F and v switch, a parametric excitation that makes
reverse-mode gradients grow exponentially with the number of steps (measured on
a 164-disc UCS test: d sigma / d E off by 1e5 after 500 steps, 1e11 after
1,000), while the forward run is stable; the curve itself is rough in the
parameters for the same reason (finite differences change sign between step
sizes).  The differentiable tests therefore use :func:`quasi_static_damping`:
dashpots on the relative motion of bonds and contacts (``bond_damping``,
``contact_damping``, a fraction of critical) for the particle-scale modes and a
light mass-proportional damping tuned to the specimen's lowest axial mode.  Both
are smooth; with the velocity ramp the curve matches finite differences to
<1 % up to the peak (tests/test_calibrate.py).

Loading rate
------------
The default platen step (5 nm per step; with the time step of the 4 mm x 8 mm
test specimens, 1.27e-8 s, a strain rate of ~50 /s) suits fitting curves made
with the same set-up, but the curve depends on it: over 8 packings of ~100 and
~330 discs the peak stress at 1.25 nm per step (a 40-record ramp) is 21-44 % and
15-35 % lower than at 5 nm, and at 0.625 nm (~100 discs) a further 7-19 % lower:
the peak is not yet independent of the rate there (``python
experiments/packing_scatter.py``, results in experiments/results/packing_scatter/).
The pre-peak slope over 20-40 % of the peak changes by at most 3 % between 1.25
and 0.625 nm for 7 of the 8 packings (9 % for the eighth); at 5 nm it is still
shaped by the waves of the platen's start (7.7-15.5 GPa against 8.7-21.9 GPa at
1.25 nm).  To calibrate against a laboratory curve, use a slower
``platen_step`` and longer ``ramp_records``, and check how far the fitted values
move when ``platen_step`` is halved again.

Non-smooth events of the bond model (002 eq 6-11) are kept exact:

* yield (tension cut-off, Mohr-Coulomb) is a return mapping, piecewise smooth;
  its gradient is the one of the active branch;
* softening (002 eq 7, 9) is linear in the plastic strain, so the gradient with
  respect to eps_lim / gamma_lim flows through every yielding bond;
* breakage happens when T or c has softened to zero, so the bond force is
  continuous through it; the switch itself (and the loss of moments, ineq 11,
  and the making or losing of contacts) is a discrete event whose timing carries
  no gradient.  The gradient is the pathwise derivative with the sequence of
  events held fixed.  Past the peak, where the events cascade, a small change
  of a parameter can reorder them: finite differences there depend on their step
  and the pathwise gradient describes the smooth part of the response only.
  Gradients stay finite through breakage (tests).
"""
from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import neighbors, timestep
from jdem.simulate import make_config, rollout
from jdem.state import Config, Params, State, empty_bonds
from jdem.validate import InputError


class CurveData(NamedTuple):
    """The traced part of a curve model (leading axis B for an ensemble).

    state     initial :class:`jdem.state.State` (platens touching the specimen)
    h0        (B,) or () initial platen distance [m]
    area      (B,) or () platen area [m^2] (2D: width x 1 m)
    step      (B, W, d) or (W, d) wall displacement per time step at full speed [m]
              (the velocity is ``step / params.dt``)
    """

    state: State
    h0: jnp.ndarray
    area: jnp.ndarray
    step: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class CurveSpec:
    """The static part: ``config``, ``n_records`` records of ``record_every``
    steps, platen ramp over ``ramp_records`` records, ``ensemble`` (leading
    member axis on the data)."""

    config: Config
    n_records: int
    record_every: int
    ramp_records: int
    ensemble: bool


@jax.tree_util.register_pytree_node_class
class CurveModel:
    """A differentiable UCS test: ``data`` (pytree leaves) and ``spec`` (static,
    hashable).  A pytree itself, so it may be passed to jitted functions."""

    def __init__(self, data: CurveData, spec: CurveSpec):
        self.data = data
        self.spec = spec

    def tree_flatten(self):
        return (self.data,), self.spec

    @classmethod
    def tree_unflatten(cls, spec, children):
        return cls(children[0], spec)

    @property
    def n_members(self) -> int:
        return int(self.data.h0.shape[0]) if self.spec.ensemble else 1


def quasi_static_damping(params: Params, height, density=2500.0, *, bond_damping=0.3,
                         low_mode_damping=0.3) -> Params:
    """Smooth damping for differentiable quasi-static tests (module docstring).

    Sets ``local_damping = 0``, ``bond_damping = contact_damping = bond_damping``
    (fraction of critical of the dashpots on bonds and contacts) and a
    mass-proportional ``viscous_damping = 2 xi omega_1`` with xi =
    ``low_mode_damping`` and omega_1 = pi c / (2 H) the lowest axial mode of a bar
    of height ``height`` [m] fixed at one end, c = sqrt(E / rho).
    """
    e_mod = float(np.max(np.asarray(params.bond_youngs)))
    omega1 = np.pi * np.sqrt(e_mod / float(density)) / (2.0 * float(height))
    like = lambda v: jnp.full(np.shape(params.local_damping), v,
                              jnp.asarray(params.local_damping).dtype)
    return params._replace(local_damping=like(0.0), bond_damping=like(bond_damping),
                           contact_damping=like(bond_damping),
                           viscous_damping=like(2.0 * low_mode_damping * omega1))


# ----------------------------------------------------------------------------- set-up
def _pad_particles(p, n):
    extra = n - p.pos.shape[0]
    if extra == 0:
        return p
    fill = dict(mass=1.0, inertia=1.0)
    return p._replace(**{name: jnp.concatenate(
        [a, jnp.full((extra,) + a.shape[1:], fill.get(name, 0), a.dtype)])
        for name, a in p._asdict().items()})


def _pad_bonds(b, n, dim):
    extra = n - b.i.shape[0]
    if extra == 0:
        return b
    pad = empty_bonds(dim, extra, b.normal_force.dtype)
    return jax.tree_util.tree_map(lambda a, e: jnp.concatenate([a, e]), b, pad)


def _pad_walls(w, n):
    extra = n - w.shear.shape[1]
    if extra == 0:
        return w
    z = jnp.zeros((w.shear.shape[0], extra, w.shear.shape[2]), w.shear.dtype)
    return w._replace(shear=jnp.concatenate([w.shear, z], axis=1))


def _stack_members(states, dim):
    """Pad states of different specimens to common capacities and stack them;
    returns (state (B, ...), config) with one search grid covering all."""
    n = max(s.particles.pos.shape[0] for s in states)
    nb = max(s.bonds.i.shape[0] for s in states)
    parts = [_pad_particles(s.particles, n) for s in states]
    bonds = [_pad_bonds(s.bonds, nb, dim) for s in states]
    walls = [_pad_walls(s.walls, n) for s in states]
    union = parts[0]._replace(
        pos=jnp.concatenate([p.pos for p in parts]),
        radius=jnp.concatenate([p.radius for p in parts]),
        valid=jnp.concatenate([p.valid for p in parts]))
    config = make_config(union)
    built = []
    for p, b in zip(parts, bonds):
        c, config = neighbors.allocate(p, config, b)
        built.append((p, b, c))
    cap = max(c.i.shape[0] for _, _, c in built)
    members = []
    for (p, b, c), w, s in zip(built, walls, states):
        c = neighbors.build(neighbors._resize(c, cap), p, config, b)
        members.append(s._replace(particles=p, bonds=b, contacts=c, walls=w))
    state = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *members)
    return state, config


def _stiffest(params: Params, factor: float) -> Params:
    """Params with bond and rock-contact stiffness scaled by ``factor`` (for dt)."""
    return params._replace(bond_youngs=params.bond_youngs * factor,
                           kn=params.kn.at[0].multiply(factor),
                           ks=params.ks.at[0].multiply(factor))


def ucs_model(specimens, params: Params, *, platen_step=5e-9, max_strain=3e-3,
              record_every=50, ramp_records=8, max_stiffness=2.0, bond_damping=0.3,
              low_mode_damping=0.3, density=2500.0):
    """A differentiable uniaxial compression test (002 §2 set-up, smooth damping).

    specimens      one :class:`jdem.specimen.Specimen` (or ``(particles, bonds)``),
                   or a list of them: an ensemble, run as one vmapped call
    params         unbatched ``Params`` with two materials (rock 0, platen 1), e.g.
                   :func:`jdem.labtests.rock_params`; its damping is replaced by
                   :func:`quasi_static_damping`
    platen_step    top platen displacement per step [m] at full speed
    max_strain     axial strain reached at the end (the ramp included)
    record_every   steps per record (one point of the curve)
    ramp_records   records over which the platen speeds up (half a cosine)
    max_stiffness  the time step is the recommended one (000 eq 3-26) for bond and
                   contact stiffness ``max_stiffness`` times those of ``params``,
                   so that calibration may raise E that far
    Returns ``(model, params)``: the :class:`CurveModel` and ``params`` with the
    damping and the time step in force.
    """
    from jdem import labtests

    single = hasattr(specimens, "particles") or (isinstance(specimens, tuple)
                                                 and not hasattr(specimens[0], "particles")
                                                 and len(specimens) in (2, 3))
    members = [specimens] if single else list(specimens)
    if not members:
        raise InputError("specimens is empty")
    if jnp.zeros(()).dtype != jnp.float64:
        raise InputError("ucs_model needs float64: call jax.config.update('jax_enable_x64', "
                         "True) first (platen steps of nanometres are below float32 "
                         "resolution of the positions)")
    if np.ndim(params.dt) != 0:
        raise InputError("ucs_model needs unbatched params (one member); batch with vmap")
    if not (np.isfinite(platen_step) and platen_step > 0):
        raise InputError(f"platen_step must be > 0, got {platen_step!r}")
    if not (np.isfinite(max_strain) and max_strain > 0):
        raise InputError(f"max_strain must be > 0, got {max_strain!r}")
    if not max_stiffness >= 1.0:
        raise InputError(f"max_stiffness must be >= 1, got {max_stiffness!r}")
    setups = [labtests.platen_setup(m, params, platen_step=platen_step) for m in members]
    heights = [su.frame.h0 for su in setups]
    stiff = _stiffest(setups[0].params, max_stiffness)
    dt = min(float(su.params.dt) for su in setups)   # at the given stiffness
    dt = dt / np.sqrt(max_stiffness)                   # dt ~ 1 / sqrt(k)
    params = quasi_static_damping(setups[0].params, float(np.mean(heights)), density,
                                  bond_damping=bond_damping, low_mode_damping=low_mode_damping)
    params = params._replace(dt=jnp.asarray(dt, jnp.asarray(params.dt).dtype))
    for su in setups:
        timestep.check_timestep(su.state, stiff._replace(dt=params.dt), su.config)
    dim = setups[0].frame.dim
    vel = []   # top platen displacement per step
    for su in setups:
        v = np.zeros(np.shape(su.state.walls.vel))
        v[1, dim - 1] = -platen_step
        vel.append(v)
    full_records = max_strain * float(np.min(heights)) / platen_step / record_every
    n_records = int(np.ceil(full_records + 0.5 * ramp_records))
    area = np.array([su.frame.area for su in setups])
    h0 = np.array(heights)
    if single:
        su = setups[0]
        data = CurveData(su.state, jnp.asarray(h0[0]), jnp.asarray(area[0]), jnp.asarray(vel[0]))
        config = su.config
    else:
        state, config = _stack_members([su.state for su in setups], dim)
        data = CurveData(state, jnp.asarray(h0), jnp.asarray(area), jnp.asarray(np.stack(vel)))
    spec = CurveSpec(config=config, n_records=n_records, record_every=int(record_every),
                     ramp_records=int(ramp_records), ensemble=not single)
    return CurveModel(data, spec), params


# ----------------------------------------------------------------------------- the curve
def _platen_observe(state, params, config):
    w = state.walls
    return dict(bottom=w.point[0, config.dim - 1], top=w.point[1, config.dim - 1],
                force=-jnp.sum(w.force[1] * w.normal[1]),
                fracture_degree=jnp.sum(state.bonds.valid & state.bonds.broken)
                / jnp.maximum(jnp.sum(state.bonds.valid), 1))


@functools.partial(jax.jit, static_argnames=("spec",))
def _curve(params: Params, data: CurveData, spec: CurveSpec):
    batch = spec.ensemble
    if batch and jnp.ndim(params.dt) == 0:   # one parameter set for every member
        nb = data.h0.shape[0]
        params = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (nb,) + jnp.shape(a)),
                                        params)
    ramp = max(spec.ramp_records, 1)

    def block(s, k):
        x = jnp.minimum(1.0, (k + 0.5) / ramp)
        frac = (0.5 - 0.5 * jnp.cos(jnp.pi * x)).astype(data.step.dtype)   # smooth start
        dt = params.dt[..., None, None] if batch else params.dt
        s = s._replace(walls=s.walls._replace(vel=data.step / dt * frac))
        s, rec = rollout(s, params, spec.config, 1, spec.record_every, _platen_observe,
                         batched=batch, checkpoint=False)
        return s, jax.tree_util.tree_map(lambda a: a[0], rec)

    final, rec = jax.lax.scan(jax.checkpoint(block), data.state, jnp.arange(spec.n_records))
    rec = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), rec)   # records last
    h0 = data.h0[..., None] if batch else data.h0
    area = data.area[..., None] if batch else data.area
    strain = (h0 - (rec["top"] - rec["bottom"])) / h0
    stress = rec["force"] / area
    over = neighbors.overflowed(final.contacts, spec.config)
    return dict(strain=jax.lax.stop_gradient(strain), stress=stress,
                fracture_degree=rec["fracture_degree"], overflowed=over,
                first_bad_step=jnp.max(final.first_bad_step))


def simulate_curve(params: Params, model: CurveModel) -> dict:
    """Run the test; a dict of arrays, records on the last axis (ensemble: a
    leading member axis):

    strain           (..., R) axial strain (h0 - H) / h0 from the platen positions
    stress           (..., R) compressive force on the top platen / area [Pa]
    fracture_degree  (..., R) broken / total bonds (002 §2.3)
    overflowed       () the neighbour list overflowed: the curve is wrong; grow it
                     with :func:`grow` and run again
    first_bad_step   () first non-finite step (-1 if none)

    Pure: use it inside ``jax.grad`` / ``jax.vmap``.  With an ensemble model,
    ``params`` may carry the member axis (one parameter set per member, e.g. a
    sweep over copies of one specimen: ``ucs_model([spec] * 64, ...)``); that
    refreshes the neighbour lists of all members in one ``lax.cond``, which a
    ``jax.vmap`` of the single-specimen curve cannot (under ``vmap`` the
    rebuild would run at every step).
    """
    return _curve(params, model.data, model.spec)


def grow(model: CurveModel) -> CurveModel:
    """The model with a neighbour list twice as long (after an overflow)."""
    c = model.data.state.contacts
    cap = 2 * c.i.shape[-1]
    config = model.spec.config.replace(max_per_cell=model.spec.config.max_per_cell + 4)
    resize = lambda cc: neighbors._resize(cc, cap)
    contacts = jax.vmap(resize)(c) if model.spec.ensemble else resize(c)
    state = model.data.state._replace(contacts=contacts)
    return CurveModel(model.data._replace(state=state),
                      dataclasses.replace(model.spec, config=config))


def checked_curve(params: Params, model: CurveModel, *, max_grow=4):
    """:func:`simulate_curve` on the host, growing the neighbour list on overflow
    and raising on divergence.  Returns ``(curve as NumPy, model)``."""
    for _ in range(max_grow + 1):
        out = simulate_curve(params, model)
        if not bool(out["overflowed"]):
            break
        model = grow(model)
    else:
        raise RuntimeError("neighbour list still overflows after growing it "
                           f"{max_grow} times")
    if int(out["first_bad_step"]) >= 0:
        raise RuntimeError(f"the test diverged at step {int(out['first_bad_step'])} "
                           "(time step too large for these parameters?)")
    return {k: np.asarray(v) for k, v in out.items()}, model
