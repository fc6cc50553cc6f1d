"""Cell-list neighbour search with a fixed capacity and overflow detection
(000 §2.3.3 "分格检索", §4.5.1).
Citations ("000 §2.3.3") refer to the documents listed in REFERENCES.md.

The domain is cut into a regular grid of cells of edge ``Config.cell_size``
(>= largest diameter + skin).  Each particle is checked only against particles
in its own and the adjacent cells (3**d cells), so a build is O(N).  The list
keeps every pair (i < j) whose gap is below ``Config.skin``; it stays valid
until some particle has moved (or grown) by half the skin, when it is rebuilt.

Capacities are static (JAX needs fixed shapes): C pairs (the length of the
``Contacts`` arrays) and
``Config.max_per_cell`` particles per cell.  A build that finds more records
how many it needed (``Contacts.n_pairs``, ``Contacts.max_in_cell``); the host
loop in :mod:`jdem.simulate` sees :func:`overflowed`, re-allocates larger and
re-runs the chunk, so a contact is never dropped silently.

The list holds each pair once, as i < j, sorted by (i, j).  Tangential contact
history survives a rebuild: every pair of the new list looks for its (i, j)
among the old rows of particle i.  Bonded pairs (see :mod:`jdem.bond`)
are excluded: the bond owns them.
"""
from __future__ import annotations

import functools
import itertools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem.kinematics import dot
from jdem.state import Config, Contacts, Particles, aligned_rows


# ----------------------------------------------------------------------------- grid
class SearchGrid(NamedTuple):
    """The lengths of the search grid as arrays: ``origin`` (d,) [m], ``cell_size``
    [m] and ``skin`` [m] (see :class:`jdem.state.Config`).  :func:`build` takes
    them as arguments rather than as part of its static ``Config``, so that one
    compiled build serves every grid of the same shape."""
    origin: jax.Array
    cell_size: jax.Array
    skin: jax.Array


def search_grid(config: Config, dtype) -> SearchGrid:
    """The :class:`SearchGrid` of ``config`` in the positions' ``dtype``."""
    return SearchGrid(origin=jnp.asarray(config.grid_origin, dtype),
                      cell_size=jnp.asarray(config.cell_size, dtype),
                      skin=jnp.asarray(config.skin, dtype))


def _shape_key(config: Config) -> Config:
    """The fields a build's program depends on (dimension, grid shape, cell
    capacity); the others take fixed values, so that they do not recompile it."""
    return Config(dim=config.dim, grid_origin=(0.0,) * config.dim,
                  grid_shape=tuple(config.grid_shape), max_per_cell=config.max_per_cell)


def _cell_coords(pos, config: Config, grid: SearchGrid):
    shape = jnp.asarray(config.grid_shape, jnp.int32)
    c = jnp.floor((pos - grid.origin) / grid.cell_size).astype(jnp.int32)
    # clamping keeps neighbouring particles in neighbouring cells: still exact
    return jnp.clip(c, 0, shape - 1)


def _ravel(coords, config: Config):
    idx = jnp.zeros(coords.shape[:-1], jnp.int32)
    for axis, n in enumerate(config.grid_shape):
        idx = idx * n + coords[..., axis]
    return idx


def _stencil(dim):
    return np.array(list(itertools.product((-1, 0, 1), repeat=dim)), dtype=np.int32)


def _sort_pairs(major, minor, major_max, n_minor):
    """Integer pairs sorted by (major, minor): major in [0, major_max], minor in
    [0, n_minor).  Through one int32 key major * n_minor + minor when it fits:
    sorting a single array is ~4x faster on XLA:CPU than a two-key sort or a
    stable argsort."""
    if (major_max + 1) * n_minor < 2**31:
        key = jnp.sort(major * n_minor + minor)
        return key // n_minor, key % n_minor
    return jax.lax.sort((major, minor), num_keys=2)


def cell_table(particles: Particles, config: Config, grid: SearchGrid):
    """Particles sorted into cells: table (n_cells + 1, K) of particle ids, N = empty.

    Returns the table, each particle's cell coordinates and the fullest cell's count.
    """
    n = particles.pos.shape[0]
    k = config.max_per_cell
    coords = _cell_coords(particles.pos, config, grid)
    cell = jnp.where(particles.valid, _ravel(coords, config), config.n_cells)
    sorted_cell, order = _sort_pairs(cell, jnp.arange(n, dtype=jnp.int32), config.n_cells, n)
    first = jnp.searchsorted(sorted_cell, sorted_cell, side="left")
    rank = jnp.arange(n, dtype=jnp.int32) - first.astype(jnp.int32)
    in_grid = sorted_cell < config.n_cells
    max_in_cell = jnp.max(jnp.where(in_grid, rank + 1, 0), initial=0)
    slot = jnp.where(in_grid & (rank < k), rank, k)  # k is out of range: dropped
    table = jnp.full((config.n_cells + 1, k), n, jnp.int32)
    table = table.at[sorted_cell, slot].set(order.astype(jnp.int32), mode="drop")
    return table, coords, max_in_cell


def candidates(particles: Particles, config: Config, grid: SearchGrid):
    """All (i, j) with j in a cell adjacent to i's: arrays (N, M) with M = 3**d * K.

    Row i lists the table rows of i's 3**d neighbour cells in stencil order (N marks
    an empty slot).  When the grid has no more cells than particles, the 3**d
    shifted copies of the padded cell grid are first stacked into one neighbour-cell
    table (n_cells, M), so that each particle gathers one contiguous row instead of
    3**d short ones (same result, fewer scattered reads); on sparse grids the
    per-particle gather is kept, whose size does not grow with the empty cells.
    """
    n = particles.pos.shape[0]
    table, coords, max_in_cell = cell_table(particles, config, grid)
    if config.n_cells <= n:
        shape = tuple(config.grid_shape)
        by_cell = table[:config.n_cells].reshape(shape + (config.max_per_cell,))
        padded = jnp.pad(by_cell, [(1, 1)] * config.dim + [(0, 0)], constant_values=n)
        shifted = [padded[tuple(slice(1 + int(o), 1 + int(o) + g) for o, g in zip(s, shape))]
                   for s in _stencil(config.dim)]
        neighbour_cells = jnp.stack(shifted, axis=config.dim).reshape(config.n_cells, -1)
        return neighbour_cells[_ravel(coords, config)], max_in_cell
    shape = jnp.asarray(config.grid_shape, jnp.int32)
    neigh = coords[:, None, :] + jnp.asarray(_stencil(config.dim))[None]  # (N, S, d)
    inside = jnp.all((neigh >= 0) & (neigh < shape), axis=-1)
    cells = jnp.where(inside, _ravel(neigh, config), config.n_cells)
    return table[cells].reshape(n, -1), max_in_cell  # (N, S*K)


# ----------------------------------------------------------------------------- search
def _bonded(bonds, cand):
    """Mask (N, M): is candidate ``cand[i, k]`` bonded to particle i?

    Bonds are sorted by (i, j), so particle i's partners j > i sit in one run
    ``bonds.j[start_i:end_i]``; a short binary search inside that run suffices
    (7 halvings cover up to 127 bonds per particle, far above what packed discs
    or spheres reach).
    """
    n = cand.shape[0]
    n_bonds = jnp.sum(bonds.valid).astype(jnp.int32)
    size = bonds.i.shape[0]
    keys = jnp.where(jnp.arange(size) < n_bonds, bonds.i, n)
    rows = jnp.arange(n, dtype=jnp.int32)
    start = jnp.searchsorted(keys, rows, side="left").astype(jnp.int32)
    end = jnp.searchsorted(keys, rows, side="right").astype(jnp.int32)
    lo = jnp.broadcast_to(start[:, None], cand.shape)
    hi = jnp.broadcast_to(end[:, None], cand.shape)
    for _ in range(7):
        mid = (lo + hi) // 2
        less = bonds.j[jnp.clip(mid, 0, size - 1)] < cand
        active = lo < hi
        lo = jnp.where(active & less, mid + 1, lo)
        hi = jnp.where(active & ~less, mid, hi)
    at = jnp.clip(lo, 0, size - 1)
    return (lo < end[:, None]) & (bonds.j[at] == cand)


def _compact(mask, cand, cap, max_per_cell):
    """Lay the kept candidates ``cand[mask]`` (N, M) out row after row in ``cap`` slots.

    Each row of the mask is cut into groups of w <= 31 slots (one neighbour cell
    per group when ``max_per_cell`` <= 31) and every group is packed into an int32
    bit set by a reduction.  Bit counts give each group's exclusive prefix within
    its row and each row's start in the list; then every list slot finds its row
    (binary search over the row ends), its group (binary search over the row's
    prefixes) and its bit (a scan over w bits); a sort of the kept pairs' keys
    finally orders each row by partner.  A per-row sort of all (N, M) candidates
    instead cost ~3x this whole build.  Packing by a reduction also
    makes XLA keep the (N, M / w) bit sets in memory, whereas gathering straight
    from the mask made it recompute the distance test inside every gather.

    Returns ``(i, j, valid, count)``: (cap,) arrays sorted by (i, j), valid rows
    first, and the number of kept pairs (may exceed cap).
    """
    n, m = cand.shape
    w = min(max_per_cell, 31)
    groups = -(-m // w)
    if groups * w != m:  # pad the rows to whole groups with empty slots
        mask = jnp.pad(mask, ((0, 0), (0, groups * w - m)))
        cand = jnp.pad(cand, ((0, 0), (0, groups * w - m)), constant_values=n)
    bits = jnp.asarray([1 << b for b in range(w)], jnp.int32)
    code = jnp.sum(jnp.where(mask.reshape(n, groups, w), bits, 0), axis=2)  # (N, G)
    per_group = jax.lax.population_count(code)
    before = jnp.cumsum(per_group, axis=1) - per_group  # exclusive prefix in the row
    per_row = before[:, -1] + per_group[:, -1]
    ends = jnp.cumsum(per_row)
    count = ends[-1]
    slot = jnp.arange(cap, dtype=jnp.int32)
    row = jnp.minimum(jnp.searchsorted(ends, slot, side="right"), n - 1).astype(jnp.int32)
    rank = slot - (ends[row] - per_row[row])  # index of the pair within its row
    # the row's group holding that pair: the last group whose prefix is <= rank
    flat_before = before.reshape(-1)
    lo, hi = jnp.zeros_like(rank), jnp.full_like(rank, groups)
    for _ in range(math.ceil(math.log2(groups + 1))):
        mid = (lo + hi) // 2
        le = flat_before[row * groups + jnp.minimum(mid, groups - 1)] <= rank
        active = lo < hi
        lo, hi = jnp.where(active & le, mid + 1, lo), jnp.where(active & ~le, mid, hi)
    group = jnp.clip(lo - 1, 0, groups - 1)
    at = row * groups + group
    target = rank - flat_before[at]  # the pair is the target-th set bit of the group
    word = code.reshape(-1)[at]
    seen, bit_at = jnp.zeros_like(rank), jnp.zeros_like(rank)
    for b in range(w):
        bit = (word >> b) & 1
        bit_at = jnp.where((bit > 0) & (seen == target), b, bit_at)
        seen = seen + bit
    valid = slot < count
    new_j = cand.reshape(-1)[at * w + bit_at].astype(jnp.int32)
    # order each row by partner (empty slots, as row n, last): the list, and the
    # order in which a particle's contact forces are summed, then do not depend on
    # the grid
    row, new_j = _sort_pairs(jnp.where(valid, row, n), new_j, n, n)
    return jnp.where(valid, row, 0), jnp.where(valid, new_j, 0), valid, count


def carry_history(contacts: Contacts, new_i, new_j, valid, n):
    """Tangential history (cap, d) of the new pairs: the old row's value where (i, j)
    was listed before, else 0.  The old list is grouped by i, so each new pair scans
    the old rows of its particle i (a loop as long as the longest such run)."""
    size = contacts.i.shape[0]
    if size == 0:
        return jnp.zeros(new_i.shape + contacts.shear.shape[1:], contacts.shear.dtype)
    n_old = jnp.sum(contacts.valid).astype(jnp.int32)
    keys = jnp.where(jnp.arange(size) < n_old, contacts.i, n)  # valid rows come first
    start = jnp.searchsorted(keys, jnp.arange(n + 1, dtype=jnp.int32), side="left")
    start = start.astype(jnp.int32)
    first, stop = start[new_i], start[new_i + 1]

    def scan_one_more(carry):
        k, old_row, found = carry
        at = jnp.minimum(first + k, size - 1)
        hit = (first + k < stop) & (contacts.j[at] == new_j)
        return k + 1, jnp.where(hit, at, old_row), found | hit

    longest = jnp.max(start[1:] - start[:-1])
    _, old_row, found = jax.lax.while_loop(
        lambda carry: carry[0] < longest, scan_one_more,
        (jnp.zeros((), jnp.int32), jnp.zeros_like(new_i), jnp.zeros(new_i.shape, bool)))
    return jnp.where((found & valid)[:, None], contacts.shear[old_row], 0.0)


# ----------------------------------------------------------------------------- build
def candidate_mask(particles: Particles, cand, config: Config, grid: SearchGrid, bonds=None):
    """(N, M) bool: the candidates ``cand`` (N, M) of :func:`candidates` that
    :func:`build` lists: real partners j > i of valid particles whose gap is
    below ``grid.skin``, and not bonded to i (bonded pairs interact through
    their bond only)."""
    n = particles.pos.shape[0]
    ii = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32)[:, None], cand.shape)
    real = (cand < n) & (cand > ii) & particles.valid[:, None]
    # gap test one component at a time (N,) -> (N, M): no (N, M, d) temporaries
    partner = jnp.minimum(cand, n - 1)   # empty slots are masked by ``real``
    gap2 = 0.0
    for axis in range(config.dim):
        x = particles.pos[:, axis]
        gap2 = gap2 + (x[partner] - x[:, None]) ** 2
    reach = particles.radius[partner] + particles.radius[:, None] + grid.skin
    mask = real & (gap2 < reach * reach)
    if bonds is not None and bonds.i.shape[0] > 0:
        mask = mask & ~_bonded(bonds, cand)
    return mask


def build(contacts: Contacts, particles: Particles, config: Config, bonds=None) -> Contacts:
    """Rebuild the pair list from scratch at the current positions (jit-able).

    Keeps the tangential history of pairs that were already listed.  Records
    the space it needed so that the host can detect overflow.
    """
    return _build(contacts, particles, _shape_key(config),
                  search_grid(config, particles.pos.dtype), bonds)


@functools.partial(jax.jit, static_argnames=("config",))
def _build(contacts: Contacts, particles: Particles, config: Config, grid: SearchGrid,
           bonds=None) -> Contacts:
    n = particles.pos.shape[0]
    cap = contacts.i.shape[0]
    cand, max_in_cell = candidates(particles, config, grid)
    mask = candidate_mask(particles, cand, config, grid, bonds)
    new_i, new_j, valid, count = _compact(mask, cand, cap, config.max_per_cell)
    shear = carry_history(contacts, new_i, new_j, valid, n)
    return Contacts(
        i=new_i, j=new_j, valid=valid, shear=shear,
        pos_at_build=particles.pos, radius_at_build=particles.radius,
        n_pairs=jnp.maximum(contacts.n_pairs, count.astype(contacts.n_pairs.dtype)),
        max_in_cell=jnp.maximum(contacts.max_in_cell, max_in_cell.astype(jnp.int32)),
        n_builds=contacts.n_builds + 1)


def needs_rebuild(contacts: Contacts, particles: Particles, config: Config):
    """True when a pair outside the list could now be within contact: some particle
    moved by more than half the skin (growth of radii counted too)."""
    moved = particles.pos - contacts.pos_at_build
    disp = jnp.sqrt(jnp.max(jnp.where(particles.valid, dot(moved, moved), 0.0), initial=0.0))
    grow = jnp.max(jnp.where(particles.valid, particles.radius - contacts.radius_at_build, 0.0),
                   initial=0.0)
    return 2.0 * disp + 2.0 * jnp.maximum(grow, 0.0) >= config.skin


def update(contacts: Contacts, particles: Particles, config: Config, bonds=None) -> Contacts:
    """Rebuild if needed (``lax.cond``), else return the list unchanged."""
    return jax.lax.cond(needs_rebuild(contacts, particles, config),
                        lambda c: build(c, particles, config, bonds), lambda c: c, contacts)


def overflowed(contacts: Contacts, config: Config):
    """True if some build since allocation did not fit (works on batched lists too)."""
    return jnp.any((contacts.n_pairs > contacts.i.shape[-1]) |
                   (contacts.max_in_cell > config.max_per_cell))


def empty(particles: Particles, capacity: int) -> Contacts:
    """An unbuilt list of the given capacity (forces a build on first use)."""
    cap = int(capacity)
    n, d = particles.pos.shape
    dtype = particles.pos.dtype
    return Contacts(
        i=jnp.zeros((cap,), jnp.int32), j=jnp.zeros((cap,), jnp.int32),
        valid=jnp.zeros((cap,), bool), shear=jnp.zeros((cap, d), dtype),
        pos_at_build=jnp.full((n, d), jnp.inf, dtype), radius_at_build=particles.radius,
        n_pairs=jnp.zeros((), jnp.int32), max_in_cell=jnp.zeros((), jnp.int32),
        n_builds=jnp.zeros((), jnp.int32))


def grid_for(particles: Particles, *, skin, margin=None, extra_bounds=None):
    """Grid settings (origin, shape, cell size) covering the valid particles.

    ``extra_bounds`` = (lo, hi) widens the box, e.g. to the walls.  Particles that
    later leave the box are clamped into border cells (correct, only slower).
    """
    pos = np.asarray(particles.pos)[np.asarray(particles.valid)]
    rad = np.asarray(particles.radius)[np.asarray(particles.valid)]
    cell = float(2.0 * rad.max() + skin)
    lo, hi = pos.min(axis=0), pos.max(axis=0)
    if extra_bounds is not None:
        lo = np.minimum(lo, extra_bounds[0])
        hi = np.maximum(hi, extra_bounds[1])
    margin = cell if margin is None else margin
    lo = lo - margin
    shape = tuple(int(max(1, math.ceil((h + margin - l) / cell))) for l, h in zip(lo, hi))
    return tuple(float(v) for v in lo), shape, cell


def room_for(need_pairs: int, slack: float = 1.25) -> int:
    """List rows to allocate for ``need_pairs`` pairs: ``slack`` times as many plus
    16, rounded up by :func:`jdem.state.aligned_rows`."""
    return aligned_rows(int(math.ceil(need_pairs * slack)) + 16)


BONDED_SLACK = 2.0   # list rows per pair found, for a bonded assembly (see allocate)


def dense_capacity(particles: Particles, dim: int) -> int:
    """Room for a dense packing: ~3 listed pairs per disc, ~7 per sphere (rounded
    up by :func:`jdem.state.aligned_rows`)."""
    return aligned_rows(int(np.sum(np.asarray(particles.valid))) * (3 if dim == 2 else 7))


def allocate(particles: Particles, config: Config, bonds=None, *, slack=1.25,
             old: Contacts | None = None, min_capacity: int | None = None):
    """Size the list for the current positions and build it (host function).

    Returns ``(contacts, config)``: the list has room for the pairs found times
    ``slack``, and at least ``min_capacity`` rows, so that a run seldom needs a
    re-allocation (each costs a recompilation).  The default: for an assembly
    without bonds :func:`dense_capacity` (a loose assembly may pack down); for a
    bonded one :data:`BONDED_SLACK` times the pairs found, because its bonded
    pairs stay out of the list for good (broken bonds included, see
    :mod:`jdem.bond`) and only pairs that meet across cracks are added
    (measured: a 2,741-disc UCS specimen taken to 4e-3 strain, 374 bonds broken,
    needs 966 rows at the start and at the end, where the dense default gives
    8,223).  ``config.max_per_cell`` is grown if a cell was too full.  If ``old``
    is given its tangential history is kept and its recorded needs count.
    """
    c = build(empty(particles, 1), particles, config, bonds)
    need_pairs, need_cell = int(c.n_pairs), int(c.max_in_cell)
    if old is not None:
        need_pairs = max(need_pairs, int(np.max(np.asarray(old.n_pairs))))
        need_cell = max(need_cell, int(np.max(np.asarray(old.max_in_cell))))
    if need_cell > config.max_per_cell:  # the probe could not see pairs in overfull cells
        return allocate(particles, config.replace(max_per_cell=need_cell + 2), bonds,
                        slack=slack, old=old, min_capacity=min_capacity)
    if min_capacity is None:  # after the merge: twice the most pairs ever seen
        bonded = bonds is not None and bool(np.any(np.asarray(bonds.valid)))
        min_capacity = room_for(need_pairs, BONDED_SLACK) if bonded \
            else dense_capacity(particles, config.dim)
    cap = max(min_capacity, room_for(need_pairs, slack),
              0 if old is None else old.i.shape[-1])
    start = empty(particles, cap) if old is None else _resize(old, cap)
    return build(start, particles, config, bonds), config


def _resize(contacts: Contacts, cap: int) -> Contacts:
    """Copy a list into a larger capacity (rows beyond the old ones invalid) and
    reset its need counters."""
    old_cap = contacts.i.shape[0]
    if cap < old_cap:
        raise ValueError(f"cannot shrink a neighbour list from {old_cap} to {cap} rows")
    pad = lambda a: jnp.concatenate([a, jnp.zeros((cap - old_cap,) + a.shape[1:], a.dtype)])
    return contacts._replace(i=pad(contacts.i), j=pad(contacts.j), valid=pad(contacts.valid),
                             shear=pad(contacts.shear),
                             n_pairs=jnp.zeros((), jnp.int32),
                             max_in_cell=jnp.zeros((), jnp.int32))


def reallocate(contacts: Contacts, particles: Particles, config: Config, bonds=None, *,
               capacity: int | None = None):
    """The one way to give a neighbour list more room (host function).

    The growth policy: the capacity becomes ``capacity`` if given, else
    :func:`room_for` of the most pairs any build found (``contacts.n_pairs``),
    never less than it was; ``config.max_per_cell`` grows to the fullest cell
    seen plus 2.  The list is then rebuilt at the current positions, keeping
    the tangential history of the pairs it holds.  A build whose cells were
    too full counted only the pairs of the members it kept, so the rebuilt list
    may still be short: the sizes then grow to what the rebuild found and the
    rebuild starts again from ``contacts``, so no pair's history is lost to a
    list that was too small and one call is enough.  Works on a batch (leading
    member axis on ``contacts``, ``particles`` and ``bonds``): every member gets
    the same capacity.  Returns ``(contacts, config)``.

    Use it when :func:`overflowed` is true after a run, then run the chunk again
    from its starting state (the host loop of :func:`jdem.run` and of
    :func:`jdem.lab.run` does that for you).
    """
    old_cap = int(contacts.i.shape[-1])
    need_pairs = int(np.max(np.asarray(contacts.n_pairs)))
    need_cell = int(np.max(np.asarray(contacts.max_in_cell)))
    cap = max(old_cap, room_for(need_pairs) if capacity is None else int(capacity))
    while True:
        config = config.replace(max_per_cell=max(config.max_per_cell, need_cell + 2))
        grown = _regrown(contacts, particles, bonds, config, cap)
        if not bool(overflowed(grown, config)):
            return grown, config
        # the rebuild saw more than the failed build could count: size from it
        need_pairs = int(np.max(np.asarray(grown.n_pairs)))
        need_cell = int(np.max(np.asarray(grown.max_in_cell)))
        cap = max(cap, room_for(need_pairs))


@functools.partial(jax.jit, static_argnames=("config", "cap"))
def _regrown(contacts: Contacts, particles: Particles, bonds, config: Config, cap: int):
    """``contacts`` copied into ``cap`` rows and rebuilt (each member of a batch)."""
    def regrow(c, p, b):
        return build(_resize(c, cap), p, config, b)

    return (jax.vmap(regrow) if contacts.i.ndim == 2 else regrow)(contacts, particles, bonds)
