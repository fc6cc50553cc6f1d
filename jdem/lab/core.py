"""One definition of a laboratory test, two ways to run it.

A :class:`LabTest` is a small NamedTuple of functions (in the spirit of optax's
``GradientTransformation``): ``setup`` builds a :class:`Setup` on the host
(specimen between platens or grips, time step, damping, loading schedule), and
the traced functions ``load`` (the loading of record k), ``boundary`` (forces
from outside the particle system, every step), ``observe`` (what one record
holds) and ``derive`` (the history from the records) define the test.  Both
runners use the same record block, built from those functions:

* :func:`curve` -- a pure function of ``Params`` (and of the specimen state):
  ``lax.scan`` over the records, each record block under ``jax.checkpoint`` so
  reverse-mode memory grows with the number of records, not of steps.  Works
  under ``jax.jit``, ``jax.vmap``, ``jax.grad`` and ``jax.jvp``.
* :func:`run` -- the host loop: the same records in jitted chunks, with a
  progress bar, neighbour-list re-allocation on overflow (the chunk is run
  again from its start), a divergence stop, an early stop past the peak,
  periodic HDF5 checkpoints and resume.

Because both run the same block on the same state, the host-loop curve equals
the pure curve to round-off (tests/test_lab.py).  The neighbour list cannot
grow inside a pure function: :func:`curve` returns ``overflowed`` in its
history, and :func:`checked_curve` (what calibration uses) grows the list with
:func:`jdem.neighbors.reallocate` and runs again.

Layout of a history: a dict of arrays with records on axis 0, or on axis 1
after a leading member axis when the setup is batched (a sweep over parameter
sets, or an ensemble of packings).
"""
from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import neighbors, precision as precision_mod
from jdem.lab import pattern, summary
from jdem.lab.checkpoint import load_checkpoint, save_checkpoint
from jdem.batch import broadcast_batch, is_batched, member, put_member
from jdem.simulate import (MemberFailure, SimulationDiverged, advance, blank_member_records,
                           check_current_step, diagnose, inert, rollout, scan_first)
from jdem.state import Config, Params, State
from jdem.timestep import check_timestep
from jdem.validate import InputError, check_params, require_int


class LabTest(NamedTuple):
    """A laboratory test as pure functions (hashable, so it can be static).

    name      short name (``"ucs"``, ``"biaxial"``, ``"brazilian"``, ``"tension"``)
    setup     ``setup(specimen, params, **options) -> Setup`` (host)
    load      ``load(state, k, frame, plan) -> state``: the loading in force during
              record ``k`` (wall or grip velocities along the ramp, servo flags,
              servo areas); traced
    boundary  ``boundary(state, params, frame) -> (state, force (N, d))`` applied
              every step (:func:`jdem.integrate.physics_step`); traced
    observe   ``observe(state, params, config, frame) -> dict`` of one record (one
              member's state and frame); traced
    derive    ``derive(raw, frame, plan) -> dict``: the history from the records
              (records on axis 0, any member axis after it); traced (jnp)
    """

    name: str
    setup: Callable
    load: Callable
    boundary: Callable
    observe: Callable
    derive: Callable


@dataclasses.dataclass(frozen=True)
class Plan:
    """The static part of a set-up (hashable).

    test             the :class:`LabTest`
    config           engine :class:`jdem.state.Config`
    n_records        records of the whole run (the preload included)
    record_every     steps per record
    preload_records  records of the isotropic preload before axial loading (0: none)
    ramp_records     records over which the loading speeds up (half a cosine)
    batched          state and frame carry a leading member axis
    damping          the :class:`jdem.lab.damping.Damping` in force
    options          the test's own static settings, a tuple of (name, value)
    """

    test: LabTest
    config: Config
    n_records: int
    record_every: int
    preload_records: int
    ramp_records: int
    batched: bool
    damping: object
    options: tuple = ()

    def option(self, name, default=None):
        return dict(self.options).get(name, default)

    def replace(self, **changes) -> "Plan":
        return dataclasses.replace(self, **changes)


@jax.tree_util.register_pytree_node_class
class Setup:
    """A lab test ready to run: ``state`` (initial), ``params`` (with the time
    step and damping in force), ``frame`` (the test's reference geometry and
    loading, a NamedTuple of arrays) and the static ``plan``.  A pytree, so it
    can be passed to jitted functions."""

    def __init__(self, state: State, params: Params, frame, plan: Plan):
        self.state, self.params, self.frame, self.plan = state, params, frame, plan

    def tree_flatten(self):
        return (self.state, self.params, self.frame), self.plan

    @classmethod
    def tree_unflatten(cls, plan, children):
        return cls(*children, plan)

    def replace(self, **changes) -> "Setup":
        kw = dict(state=self.state, params=self.params, frame=self.frame, plan=self.plan)
        kw.update(changes)
        return Setup(**kw)

    @property
    def n_members(self) -> int:
        return int(np.shape(self.state.step)[0]) if self.plan.batched else 1

    @property
    def test(self) -> LabTest:
        return self.plan.test

    @property
    def dtype(self):
        """The working float dtype (float32 or float64) of state, params and frame."""
        return jnp.asarray(self.params.dt).dtype

    def __repr__(self):
        p = self.plan
        return (f"Setup({p.test.name}, {self.n_members} member(s), {p.n_records} records x "
                f"{p.record_every} steps, damping {p.damping})")


class LabResult(NamedTuple):
    """history: dict (records on axis 0; batched: members on axis 0, records on
    axis 1); state: the final state; setup: the set-up in force at the end (its
    neighbour list may have grown); failures: a :class:`jdem.simulate.MemberFailure`
    per member of a batched run that failed and was set aside (its records from
    the failure on are NaN, ``history["member_failed_step"]`` its first bad step)."""

    history: dict
    state: State
    setup: Setup
    failures: tuple = ()


# ----------------------------------------------------------------------------- the record block
def ramp(k, plan: Plan):
    """Fraction of full loading speed during record ``k``: 0 during the preload,
    then half a cosine over ``ramp_records`` (a sudden start would ring the
    specimen's lowest mode), then 1.  ``ramp_records = 0``: full speed at once."""
    kk = jnp.asarray(k) - plan.preload_records
    if plan.ramp_records == 0:   # a sudden start
        return jnp.where(kk < 0, 0.0, 1.0)
    x = jnp.clip((kk + 0.5) / plan.ramp_records, 0.0, 1.0)
    return jnp.where(kk < 0, 0.0, 0.5 - 0.5 * jnp.cos(jnp.pi * x))


def in_precision(setup: Setup, precision=precision_mod.DEFAULT) -> Setup:
    """``setup`` with its state, params and frame in ``precision`` ("float32" or
    "float64", :mod:`jdem.precision`); the test set-ups call it last."""
    dtype = precision_mod.dtype_of(precision)
    cast = lambda t: precision_mod.cast(t, dtype)
    return setup.replace(state=cast(setup.state), params=cast(setup.params),
                         frame=cast(setup.frame))


def _params_for(params, setup: Setup):
    """``params`` for the runners: in the set-up's precision (calibration may
    hand float64 parameters to a float32 set-up; the cast is differentiable)
    and broadcast to every member of a batched set-up."""
    params = precision_mod.cast(params, setup.dtype)
    if setup.plan.batched and not is_batched(params):
        return broadcast_batch(params, setup.n_members)   # one parameter set for every member
    return params


def _no_record(state, params, config):
    return {}


def _block(plan: Plan, params, frame):
    test = plan.test

    observe = jax.vmap(test.observe, in_axes=(0, 0, None, 0)) if plan.batched \
        else test.observe

    def block(s, k):
        s = test.load(s, k, frame, plan)
        s, _ = rollout(s, params, plan.config, 1, plan.record_every, _no_record,
                       batched=plan.batched, checkpoint=False, boundary=(test.boundary, frame))
        return s, observe(s, params, plan.config, frame)

    return block


def _finish(raw, frame, plan: Plan):
    """The derived history, members first."""
    hist = plan.test.derive(raw, frame, plan)
    if plan.batched:
        hist = {k: jnp.swapaxes(v, 0, 1) for k, v in hist.items()}
    return hist


# ----------------------------------------------------------------------------- pure
@functools.partial(jax.jit, static_argnames=("plan",))
def _pure(state, params, frame, plan: Plan):
    block = _block(plan, params, frame)
    final, raw = jax.lax.scan(jax.checkpoint(block), state, jnp.arange(plan.n_records))
    hist = _finish(raw, frame, plan)
    hist["overflowed"] = neighbors.overflowed(final.contacts, plan.config)
    hist["first_bad_step"] = jnp.max(final.first_bad_step)
    hist["member_first_bad_step"] = final.first_bad_step   # (members,) when batched
    return hist, final


def curve(setup: Setup, params: Params | None = None) -> LabResult:
    """Run the whole test as one pure function; returns a :class:`LabResult`
    whose history (JAX arrays) holds the test's entries plus

    overflowed      () the neighbour list overflowed: the curve is wrong; grow it
                    (:func:`grow`) and run again, or use :func:`checked_curve`
    first_bad_step  () first non-finite step (-1 if none)
    member_first_bad_step  the same per member (members,) of a batched set-up

    ``params`` defaults to ``setup.params`` (use e.g.
    ``jdem.materials.material(setup.params, values)`` to change the rock).  With
    a batched set-up, ``params`` may be one parameter set (shared) or one per
    member.  Differentiable in ``params`` (and in ``setup.state``)."""
    params = setup.params if params is None else params
    params = _params_for(params, setup)
    hist, final = _pure(setup.state, params, setup.frame, setup.plan)
    return LabResult(hist, final, setup)


def grow(setup: Setup) -> Setup:
    """The set-up with a larger neighbour list (:func:`jdem.neighbors.reallocate`
    after an overflow: the needs it recorded, or twice the capacity)."""
    s = setup.state
    c = s.contacts
    cap = max(2 * int(c.i.shape[-1]), neighbors.room_for(int(np.max(np.asarray(c.n_pairs)))))
    contacts, config = neighbors.reallocate(c, s.particles, setup.plan.config, s.bonds,
                                            capacity=cap)
    return setup.replace(state=s._replace(contacts=contacts),
                         plan=setup.plan.replace(config=config))


def checked_curve(setup: Setup, params: Params | None = None, *, max_grow=4):
    """:func:`curve` on the host, growing the neighbour list on overflow and
    raising on divergence.  Returns ``(history as NumPy, setup)``."""
    for _ in range(max_grow + 1):
        res = curve(setup, params)
        if not bool(res.history["overflowed"]):
            break
        setup = grow(setup)
    else:
        raise RuntimeError(f"neighbour list still overflows after growing it {max_grow} times")
    bad = int(res.history["first_bad_step"])
    if bad >= 0:
        raise SimulationDiverged(bad, None, {k: np.asarray(v) for k, v in res.history.items()})
    return {k: np.asarray(v) for k, v in res.history.items()}, setup


# ----------------------------------------------------------------------------- host loop
@functools.lru_cache(maxsize=8)   # each program holds memory mappings
def record_chunk(plan: Plan, n: int):
    """The jitted chunk the host loop :func:`run` runs: ``fn(state, params, frame,
    k0, n_run=n)`` takes records ``k0 .. k0 + n_run - 1`` (``k0`` an int32
    scalar, ``0 <= n_run <= n``) and returns ``(state, raw records)`` with
    ``n`` records on axis 0, of which the first ``n_run`` are real (the rest
    hold zeros and leave the state alone).  One program per (plan, n), cached:
    a run's last, shorter chunk and the rerun up to a peak reuse the program of
    its full chunks instead of compiling one of their own."""
    def records(state, params, frame, k0, n_run):
        return scan_first(_block(plan, params, frame), state, k0 + jnp.arange(n), n_run)

    jitted = jax.jit(records)

    def fn(state, params, frame, k0, n_run=n):
        return jitted(state, params, frame, k0, jnp.asarray(n_run, jnp.int32))

    # ahead-of-time compilation (benchmarks): fn.lower(...).compile() takes the
    # arguments of fn, n_run included
    fn.lower = lambda state, params, frame, k0, n_run=n: jitted.lower(
        state, params, frame, k0, jnp.asarray(n_run, jnp.int32))
    return fn


def _strong(tree):
    """Drop weak types (they would recompile an otherwise identical call)."""
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=jnp.asarray(a).dtype), tree)


def _concat(parts):
    return {k: np.concatenate([p[k] for p in parts], axis=0) for k in parts[0]}


def _host_history(parts, setup: Setup) -> dict:
    raw = _concat(parts)
    hist = _finish(raw, setup.frame, setup.plan)
    return {k: np.asarray(v) for k, v in hist.items()}


def run(setup: Setup, params: Params | None = None, *, progress=True, chunk_records=None,
        stop_stress_ratio=None, keep_peak_state=False, checkpoint=None, checkpoint_every=60.0,
        resume=None, check_dt=True, warn_dynamic=True) -> LabResult:
    """Run the test as a host loop of jitted chunks of records.

    params            default ``setup.params``
    progress          tqdm bar (steps, current axial stress)
    chunk_records     records per jitted chunk (default about 2,000 steps per chunk)
    stop_stress_ratio stop once every member's axial stress fell below this
                      fraction of its peak, a whole chunk after the peak
    keep_peak_state   add the bonds at each member's peak (``peak_*`` entries; the
                      chunk holding the peak is run again up to that record)
    checkpoint        HDF5 path: the run is saved there every ``checkpoint_every``
                      seconds (atomically: written beside it, then renamed) and
                      when it ends, is interrupted or fails
    resume            HDF5 path of a checkpoint to continue from (the same test);
                      the continuation is bit-for-bit the uninterrupted run
    warn_dynamic      warn when the in-run quasi-static indicator is high
                      (:func:`jdem.lab.summary.kinetic_ratio`)

    Returns a :class:`LabResult` (history as NumPy, with the per-bond ``end_*``
    arrays of the final state, see :func:`jdem.lab.pattern.bond_record`).
    Raises :class:`jdem.SimulationDiverged` with the state at the start of the
    chunk that went wrong (and the history before it).
    """
    if chunk_records is not None:
        require_int("chunk_records", chunk_records, 1)
    parts, k0 = [], 0
    if resume is not None:
        setup, params_saved, parts, k0 = load_checkpoint(resume, setup)
        params = params_saved if params is None else params
    params = setup.params if params is None else params
    params = _strong(_params_for(params, setup))
    check_params(params)
    plan = setup.plan
    failures = []
    if check_dt:
        _check_timestep(setup, params, failures)
    per = min(chunk_records or max(1, 2000 // plan.record_every), plan.n_records)
    nb = setup.n_members
    state, frame = _strong(setup.state), _strong(setup.frame)
    for f in failures:
        state = put_member(state, f.member, inert(f.last_good_state))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=plan.n_records * plan.record_every, initial=k0 * plan.record_every,
                   desc=plan.test.name, unit="step", leave=False)
    peak_val = np.full(nb, -np.inf)
    peak_at = [None] * nb          # (chunk start state, k0, record index in chunk, plan)
    last_save = time.time()
    status = "interrupted"
    try:
        while k0 < plan.n_records:
            n = min(per, plan.n_records - k0)
            earlier = [f.member for f in failures]
            fn = record_chunk(plan, per)    # one program for every chunk
            new_state, raw = fn(state, params, frame, jnp.asarray(k0, jnp.int32), n)
            if bool(neighbors.overflowed(new_state.contacts, plan.config)):
                need = state.contacts._replace(n_pairs=new_state.contacts.n_pairs,
                                               max_in_cell=new_state.contacts.max_in_cell)
                contacts, config = neighbors.reallocate(need, state.particles, plan.config,
                                                        state.bonds)
                state = state._replace(contacts=contacts)
                plan = plan.replace(config=config)
                setup = setup.replace(plan=plan)
                continue
            raw = {key: np.asarray(v)[:n] for key, v in raw.items()}
            bad = np.asarray(new_state.first_bad_step).reshape(-1)
            if np.any(bad >= 0):
                try:
                    new_state = _set_aside(setup.replace(state=state), params, k0, bad,
                                           failures, raw, parts, new_state, fn)
                except SimulationDiverged:
                    status = "diverged"
                    raise
            if check_dt:
                try:
                    new_state = check_current_step(
                        new_state, params, plan.config, failures, plan.batched,
                        lambda: _host_history(parts, setup) if parts else {})
                except SimulationDiverged:
                    status = "diverged"
                    raise
            for b in earlier:       # members set aside before this chunk
                blank_member_records(raw, b, 0)
            start = state
            parts.append(raw)
            state = new_state
            k0 += n
            if bar is not None:
                bar.update(n * plan.record_every)
            if stop_stress_ratio is not None or keep_peak_state or bar is not None:
                stress = _axial_stress(parts, setup)
                if stress is not None:
                    stress = stress.reshape(nb, -1)
                    if bar is not None and stress.shape[1]:
                        bar.set_postfix(stress=f"{float(np.max(stress[:, -1])) / 1e6:.3g} MPa")
                    n_new = min(n, stress.shape[1])
                    for b in range(nb):
                        if not stress.shape[1] or not np.any(np.isfinite(stress[b])):
                            continue
                        j = int(np.nanargmax(stress[b]))
                        if stress[b, j] > peak_val[b]:
                            peak_val[b] = stress[b, j]
                            if j >= stress.shape[1] - n_new:   # in this chunk: its record
                                peak_at[b] = (start, k0 - n, n - (stress.shape[1] - j), plan,
                                              per)
                    if stop_stress_ratio is not None and stress.shape[1] > n_new:
                        gone = np.isin(np.arange(nb), [f.member for f in failures])
                        with np.errstate(invalid="ignore"):
                            recent = np.where(gone, -np.inf, stress[:, -n_new:].mean(axis=1))
                        idx = np.argmax(np.where(np.isfinite(stress), stress, -np.inf), axis=1)
                        if np.all(gone | ((recent < stop_stress_ratio * peak_val)
                                          & (idx < stress.shape[1] - n_new))):
                            break
            if checkpoint is not None and time.time() - last_save >= checkpoint_every:
                save_checkpoint(checkpoint, setup.replace(state=state), params, parts, k0)
                last_save = time.time()
        status = "done"
    finally:
        if bar is not None:
            bar.close()
        if checkpoint is not None and parts and status != "diverged":
            save_checkpoint(checkpoint, setup.replace(state=state), params, parts, k0,
                            status=status)
    for f in failures:     # a set-aside member ends in its last good state
        state = put_member(state, f.member, f.last_good_state)
    setup = setup.replace(state=state)
    history = _host_history(parts, setup)
    history.update(pattern.bond_record(state, "end_"))
    if plan.batched:
        failed_step = np.full(nb, -1, np.int64)
        for f in failures:
            failed_step[f.member] = f.step
        history["member_failed_step"] = failed_step
    if failures:
        import warnings

        warnings.warn("; ".join(f"{plan.test.name} member {f.member} set aside at step "
                                f"{f.step}: {f.reason}" for f in failures),
                      RuntimeWarning, stacklevel=2)
    if keep_peak_state:
        recs = []
        for b in range(nb):
            if b in {f.member for f in failures}:
                raise InputError(f"keep_peak_state: member {b} failed during the run "
                                 f"(result.failures); its peak state is not kept")
            if peak_at[b] is None:
                raise InputError("keep_peak_state: the peak lies in the part of the run "
                                 "before the resumed checkpoint; run it without resume")
            s0, kstart, j, plan_b, per_b = peak_at[b]
            fn = record_chunk(plan_b, per_b)       # the run's program, stopped after record j
            s, _ = fn(s0, params, frame, jnp.asarray(kstart, jnp.int32), j + 1)
            rec = pattern.bond_record(member(s, b) if plan.batched else s, "peak_")
            rec["peak_step"] = np.asarray(np.asarray(s.step).reshape(-1)[b if plan.batched else 0])
            recs.append(rec)
        history.update({key: np.stack([r[key] for r in recs]) if plan.batched else recs[0][key]
                        for key in recs[0]})
    if warn_dynamic:
        summary.warn_if_dynamic(history, plan.test.name)
    return LabResult(history, state, setup, tuple(failures))


def _good_state(setup: Setup, params, k0: int, first: int, chunk):
    """The state of the run started at record ``k0`` from ``setup.state`` just
    before step ``first``: whole records (by ``chunk``, the run's
    :func:`record_chunk` program), then the steps of the record that holds
    ``first`` under that record's loading."""
    plan, state = setup.plan, setup.state
    start = int(np.min(np.asarray(state.step)))
    j, m = divmod(first - start, plan.record_every)
    if j:
        state, _ = chunk(state, params, setup.frame, jnp.asarray(k0, jnp.int32), j)
    state = plan.test.load(state, jnp.asarray(k0 + j, jnp.int32), setup.frame, plan)
    return advance(state, params, plan.config, m, batched=plan.batched,
                   boundary=(plan.test.boundary, setup.frame))


def _set_aside(setup: Setup, params, k0, bad, failures, raw, parts, new_state, chunk):
    """The members of a chunk started at record ``k0`` that failed the guard
    (``bad``: first bad step per member, -1 for none).  One system, or a batch
    whose every member has failed: raise :class:`SimulationDiverged` with the
    state before the bad step and the reason.  Otherwise blank each newly failed
    member's records from the bad one on, note a ``MemberFailure`` and return
    the chunk's end state ``new_state`` with that member inert."""
    plan = setup.plan
    start = int(np.min(np.asarray(setup.state.step)))
    boundary = (plan.test.boundary, setup.frame)
    for b in np.flatnonzero(bad >= 0):
        first = int(bad[b])
        good = _good_state(setup, params, k0, first, chunk)
        if not plan.batched:
            raise SimulationDiverged(first, good, _host_history(parts, setup) if parts else {},
                                     diagnose(good, params, plan.config, boundary))
        good = member(good, b)
        reason = diagnose(good, member(params, b), plan.config,
                          (plan.test.boundary, member(setup.frame, b)))
        failures.append(MemberFailure(int(b), first, reason, good))
        if len(failures) == setup.n_members:
            f0 = min(failures, key=lambda f: f.step)
            raise SimulationDiverged(f0.step, f0.last_good_state,
                                     _host_history(parts, setup) if parts else {},
                                     f"every member failed; member {f0.member} first: "
                                     f"{f0.reason}")
        blank_member_records(raw, b, (first - start) // plan.record_every)
        new_state = put_member(new_state, b, inert(good))
    return new_state


@functools.partial(jax.jit, static_argnames=("plan",))
def _derived_axial_stress(raw, frame, plan: Plan):
    return plan.test.derive(raw, frame, plan).get("axial_stress")


def _axial_stress(parts, setup):
    """The axial stress of the records run so far (members first), or None for a
    test without one.  Derived by one compiled program for the whole run: the
    records are padded to the plan's length with the last one (the derivation
    is record by record, so the padding does not change the records before it)
    and the padded part is cut off.  Derived op by op on the growing history,
    every chunk compiled each operation anew (14 s of a 67 s precision test)."""
    raw = _concat(parts)
    n = next(iter(raw.values())).shape[0]
    total = max(setup.plan.n_records, n)
    if total > n:
        raw = {k: np.concatenate([v, np.repeat(v[-1:], total - n, axis=0)], axis=0)
               for k, v in raw.items()}
    s = _derived_axial_stress(raw, setup.frame, setup.plan)
    if s is None:
        return None
    s = np.asarray(s)[:max(n - setup.plan.preload_records, 0)]
    return np.swapaxes(s, 0, 1) if setup.plan.batched else s


def _check_timestep(setup: Setup, params, failures):
    """Refuse a time step above the critical one: raise ``InputError`` for one
    system or when every member of a batch has it; otherwise note the members
    that have it in ``failures`` (they are set aside before the run starts)."""
    if not setup.plan.batched:
        check_timestep(setup.state, params, setup.plan.config)
        return
    refused = []
    for b in range(setup.n_members):
        try:
            check_timestep(member(setup.state, b), member(params, b), setup.plan.config)
        except InputError as e:
            refused.append((b, str(e)))
    if len(refused) == setup.n_members:
        raise InputError(f"every member: {refused[0][1]}")
    step = int(np.min(np.asarray(setup.state.step)))
    for b, why in refused:
        failures.append(MemberFailure(b, step, f"refused at the start: {why}",
                                      member(setup.state, b)))


def n_records_for(load_steps, record_every, ramp_records, preload_records=0):
    """Records of a run whose loading needs ``load_steps`` steps at full speed,
    after a ramp of ``ramp_records`` (which covers half its length, so half a
    ramp more is run) and a preload of ``preload_records``."""
    return int(preload_records + math.ceil(float(load_steps) / record_every
                                           + 0.5 * ramp_records))


def stack_setups(setups) -> Setup:
    """One batched set-up from unbatched set-ups of the same specimen and schedule
    that differ in their params and frames only (e.g. the same test under two
    dampings): members in the order given.  The plan (its ``damping`` is only a
    label then) is the first one's."""
    first = setups[0]
    for k, su in enumerate(setups):
        if su.plan.batched:
            raise InputError(f"setups[{k}] is batched already")
        same = su.plan.replace(damping=first.plan.damping) == first.plan
        if not same or su.state.particles.pos.shape != first.state.particles.pos.shape:
            raise InputError(f"setups[{k}] differs from setups[0] in more than params and frame "
                             f"(specimen, schedule or time step)")
    stack = lambda *a: jnp.stack(a)
    return Setup(broadcast_batch(first.state, len(setups)),
                 jax.tree_util.tree_map(stack, *[su.params for su in setups]),
                 jax.tree_util.tree_map(stack, *[su.frame for su in setups]),
                 first.plan.replace(batched=True))
