"""Building a simulation and running it.

* :func:`make_state` assembles particles, walls and bonds into a ``State`` and
  sizes the neighbour list.
* :func:`rollout` is the pure, differentiable core: ``lax.scan`` over records,
  each record ``record_every`` steps, each record block wrapped in
  ``jax.checkpoint`` so reverse-mode memory grows with the number of records,
  not steps.  It works under ``jax.grad`` and ``jax.vmap``.
* :func:`run` is the host loop around it, one jitted chunk of records at a time.
  Between chunks it

  - checks the neighbour list: on overflow it re-allocates larger from the
    chunk's starting state and runs the chunk again (nothing is dropped);
  - checks for NaN/Inf: it stops with :class:`SimulationDiverged`, which names
    the first bad step and carries the last good state (the state one step
    before it);
  - shows a progress bar (tqdm) and collects the history.
"""
from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import integrate, neighbors
from jdem.measure import basic_observables
from jdem.state import Config, Params, State, empty_bonds, no_walls
from jdem.validate import InputError, check_materials, check_params, check_particles, require_int


class RunResult(NamedTuple):
    """state: final State; config: the Config in force at the end (capacities may
    have grown); history: dict of NumPy arrays, records along axis 0 (batched
    runs: batch along axis 0, records along axis 1)."""

    state: State
    config: Config
    history: dict


class SimulationDiverged(RuntimeError):
    """A position or velocity became NaN/Inf.  ``step`` is the first bad step;
    ``last_good_state`` the state just before it; ``history`` what was recorded."""

    def __init__(self, step, last_good_state, history):
        super().__init__(
            f"simulation diverged: non-finite positions/velocities at step {step}; "
            f"the last good state (step {step}) is kept in .last_good_state "
            f"(is params.dt below the critical step? see jdem.timestep)")
        self.step = step
        self.last_good_state = last_good_state
        self.history = history


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
    The neighbour list must be large enough (check ``neighbors.overflowed`` on
    the result); :func:`run` does that for you.  ``boundary = (fn, data)``
    adds boundary conditions to every step (see :func:`jdem.integrate.physics_step`).
    """
    observe = observe or basic_observables
    step_fn = integrate.step_batched if batched else integrate.step
    obs = jax.vmap(observe, in_axes=(0, 0, None)) if batched else observe

    def one_step(s, _):
        return step_fn(s, params, config, boundary), None

    def block(s, _):
        s, _ = jax.lax.scan(one_step, s, None, length=record_every)
        return s, obs(s, params, config)

    if checkpoint:
        block = jax.checkpoint(block)
    return jax.lax.scan(block, state, None, length=n_records)


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
        batched=False, check_dt=True, desc="jdem", boundary=None) -> RunResult:
    """Run ``n_steps`` steps in jitted chunks; see the module docstring.

    n_steps       total steps; must be a multiple of ``record_every``
    record_every  steps between history records
    observe       ``observe(state, params, config) -> dict of arrays`` (default
                  :func:`jdem.measure.basic_observables`); must be a module-level
                  function or otherwise reused object so compiled chunks are cached
    chunk_steps   steps per jitted chunk (default about 5,000, a multiple of record_every)
    batched       leading batch axis on state and params (a parameter sweep)
    check_dt      raise if ``params.dt`` exceeds the critical step
    boundary      optional ``(fn, data)`` boundary conditions applied every step
                  (see :func:`jdem.integrate.physics_step`); ``fn`` must be a
                  module-level function so compiled chunks are cached, ``data``
                  a pytree (batched runs: leading batch axis)
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
    done = 0
    try:
        while done < total_records:
            n_rec = min(per_chunk, total_records - done)
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
            bad = np.asarray(new_state.first_bad_step)
            if np.any(bad >= 0):
                first = int(np.min(bad[bad >= 0]))
                start = int(np.min(np.asarray(state.step)))
                good = advance(state, params, config, first - start, batched=batched,
                               boundary=_with(boundary_fn, data))
                raise SimulationDiverged(first, good, _stack(history, batched))
            history.append(jax.tree_util.tree_map(np.asarray, hist))
            state = new_state
            done += n_rec
            if bar is not None:
                bar.update(n_rec * record_every)
    finally:
        if bar is not None:
            bar.close()
    return RunResult(state, config, _stack(history, batched))


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
