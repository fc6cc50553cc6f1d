"""Cell-list neighbour search against brute force, overflow and history carry-over."""
import jax.numpy as jnp
import numpy as np
import pytest

import jdem
from jdem import neighbors
from jdem.bond import create_bonds


def _brute_pairs(pos, rad, skin):
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    ii, jj = np.nonzero(np.triu(dist < rad[:, None] + rad[None] + skin, k=1))
    return set(zip(ii.tolist(), jj.tolist()))


def _pairs(c, with_shear=False):
    i, j, v, s = (np.asarray(a) for a in (c.i, c.j, c.valid, c.shear))
    if with_shear:
        return {(int(a), int(b)): sh for a, b, sh in zip(i[v], j[v], s[v])}
    return set(zip(i[v].tolist(), j[v].tolist()))


def _tagged(c):
    """``c`` with a history unique to each listed row and component (nonzero)."""
    tag = jnp.arange(c.shear.size, dtype=c.shear.dtype).reshape(c.shear.shape) + 1.0
    return c._replace(shear=jnp.where(c.valid[:, None], tag, 0.0))


@pytest.mark.parametrize("dim", [2, 3])
def test_cell_list_finds_exactly_the_brute_force_pairs(dim):
    rng = np.random.default_rng(3)
    n = 300
    pos = rng.uniform(0, 0.02 if dim == 2 else 0.008, size=(n, dim))
    rad = rng.uniform(0.0004, 0.0008, size=n)
    p = jdem.make_particles(pos, rad, capacity=n + 7)  # padding rows must be ignored
    state, cfg = jdem.make_state(p, skin=2e-4)
    c = state.contacts
    got = _pairs(c)
    assert got == _brute_pairs(pos, rad, 2e-4)
    assert not bool(neighbors.overflowed(c, cfg))
    # particles that leave the grid are clamped into border cells and still found
    moved = np.array(pos)
    moved[:20] += 0.05
    p2 = p._replace(pos=jnp.asarray(np.vstack([moved, np.zeros((7, dim))])))
    c2 = neighbors.build(c, p2, cfg)
    # they crowd into the corner cells: the build must say it ran out of room ...
    assert bool(neighbors.overflowed(c2, cfg))
    # ... and a re-allocation then finds every pair
    c2, cfg2 = neighbors.allocate(p2, cfg, old=c2)
    assert not bool(neighbors.overflowed(c2, cfg2))
    got2 = _pairs(c2)
    assert got2 == _brute_pairs(moved, rad, 2e-4)


def test_overflow_is_flagged_and_pairs_are_sorted():
    rng = np.random.default_rng(0)
    pos = rng.uniform(0, 0.01, size=(200, 2))
    p = jdem.make_particles(pos, np.full(200, 5e-4))
    cfg = jdem.make_config(p, skin=1e-4).replace(max_per_cell=2)
    c = neighbors.build(neighbors.empty(p, 10), p, cfg)
    assert bool(neighbors.overflowed(c, cfg))
    assert int(c.n_pairs) > 10 and int(c.max_in_cell) > 2
    big, cfg2 = neighbors.allocate(p, cfg)
    assert not bool(neighbors.overflowed(big, cfg2))
    v = np.asarray(big.valid)
    keys = list(zip(np.asarray(big.i)[v].tolist(), np.asarray(big.j)[v].tolist()))
    assert keys == sorted(keys) and len(set(keys)) == len(keys) == int(big.n_pairs)
    assert all(i < j for i, j in keys)
    assert not np.any(np.asarray(big.valid)[len(keys):])  # valid rows come first


@pytest.mark.parametrize("dim", [2, 3])
def test_wide_cells_give_the_same_pairs(dim):
    """Cells of more than 31 slots are packed in several bit sets: same pairs."""
    rng = np.random.default_rng(5)
    pos = rng.uniform(0, 0.01 if dim == 2 else 0.005, size=(250, dim))
    p = jdem.make_particles(pos, rng.uniform(3e-4, 5e-4, size=250))
    cfg = jdem.make_config(p, skin=1e-4)
    c, cfg = neighbors.allocate(p, cfg)
    wide, _ = neighbors.allocate(p, cfg.replace(max_per_cell=45))
    assert cfg.max_per_cell <= 31
    assert _pairs(wide) == _pairs(c) == _brute_pairs(pos, np.asarray(p.radius), 1e-4)


def test_history_survives_rebuild_and_bonded_pairs_are_excluded():
    pos = np.array([[0.0, 0.0], [0.0019, 0.0], [0.0038, 0.0], [0.0, 0.0019]])
    p = jdem.make_particles(pos, np.full(4, 1e-3))
    state, cfg = jdem.make_state(p, skin=2e-4)
    c = _tagged(state.contacts)
    before = _pairs(c, with_shear=True)
    rebuilt = neighbors.build(c, p, cfg)
    after = _pairs(rebuilt, with_shear=True)
    assert before.keys() == after.keys()
    for k in before:
        np.testing.assert_array_equal(before[k], after[k])
    bonds = jdem.empty_bonds(2, 2)._replace(i=jnp.array([0, 1], jnp.int32), j=jnp.array([1, 2], jnp.int32),
                                           valid=jnp.array([True, True]))
    excluded = neighbors.build(c, p, cfg, bonds)
    assert _pairs(excluded) == set(before) - {(0, 1), (1, 2)}


def test_a_bonded_assembly_gets_room_for_twice_its_pairs_not_a_dense_packing():
    """The default capacity of jdem.neighbors.allocate: bonded pairs never enter the
    list, so a bonded specimen is sized by the pairs found (BONDED_SLACK), a loose
    one by dense_capacity; either way every pair found is listed."""
    rng = np.random.default_rng(3)
    pos = np.stack(np.meshgrid(np.arange(12), np.arange(12), indexing="ij"), -1).reshape(-1, 2)
    pos = pos * 2.05e-3 + rng.uniform(-5e-5, 5e-5, pos.shape)
    p = jdem.make_particles(pos, np.full(len(pos), 1e-3))
    _, cfg = jdem.make_state(p, skin=2e-4)
    bonds = create_bonds(p, 2, gap_tolerance=0.06e-3)
    free, _ = neighbors.allocate(p, cfg)
    bonded, _ = neighbors.allocate(p, cfg, bonds)
    need = int(bonded.n_pairs)
    assert free.i.shape[0] == neighbors.dense_capacity(p, 2)
    assert bonded.i.shape[0] == max(neighbors.room_for(need, neighbors.BONDED_SLACK),
                                    neighbors.room_for(need))
    assert bonded.i.shape[0] < free.i.shape[0]
    # a re-allocation keeps twice the most pairs ever recorded, not this build's
    seen = bonded._replace(n_pairs=jnp.asarray(3 * need, bonded.n_pairs.dtype))
    again, _ = neighbors.allocate(p, cfg, bonds, old=seen)
    assert again.i.shape[0] == neighbors.room_for(3 * need, neighbors.BONDED_SLACK)
    assert _pairs(bonded) == _brute_pairs(pos, np.full(len(pos), 1e-3), 2e-4) - set(
        zip(np.asarray(bonds.i)[np.asarray(bonds.valid)].tolist(),
            np.asarray(bonds.j)[np.asarray(bonds.valid)].tolist()))


def test_a_pair_is_not_taken_for_bonded_by_the_next_particles_bond():
    """Bonds (0, 1) and (1, 2) of a triangle of touching discs: the pair (0, 2) is
    not bonded (particle 0's run of bonds ends before the bond (1, 2), whose
    partner is also 2) and must be listed; (0, 1) and (1, 2) must not."""
    pos = np.array([[0.0, 0.0], [0.0019, 0.0], [0.00095, 0.0019 * np.sqrt(3) / 2]])
    p = jdem.make_particles(pos, np.full(3, 1e-3))
    state, cfg = jdem.make_state(p, skin=2e-4)
    assert _pairs(state.contacts) == {(0, 1), (0, 2), (1, 2)}
    bonds = jdem.empty_bonds(2, 2)._replace(i=jnp.array([0, 1], jnp.int32),
                                           j=jnp.array([1, 2], jnp.int32),
                                           valid=jnp.array([True, True]))
    assert _pairs(neighbors.build(state.contacts, p, cfg, bonds)) == {(0, 2)}


def test_pairs_are_sorted_also_when_one_int32_key_would_overflow():
    """``_sort_pairs`` packs (major, minor) into one int32 key only while
    (major_max + 1) n_minor < 2^31; at 2^15 + 1 majors of 2^16 minors it must
    sort on two keys, and the order is the lexicographic one either way."""
    rng = np.random.default_rng(0)
    for major_max, n_minor in ((2**15 - 1, 2**16), (2**15, 2**16), (70_000, 70_000)):
        major = rng.integers(0, major_max + 1, 500).astype(np.int32)
        major[:3] = major_max
        minor = rng.integers(0, n_minor, 500).astype(np.int32)
        a, b = neighbors._sort_pairs(jnp.asarray(major), jnp.asarray(minor), major_max, n_minor)
        order = np.lexsort((minor, major))
        np.testing.assert_array_equal(np.asarray(a), major[order])
        np.testing.assert_array_equal(np.asarray(b), minor[order])


def test_a_list_of_no_rows_carries_no_history_and_room_has_a_floor():
    """A rebuild from a list of capacity 0 gives zero tangential history of the
    list's width; ``room_for`` gives slack x the pairs plus 16 rows, rounded up
    to 64 (jdem.state.ROW_ALIGN), so
    a list never starts with no room."""
    p = jdem.make_particles(np.array([[0.0, 0.0], [0.0019, 0.0]]), np.full(2, 1e-3))
    empty = neighbors.empty(p, 0)
    out = neighbors.carry_history(empty, jnp.zeros(4, jnp.int32), jnp.ones(4, jnp.int32),
                                  jnp.ones(4, bool), 2)
    assert out.shape == (4, 2)
    np.testing.assert_array_equal(np.asarray(out), 0.0)
    for need in (0, 1, 100, 1001):
        rows = neighbors.room_for(need)
        assert rows >= 1.25 * need + 16
        assert rows < 1.25 * need + 16 + 1 + 64          # aligned to 64 rows


def test_reallocate_after_a_cell_overflow_lists_every_pair_and_keeps_history():
    """A list built with cells that hold too few particles is flagged.  The
    build counted 268 of the 646 pairs (the rest were lost with the dropped
    cell members), so a list sized from that count alone is still short;
    one ``reallocate`` grows it to what its own rebuild finds and starts that
    rebuild again from the given list, so the result is the brute-force set,
    is not flagged, and every pair the first list held keeps its tangential
    history (a second, truncating rebuild in between would have dropped some)."""
    rng = np.random.default_rng(1)
    pos = rng.uniform(0, 0.01, size=(200, 2))
    rad = np.full(200, 5e-4)
    p = jdem.make_particles(pos, rad)
    cfg = jdem.make_config(p, skin=1e-4).replace(max_per_cell=2)
    c = neighbors.build(neighbors.empty(p, 10), p, cfg)
    assert bool(neighbors.overflowed(c, cfg)) and int(c.max_in_cell) > 3
    assert neighbors.room_for(int(c.n_pairs)) < len(_brute_pairs(pos, rad, 1e-4))
    # mark the held pairs' history with a value unique to each row
    c = _tagged(c)
    before = _pairs(c, with_shear=True)
    out, cfg2 = neighbors.reallocate(c, p, cfg)
    assert not bool(neighbors.overflowed(out, cfg2))
    assert cfg2.max_per_cell >= int(out.max_in_cell)
    assert _pairs(out) == _brute_pairs(pos, rad, 1e-4)
    after = _pairs(out, with_shear=True)
    assert before
    for pair, shear in before.items():
        np.testing.assert_array_equal(after[pair], shear)


def test_padding_rows_never_fill_a_cell():
    """Rows past the particle count (capacity) sit outside the grid: many more of
    them than a cell holds must not flag an overflow nor enter the list."""
    rng = np.random.default_rng(5)
    pos = rng.uniform(0, 0.01, size=(60, 2))
    rad = np.full(60, 5e-4)
    p = jdem.make_particles(pos, rad, capacity=400)
    state, cfg = jdem.make_state(p, skin=1e-4)
    assert 340 > cfg.max_per_cell
    c = neighbors.build(state.contacts, state.particles, cfg)
    assert not bool(neighbors.overflowed(c, cfg))
    assert int(c.max_in_cell) <= cfg.max_per_cell
    assert _pairs(c) == _brute_pairs(pos, rad, 1e-4)


def test_a_sparse_grid_one_cell_high_lists_every_pair_once():
    """A row of discs along x, far apart, on a grid one cell high (a chain or a
    bar; more cells than particles: the per-particle gather of neighbour cells).
    Each pair within reach is listed once, as brute force finds it.  A cell index
    past the top edge, if it were read, would be the next column's cell, a real
    neighbour here: its discs would be listed twice."""
    rng = np.random.default_rng(8)
    x = np.sort(rng.uniform(0, 60.0, 24))
    x[1::4] = x[0::4] + 0.9              # some pairs within reach
    y = np.zeros(24)
    y[1::4] = -0.5
    pos = np.stack([x, y], axis=1)
    rad = np.full(24, 0.5)
    p = jdem.make_particles(pos, rad)
    cfg = jdem.make_config(p, skin=0.1)
    cfg = cfg.replace(grid_shape=(cfg.grid_shape[0], 1))
    assert cfg.n_cells > 24
    c, cfg = neighbors.allocate(p, cfg)
    want = _brute_pairs(pos, rad, 0.1)
    assert len(want) >= 6
    assert _pairs(c) == want
    assert int(np.sum(np.asarray(c.valid))) == len(want)


def test_the_highest_numbered_pair_keeps_its_history():
    """A chain of touching discs, each consecutive pair in contact, the last pair
    being (n - 2, n - 1): a rebuild keeps every pair's history, that last pair's
    too (its run of old rows is the last one the per-particle index reaches)."""
    n = 5
    pos = np.stack([np.arange(n) * 1.9e-3, np.zeros(n)], axis=1)
    p = jdem.make_particles(pos, np.full(n, 1e-3))
    state, cfg = jdem.make_state(p, skin=2e-4)
    c = state.contacts
    assert _pairs(c) == {(k, k + 1) for k in range(n - 1)}
    c = _tagged(c)
    before = _pairs(c, with_shear=True)
    after = _pairs(neighbors.build(c, p, cfg), with_shear=True)
    assert after.keys() == before.keys()
    for pair, shear in before.items():
        assert np.all(shear != 0.0)
        np.testing.assert_array_equal(after[pair], shear)


def test_growing_radii_alone_trigger_a_rebuild():
    """Radii that grow (compaction by expansion) close gaps as motion does: a list
    is stale once twice the growth reaches the skin, with no particle moved."""
    pos = np.array([[0.0, 0.0], [2.5e-3, 0.0]])
    p = jdem.make_particles(pos, np.full(2, 1e-3))
    state, cfg = jdem.make_state(p, skin=4e-4)
    c = state.contacts
    assert not bool(neighbors.needs_rebuild(c, p, cfg))
    assert not bool(neighbors.needs_rebuild(c, p._replace(radius=p.radius + 1.9e-4), cfg))
    assert bool(neighbors.needs_rebuild(c, p._replace(radius=p.radius + 2.1e-4), cfg))
    # shrinking never makes a list stale, and growth adds to motion
    assert not bool(neighbors.needs_rebuild(c, p._replace(radius=p.radius - 5e-4), cfg))
    moved = p._replace(pos=p.pos.at[0, 0].add(1.2e-4), radius=p.radius + 1.2e-4)
    assert bool(neighbors.needs_rebuild(c, moved, cfg))


def test_a_list_that_fits_exactly_is_not_overflowed_and_keeps_its_cells():
    """A list whose every row is used, and cells filled to exactly
    ``max_per_cell``, did fit: no overflow is flagged, and ``allocate`` does not
    grow the cells (a larger ``Config`` would recompile every program)."""
    rng = np.random.default_rng(3)
    pos = rng.uniform(0, 0.01, size=(80, 2))
    rad = np.full(80, 5e-4)
    p = jdem.make_particles(pos, rad)
    cfg = jdem.make_config(p, skin=1e-4)
    want = _brute_pairs(pos, rad, 1e-4)
    c = neighbors.build(neighbors.empty(p, len(want)), p, cfg)
    assert _pairs(c) == want and bool(np.all(np.asarray(c.valid)))
    assert not bool(neighbors.overflowed(c, cfg))
    full = cfg.replace(max_per_cell=int(c.max_in_cell))
    assert not bool(neighbors.overflowed(c, full))
    _, again = neighbors.allocate(p, full)
    assert again.max_per_cell == int(c.max_in_cell)


@pytest.mark.parametrize("dim", [2, 3])
def test_the_grid_covers_particles_and_walls_with_a_margin(dim):
    """``grid_for``: cells of one diameter plus skin, the box of the particles
    widened to ``extra_bounds`` (walls) and by ``margin`` on every side."""
    rng = np.random.default_rng(4)
    pos = rng.uniform(0.2, 0.8, size=(30, dim))
    p = jdem.make_particles(pos, np.full(30, 0.01))
    walls_lo, walls_hi = np.full(dim, -0.3), np.full(dim, 1.4)
    for margin in (0.05, 0.5):
        origin, shape, cell = neighbors.grid_for(p, skin=0.002, margin=margin,
                                                 extra_bounds=(walls_lo, walls_hi))
        assert cell == pytest.approx(0.022)
        top = np.asarray(origin) + np.asarray(shape) * cell
        np.testing.assert_allclose(origin, walls_lo - margin)
        assert np.all(top >= walls_hi + margin) and np.all(top < walls_hi + margin + cell)
    origin, shape, cell = neighbors.grid_for(p, skin=0.002, margin=0.0)
    top = np.asarray(origin) + np.asarray(shape) * cell
    np.testing.assert_allclose(origin, pos.min(axis=0))
    assert np.all(top >= pos.max(axis=0)) and np.all(top < pos.max(axis=0) + cell)


def test_dense_capacity_is_three_rows_per_disc_and_seven_per_sphere():
    """128 particles: 384 rows in 2D and 896 in 3D (both whole multiples of the
    row alignment, so nothing is rounded); invalid rows do not count."""
    for dim, per in ((2, 3), (3, 7)):
        pos = np.zeros((130, dim)) + np.arange(130)[:, None]
        p = jdem.make_particles(pos, np.full(130, 0.1))
        p = p._replace(valid=p.valid.at[-2:].set(False))
        assert neighbors.dense_capacity(p, dim) == 128 * per


def test_grids_of_one_shape_share_a_build_and_each_finds_its_own_pairs():
    """The grid's origin, cell size and skin are arguments of the compiled build,
    not constants in it: builds on two grids of the same shape (the second one
    shifted, with larger cells and a larger skin) each find the brute-force pairs
    of their own skin, and the second reuses the first's program."""
    rng = np.random.default_rng(11)
    pos = rng.uniform(0, 0.01, size=(120, 2))
    rad = rng.uniform(3e-4, 5e-4, size=120)
    p = jdem.make_particles(pos, rad)
    small = jdem.make_config(p, skin=1e-4)
    large = small.replace(skin=4e-4, cell_size=small.cell_size + 3e-4,
                          grid_origin=tuple(o - 2e-3 for o in small.grid_origin))
    compiled = neighbors._build._cache_size()
    for cfg, skin in ((small, 1e-4), (large, 4e-4)):
        c = neighbors.build(neighbors.empty(p, 600), p, cfg)
        assert not bool(neighbors.overflowed(c, cfg))
        assert _pairs(c) == _brute_pairs(pos, rad, skin)
    assert neighbors._build._cache_size() == compiled + 1
    assert _brute_pairs(pos, rad, 4e-4) != _brute_pairs(pos, rad, 1e-4)  # the skins matter
