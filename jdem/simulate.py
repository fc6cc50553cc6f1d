"""Building a simulation and running it.

* :func:`make_state` assembles particles, walls and bonds into a ``State`` and
  sizes the neighbour list.
* :func:`rollout` is the pure, differentiable core: ``lax.scan`` over records,
  each record ``record_every`` steps, each record block wrapped in
  ``jax.checkpoint`` so reverse-mode memory grows with the number of records,
  not steps.  It works under ``jax.grad`` and ``jax.vmap``.
  Its neighbour list cannot grow: the history carries ``overflowed`` and the
  records after an overflow are NaN (:func:`raise_if_overflowed`).
* :func:`run` is the host loop around it, one jitted chunk of records at a time.
  Between chunks it

  - checks the neighbour list: on overflow it re-allocates larger from the
    chunk's starting state and runs the chunk again (nothing is dropped);
  - checks the divergence guard that every step evaluates
    (:func:`jdem.integrate.healthy`: non-finite values, a particle moving more
    than half its radius in one step, a pair overlapping by more than its
    smaller radius): it stops with :class:`SimulationDiverged`, which names the first
    bad step, the quantity and the particle (:func:`diagnose`) and carries the
    last good state (the state one step before it).  In a batched run a failing
    member is set aside instead (its particles made inert, its later records
    NaN, its last good state and reason in ``RunResult.failures``) and the
    others go on; only when every member failed does the run stop;
  - shows a progress bar (tqdm) and collects the history.
"""
from __future__ import annotations

import functools
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import contact, integrate, neighbors
from jdem.measure import basic_observables
from jdem.state import Config, Params, State, empty_bonds, no_walls
from jdem.validate import InputError, check_materials, check_params, check_particles, require_int


class MemberFailure(NamedTuple):
    """A batch member set aside by a batched run: ``member`` its index, ``step``
    the first step that failed the guard, ``reason`` what failed (from
    :func:`diagnose`), ``last_good_state`` its state before that step."""

    member: int
    step: int
    reason: str
    last_good_state: object


class RunResult(NamedTuple):
    """state: final State; config: the Config in force at the end (capacities may
    have grown); history: dict of NumPy arrays, records along axis 0 (batched
    runs: batch along axis 0, records along axis 1; a failed member's records
    from its failure on are NaN); failures: a :class:`MemberFailure` per batch
    member that was set aside (empty when all finished)."""

    state: State
    config: Config
    history: dict
    failures: tuple = ()


class SimulationDiverged(RuntimeError):
    """A step failed the divergence guard (:func:`jdem.integrate.healthy`).
    ``step`` is the first bad step; ``reason`` says what failed, where;
    ``last_good_state`` is the state just before that step (or, when noted, the
    start of the record or chunk that holds it); ``history`` what was recorded."""

    def __init__(self, step, last_good_state, history, reason=""):
        why = reason or "non-finite positions or velocities"
        super().__init__(
            f"simulation diverged at step {step}: {why}; the state before that step is "
            f"kept in .last_good_state (is params.dt below the critical step? see "
            f"jdem.timestep)")
        self.step = step
        self.last_good_state = last_good_state
        self.history = history
        self.reason = why


def diagnose(state: State, params: Params, config: Config, boundary=None) -> str:
    """Why the step from ``state`` (one system) fails the guard of
    :func:`jdem.integrate.healthy`, naming the quantity, the particle(s) and the
    value; ``""`` if it does not.  Host-side; used when a run stops."""
    s0 = integrate.refresh_neighbors(state, config)
    s1 = integrate.physics_step(s0, params, config, boundary)
    p0, p1 = s0.particles, s1.particles
    step = int(np.asarray(s0.step))
    valid = np.asarray(p1.valid)
    reasons = []
    for name in ("pos", "vel", "angvel"):
        a = np.asarray(getattr(p1, name)).reshape(valid.shape[0], -1)
        bad = np.flatnonzero(~np.all(np.isfinite(a), axis=1))
        if bad.size:
            reasons.append(f"particle {int(bad[0])} has a non-finite {name} after step {step} "
                           f"({bad.size} particle(s) in all)")
    speed = np.linalg.norm(np.asarray(p1.vel), axis=-1)
    travel = np.where(valid & np.isfinite(speed), speed * np.asarray(params.dt), 0.0) \
        / np.where(np.asarray(p1.radius) > 0, np.asarray(p1.radius), 1.0)
    k = int(np.argmax(travel)) if travel.size else 0
    if travel.size and travel[k] > 0.5:
        reasons.append(f"particle {k} moves {travel[k]:.3g} of its radius in step {step} "
                       f"(speed {speed[k]:.3g} m/s; the guard allows half a radius per step)")
    g = contact.pair_geometry(s0.contacts, p0)
    i, j = np.asarray(s0.contacts.i), np.asarray(s0.contacts.j)
    rad = np.asarray(p0.radius)
    if i.size:
        ratio = np.where(np.asarray(g.touching),
                         np.asarray(g.overlap) / np.maximum(np.minimum(rad[i], rad[j]), 1e-300), 0)
        c = int(np.argmax(ratio))
        if ratio[c] > 1.0:
            reasons.append(f"particles {int(i[c])} and {int(j[c])} overlap by {ratio[c]:.4g} of "
                           f"the smaller radius at step {step}: they are passing through each "
                           f"other (too fast for the contact stiffness and dt)")
    return "; ".join(reasons)


# ----------------------------------------------------------------------------- set-up
def make_config(particles, *, contact_model="linear", skin=None, **overrides) -> Config:
    """A ``Config`` whose search grid covers the particles (plus a margin)."""
    dim = particles.pos.shape[1]
    rad = np.asarray(particles.radius)[np.asarray(particles.valid)]
    skin = float(0.3 * rad.mean()) if skin is None else float(skin)
    origin, shape, cell = neighbors.grid_for(particles, skin=skin)
    fields = dict(dim=dim, contact_model=contact_model, skin=skin, cell_size=cell,
                  grid_origin=origin, grid_shape=shape)
    fields.update(overrides)
    return Config(**fields)


def make_state(particles, config: Config | None = None, *, walls=None, bonds=None,
               contact_model="linear", skin=None):
    """Assemble a ``State`` and size its neighbour list.  Returns ``(state, config)``.

    Raises :class:`jdem.validate.InputError` when no particle is valid or two
    valid particles share a centre (:func:`jdem.validate.check_particles`).
    """
    check_particles(particles)
    n, dim = particles.pos.shape
    if config is None:
        config = make_config(particles, contact_model=contact_model, skin=skin)
    walls = no_walls(dim, n, particles.pos.dtype) if walls is None else walls
    bonds = empty_bonds(dim, 0, particles.pos.dtype) if bonds is None else bonds
    contacts, config = neighbors.allocate(particles, config, bonds)
    state = State(particles=particles, contacts=contacts, walls=walls, bonds=bonds,
                  step=jnp.zeros((), jnp.int32), time=jnp.zeros((), particles.pos.dtype),
                  first_bad_step=jnp.full((), -1, jnp.int32))
    return state, config


# ----------------------------------------------------------------------------- pure core
def rollout(state: State, params: Params, config: Config, n_records: int, record_every: int,
            observe: Callable | None = None, *, batched=False, checkpoint=True, boundary=None):
    """Run ``n_records * record_every`` steps; return ``(state, history)``.

    ``observe(state, params, config) -> dict`` is called after every block of
    ``record_every`` steps; the history stacks its outputs along axis 0.  With
    ``batched=True`` every leaf of ``state`` and ``params`` has a leading batch
    axis and each history entry has shape ``(n_records, batch, ...)``.
    The neighbour list has a fixed capacity and cannot grow inside a pure
    function.  The history therefore always carries ``overflowed`` (per record;
    per member when batched), and every floating-point entry of a record taken
    after an overflow is NaN, so a truncated list cannot pass unnoticed;
    :func:`run` grows the list and runs the chunk again, and
    :func:`raise_if_overflowed` turns the flag into an error.  ``boundary = (fn, data)``
    adds boundary conditions to every step (see :func:`jdem.integrate.physics_step`).
    """
    observe = observe or basic_observables
    step_fn = integrate.step_batched if batched else integrate.step
    obs = jax.vmap(observe, in_axes=(0, 0, None)) if batched else observe
    over = jax.vmap(neighbors.overflowed, in_axes=(0, None)) if batched else neighbors.overflowed

    def one_step(s, _):
        return step_fn(s, params, config, boundary), None

    def block(s, _):
        s, _ = jax.lax.scan(one_step, s, None, length=record_every)
        rec = obs(s, params, config)
        lost = over(s.contacts, config)
        # a record taken after the list overflowed misses contacts: poison it
        rec = {k: jnp.where(lost.reshape(lost.shape + (1,) * (v.ndim - lost.ndim)), jnp.nan, v)
               if jnp.issubdtype(v.dtype, jnp.floating) else v for k, v in rec.items()}
        rec["overflowed"] = lost
        return s, rec

    if checkpoint:
        block = jax.checkpoint(block)
    return jax.lax.scan(block, state, None, length=n_records)


def scan_first(body: Callable, carry, xs, n_run=None):
    """``jax.lax.scan(body, carry, xs)`` in which only the first ``n_run`` items of
    ``xs`` are run (``n_run`` a traced int; ``None``: all of them).  The others
    leave the carry alone and give zero outputs, so one compiled program serves
    every ``n_run`` up to the length of ``xs``: a host loop's last, shorter chunk
    reuses the program of its full ones instead of compiling its own."""
    if n_run is None:
        return jax.lax.scan(body, carry, xs)

    def skip(c, x):
        shapes = jax.eval_shape(body, c, x)[1]
        return c, jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)

    def maybe(c, item):
        index, x = item
        return jax.lax.cond(index < n_run, body, skip, c, x)

    n = jax.tree_util.tree_leaves(xs)[0].shape[0]
    return jax.lax.scan(maybe, carry, (jnp.arange(n), xs))


class NeighbourListOverflow(RuntimeError):
    """The fixed-capacity neighbour list overflowed inside a pure rollout."""


def raise_if_overflowed(history: dict):
    """Raise :class:`NeighbourListOverflow` if a :func:`rollout` history says the
    neighbour list overflowed (grow it with :func:`jdem.neighbors.reallocate`,
    or use :func:`run`)."""
    flag = np.asarray(history["overflowed"])
    if np.any(flag):
        first = int(np.argmax(flag.reshape(flag.shape[0], -1).any(axis=1)))
        raise NeighbourListOverflow(
            f"the neighbour list overflowed by record {first}: contacts were dropped and "
            f"the records from there on are NaN; grow it (jdem.neighbors.reallocate) or use "
            f"jdem.run, which does")


def _with(boundary_fn, data):
    return None if boundary_fn is None else (boundary_fn, data)


@functools.lru_cache(maxsize=8)   # each program holds memory mappings
def _compiled_chunk(config, n_records, record_every, observe, batched, boundary_fn=None):
    def chunk(state, params, data):
        return rollout(state, params, config, n_records, record_every, observe,
                       batched=batched, checkpoint=False, boundary=_with(boundary_fn, data))

    return jax.jit(chunk)


@functools.lru_cache(maxsize=16)
def _compiled_advance(config, batched, boundary_fn=None):
    step_fn = integrate.step_batched if batched else integrate.step

    def advance(state, params, n, data):
        return jax.lax.fori_loop(
            0, n, lambda _, s: step_fn(s, params, config, _with(boundary_fn, data)), state)

    return jax.jit(advance)


def advance(state: State, params: Params, config: Config, n_steps, *, batched=False,
            boundary=None) -> State:
    """Take ``n_steps`` steps (jitted once for any count; not reverse-differentiable)."""
    fn, data = boundary if boundary is not None else (None, None)
    return _compiled_advance(config, batched, fn)(state, params,
                                                  jnp.asarray(n_steps, jnp.int32), data)


# ----------------------------------------------------------------------------- host loop
def _check_inputs(state: State, params: Params, config: Config, batched: bool, check_dt: bool):
    from jdem.timestep import check_timestep

    if batched != (np.ndim(state.step) == 1):
        raise InputError(f"batched = {batched} but the state {'has' if np.ndim(state.step) else 'has no'}"
                         f" leading batch axis (state.step has shape {np.shape(state.step)})")
    if state.particles.pos.shape[-1] != config.dim:
        raise InputError(f"state has dimension {state.particles.pos.shape[-1]} but config.dim = {config.dim}")
    check_params(params, config.dim)
    check_materials(state, params)
    if check_dt:
        if batched:
            for b in range(state.step.shape[0]):
                pick = lambda t: jax.tree_util.tree_map(lambda a: a[b], t)
                check_timestep(pick(state), pick(params), config)
        else:
            check_timestep(state, params, config)


def run(state: State, params: Params, config: Config, n_steps: int, *, record_every: int = 100,
        observe: Callable | None = None, chunk_steps: int | None = None, progress=True,
        batched=False, check_dt=True, desc="jdem", boundary=None, checkpoint=None,
        checkpoint_every=60.0, resume=None) -> RunResult:
    """Run ``n_steps`` steps in jitted chunks; see the module docstring.

    n_steps       total steps; must be a multiple of ``record_every``
    record_every  steps between history records
    observe       ``observe(state, params, config) -> dict of arrays`` (default
                  :func:`jdem.measure.basic_observables`); must be a module-level
                  function or otherwise reused object so compiled chunks are cached
    chunk_steps   steps per jitted chunk (default about 5,000, a multiple of record_every)
    batched       leading batch axis on state and params (a parameter sweep); a
                  member that fails is set aside (``RunResult.failures``) and the
                  others go on
    check_dt      raise if ``params.dt`` exceeds the critical step, at the start
                  and, with the current contacts, after every chunk
    boundary      optional ``(fn, data)`` boundary conditions applied every step
                  (see :func:`jdem.integrate.physics_step`); ``fn`` must be a
                  module-level function so compiled chunks are cached, ``data``
                  a pytree (batched runs: leading batch axis)
    checkpoint    HDF5 path: state, config and the records so far are saved there
                  (atomically, :func:`jdem.io.save_run`) every ``checkpoint_every``
                  seconds, at the end, and when the run is interrupted (Ctrl-C)
    resume        such a checkpoint of the same run (same ``n_steps``,
                  ``record_every`` and initial state's shapes): the run continues
                  from it, bit for bit, and the history holds every record
    """
    record_every = require_int("record_every", record_every, 1)
    n_steps = require_int("n_steps", n_steps, 0)
    if n_steps % record_every:
        raise InputError(f"n_steps = {n_steps} must be a multiple of record_every = {record_every}")
    _check_inputs(state, params, config, batched, check_dt)
    params = _strong(params)
    boundary_fn, data = boundary if boundary is not None else (None, None)
    data = _strong(data)
    observe = observe or basic_observables
    total_records = n_steps // record_every
    per_chunk = _chunk_records(total_records, max(1, (chunk_steps or 5000) // record_every))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n_steps, desc=desc, unit="step", leave=False)
    history: list[dict] = []
    failures: list[MemberFailure] = []
    done = 0
    if resume is not None:
        state, config, history, done = _resumed(resume, state, n_steps, record_every)
        if bar is not None:
            bar.update(done * record_every)
    last_save, status = time.time(), "interrupted"
    try:
        while done < total_records:
            n_rec = min(per_chunk, total_records - done)
            earlier = [f.member for f in failures]
            chunk = _compiled_chunk(config, n_rec, record_every, observe, batched, boundary_fn)
            new_state, hist = chunk(state, params, data)
            if bool(neighbors.overflowed(new_state.contacts, config)):
                # the needs the failed chunk recorded, on the chunk's starting list
                need = state.contacts._replace(n_pairs=new_state.contacts.n_pairs,
                                               max_in_cell=new_state.contacts.max_in_cell)
                contacts, config = neighbors.reallocate(need, state.particles, config,
                                                        state.bonds)
                state = state._replace(contacts=contacts)
                continue  # redo the chunk with room for every pair
            bad = np.asarray(new_state.first_bad_step).reshape(-1)
            hist = jax.tree_util.tree_map(np.asarray, hist)
            if np.any(bad >= 0):
                new_state = _set_aside(state, new_state, params, config, bad, failures,
                                       hist, record_every, batched, boundary_fn, data,
                                       lambda: _stack(history, batched))
            if check_dt:
                new_state = check_current_step(new_state, params, config, failures, batched,
                                               lambda: _stack(history, batched))
            for b in earlier:    # members set aside before this chunk
                blank_member_records(hist, b, 0)
            history.append(hist)
            state = new_state
            done += n_rec
            if bar is not None:
                bar.update(n_rec * record_every)
            if checkpoint is not None and time.time() - last_save >= checkpoint_every:
                _save_checkpoint(checkpoint, state, params, config, history, done, n_steps,
                                 record_every, "running")
                last_save = time.time()
        status = "done"
    except SimulationDiverged:
        status = "diverged"
        raise
    finally:
        if bar is not None:
            bar.close()
        if checkpoint is not None and status != "diverged":
            _save_checkpoint(checkpoint, state, params, config, history, done, n_steps,
                             record_every, status)
    for f in failures:   # a set-aside member ends in its last good state
        state = _put_member(state, f.member, f.last_good_state)
    if failures:
        import warnings

        warnings.warn("; ".join(f"member {f.member} set aside at step {f.step}: {f.reason}"
                                for f in failures), RuntimeWarning, stacklevel=2)
    return RunResult(state, config, _stack(history, batched), tuple(failures))


def _member(tree, b):
    from jdem.batch import member   # jdem.batch imports this module

    return member(tree, b)


def _put_member(tree, b, value):
    from jdem.batch import put_member

    return put_member(tree, b, value)


def blank_member_records(hist, b, first_record):
    """NaN the floating-point records of member ``b`` from ``first_record`` on
    (history of one chunk: records on axis 0, members on axis 1)."""
    for key, v in hist.items():
        if np.issubdtype(v.dtype, np.floating):
            v = v.copy()
            v[first_record:, b] = np.nan
            hist[key] = v


def step_margin(state: State, params: Params, config: Config, batched=False):
    """``params.dt`` over the critical step of the current contacts and bonds,
    dashpots included (:func:`jdem.timestep.critical_timestep`); (B,) when
    batched.  Above 1 the explicit scheme is unstable from here on."""
    from jdem.timestep import critical_timestep

    crit = (jax.vmap(lambda s, p: critical_timestep(s, p, config))(state, params) if batched
            else critical_timestep(state, params, config))
    return np.asarray(params.dt) / np.asarray(crit)


def check_current_step(state, params, config, failures, batched, history_so_far):
    """Between chunks: stop (one system: :class:`SimulationDiverged`) or set
    aside (a batch member: a :class:`MemberFailure` appended to ``failures``,
    the member made inert in the returned state) when two facing walls have
    passed each other (:func:`jdem.walls.crossed_pair`) or the critical step of
    the current contacts has fallen below ``params.dt``, with the chunk's end state,
    still finite, as the last good state.  ``history_so_far()`` gives the
    history for the error."""
    from jdem.walls import crossed_pair

    ratio = np.atleast_1d(step_margin(state, params, config, batched))
    done = {f.member for f in failures}
    for b in range(ratio.size):
        if b in done:
            continue
        good = _member(state, b) if batched else state
        step = int(np.asarray(good.step))
        dt = float(np.asarray(params.dt).reshape(-1)[b])
        crossed = crossed_pair(good.walls)
        if crossed is not None:
            reason = (f"walls {crossed[0]} and {crossed[1]} have passed each other by step "
                      f"{step} (gap {crossed[2]:.3g} m)")
        elif ratio[b] > 1.0:
            reason = (f"the critical time step of the current contacts fell to "
                      f"{dt / ratio[b]:.4g} s, below params.dt = {dt:.4g} s, by step {step} "
                      f"(dashpots included; jdem.timestep.critical_timestep)")
        else:
            continue
        if not batched:
            raise SimulationDiverged(step, good, history_so_far(), reason)
        failures.append(MemberFailure(int(b), step, reason, good))
        if len(failures) == ratio.size:
            raise SimulationDiverged(step, good, history_so_far(),
                                     f"every member failed; member {int(b)} last: {reason}")
        state = _put_member(state, b, inert(good))
    return state


def inert(state):
    """``state`` with every particle invalid: no forces, no motion, no trouble."""
    return state._replace(particles=state.particles._replace(
        valid=jnp.zeros_like(state.particles.valid)))


def _set_aside(state, new_state, params, config, bad, failures, hist, record_every, batched,
               boundary_fn, data, history_so_far):
    """Handle the members of a chunk that failed the guard.  One system, or a
    batch whose every member has now failed: raise :class:`SimulationDiverged`
    with the state before the first bad step.  Otherwise record a
    :class:`MemberFailure` for each new one, blank its records from the bad step
    on, and return ``new_state`` with that member made inert (its last good
    state with every particle invalid: no forces, no motion, no trouble)."""
    start = int(np.min(np.asarray(state.step)))
    boundary = _with(boundary_fn, data)
    if not batched:
        first = int(bad[0])
        good = advance(state, params, config, first - start, boundary=boundary)
        raise SimulationDiverged(first, good, history_so_far(),
                                 diagnose(good, params, config, boundary))
    for b in np.flatnonzero(bad >= 0):
        first = int(bad[b])
        good = _member(advance(state, params, config, first - start, batched=True,
                               boundary=boundary), b)
        one = None if boundary_fn is None else (boundary_fn, _member(data, b))
        reason = diagnose(good, _member(params, b), config, one)
        failures.append(MemberFailure(int(b), first, reason, good))
        if len(failures) == bad.size:
            f0 = min(failures, key=lambda f: f.step)
            raise SimulationDiverged(f0.step, f0.last_good_state, history_so_far(),
                                     f"every member failed; member {f0.member} first: "
                                     f"{f0.reason}")
        blank_member_records(hist, b, max(0, (first - start) // record_every))
        new_state = _put_member(new_state, b, inert(good))
    return new_state


def _save_checkpoint(path, state, params, config, history, done, n_steps, record_every, status):
    from jdem import io

    records = _stack(history, False)   # chunk layout: records on axis 0
    io.save_run(path, state=state, params=params, config=config, history={"records": records},
                attrs={"run": dict(n_steps=n_steps, record_every=record_every,
                                   records_done=done, status=status)})


def _resumed(path, state, n_steps, record_every):
    """``(state, config, [records], records_done)`` of a checkpoint of this run."""
    from jdem import io

    rd = io.load_run(path, numpy=True)
    meta = (rd.attrs or {}).get("run")
    if meta is None or rd.state is None:
        raise InputError(f"resume: {path} is not a jdem.run checkpoint")
    if (int(meta["n_steps"]), int(meta["record_every"])) != (n_steps, record_every):
        raise InputError(f"resume: {path} is a run of n_steps = {meta['n_steps']}, record_every "
                         f"= {meta['record_every']}; this call asks {n_steps}, {record_every}")
    mine = jax.tree_util.tree_map(np.shape, state.particles)
    theirs = jax.tree_util.tree_map(np.shape, rd.state.particles)
    if mine != theirs:
        raise InputError(f"resume: the particles in {path} have other shapes than the state "
                         f"given (another specimen?)")
    records = (rd.history or {}).get("records") or {}
    return rd.state, rd.config, ([records] if records else []), int(meta["records_done"])


def _chunk_records(total: int, target: int) -> int:
    """Records per chunk: the largest divisor of ``total`` not above ``target`` when
    that is at least half of it (one compiled chunk serves the whole run), else ``target``."""
    if total <= target:
        return total
    best = max(d for d in range(1, target + 1) if total % d == 0)
    return best if 2 * best >= target else target


def _strong(tree):
    """Drop JAX's weak types (e.g. from ``jnp.asarray(0.1)``), which would make
    an otherwise identical call recompile."""
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=jnp.asarray(a).dtype), tree)


def _stack(history, batched):
    if not history:
        return {}
    out = {k: np.concatenate([h[k] for h in history], axis=0) for k in history[0]}
    if batched:
        out = {k: np.swapaxes(v, 0, 1) for k, v in out.items()}
    return out
