"""Tangential contact history across neighbour-list rebuilds that reorder the list.

The list holds each pair (i < j) once, sorted by (i, j), valid rows first, so a
pair's row moves whenever a pair with a smaller key enters or leaves.  The
history must follow the pair, not the row: after a rebuild a pair that was
listed before keeps its own value exactly, a pair that is new starts at zero,
and so does a pair that left the list and came back.  Every case below moves
particles so that surviving pairs change rows, and checks that they did; where
the new row held another pair before, a copy by row position would give a
wrong, non-zero value, and where it was a padding row, a wrong zero.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdem
from jdem import neighbors

R = 1e-3
SKIN = 2e-4


def listed(c):
    """{(i, j): row} of the valid rows."""
    i, j, v = (np.asarray(a) for a in (c.i, c.j, c.valid))
    return {(int(a), int(b)): r for r, (a, b) in enumerate(zip(i, j)) if v[r]}


def history(c):
    """{(i, j): shear row (d,)} of the valid rows."""
    s = np.asarray(c.shear)
    return {k: s[r] for k, r in listed(c).items()}


def tag(key, dim):
    """A distinct, exactly representable history for pair (i, j)."""
    i, j = key
    base = np.array([1.0, -0.5, 0.25][:dim])
    return (1000.0 * i + j + 1.0) * base


def tagged(c, dim):
    """The list with every valid row's shear set to ``tag`` of its pair."""
    shear = np.zeros(c.shear.shape)
    for k, r in listed(c).items():
        shear[r] = tag(k, dim)
    return c._replace(shear=jnp.asarray(shear))


def brute_pairs(pos, rad, skin):
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    ii, jj = np.nonzero(np.triu(dist < rad[:, None] + rad[None] + skin, k=1))
    return set(zip(ii.tolist(), jj.tolist()))


def moved(p, pos):
    return p._replace(pos=jnp.asarray(pos, p.pos.dtype))


def assert_carried(new, expected_history):
    """Surviving pairs equal their own history exactly, all others are zero, and
    padding rows are zero too."""
    got = history(new)
    for k, h in got.items():
        np.testing.assert_array_equal(h, expected_history.get(k, np.zeros_like(h)),
                                      err_msg=f"pair {k}")
    pad = ~np.asarray(new.valid)
    assert np.all(np.asarray(new.shear)[pad] == 0)


def row_changes(old, new):
    """Surviving pairs whose row changed (``moved``), and those of them whose new
    row held another pair before (``reused``)."""
    before, after = listed(old), listed(new)
    by_row = {r: k for k, r in before.items()}
    moved_ = {k for k, r in after.items() if k in before and before[k] != r}
    reused = {k for k in moved_ if after[k] in by_row}
    return moved_, reused


# --------------------------------------------------------------------------- a hand-made case

def line_of_pairs():
    """2D, R = 1 mm: pairs (0,1), (2,3), (4,5), (4,9) overlapping; 6, 7, 8 far away."""
    pos = np.array([[0.000, 0.0], [0.0019, 0.0],      # (0, 1)
                    [0.010, 0.0], [0.0119, 0.0],      # (2, 3)
                    [0.020, 0.0], [0.0219, 0.0],      # (4, 5)
                    [0.030, 0.0], [0.040, 0.0], [0.050, 0.0],
                    [0.020, 0.0019]])                 # (4, 9)
    return pos


def test_surviving_pairs_keep_their_own_history_when_rows_shift():
    pos = line_of_pairs()
    p = jdem.make_particles(pos, np.full(len(pos), R), capacity=len(pos) + 2)
    state, cfg = jdem.make_state(p, skin=SKIN)
    c = tagged(state.contacts, 2)
    before = listed(c)
    assert list(before) == [(0, 1), (2, 3), (4, 5), (4, 9)]
    assert [before[k] for k in before] == [0, 1, 2, 3]
    # 1 leaves particle 0, 7 and 6 join it (two new pairs ahead of every other),
    # 8 joins 3 (a new pair between the survivors), 5 and 9 shift a little but stay
    new = np.vstack([pos, np.zeros((2, 2))])
    new[1] = [0.060, 0.0]
    new[7] = [-0.0019, 0.0]
    new[6] = [0.0, 0.0019]
    new[8] = [0.0119, 0.0019]
    new[5] = [0.02185, 0.0001]
    new[9] = [0.0201, 0.00195]
    rebuilt = neighbors.build(c, moved(p, new), cfg)
    after = listed(rebuilt)
    assert list(after) == [(0, 6), (0, 7), (2, 3), (3, 8), (4, 5), (4, 9)]
    assert set(after) == brute_pairs(new[:10], np.full(10, R), SKIN)
    moved_, reused = row_changes(c, rebuilt)
    assert moved_ == {(2, 3), (4, 5), (4, 9)} and reused == {(2, 3)}
    expected = {k: tag(k, 2) for k in before}
    assert_carried(rebuilt, expected)
    got = history(rebuilt)
    for k in [(0, 6), (0, 7), (3, 8)]:
        assert np.all(got[k] == 0), k
    for k in [(2, 3), (4, 5), (4, 9)]:
        assert np.all(got[k] != 0) and np.all(got[k] == tag(k, 2)), k


def test_a_pair_that_leaves_and_returns_starts_from_zero():
    pos = line_of_pairs()
    p = jdem.make_particles(pos, np.full(len(pos), R), capacity=len(pos) + 2)
    pos = np.vstack([pos, np.zeros((2, 2))])                # the padding rows
    state, cfg = jdem.make_state(p, skin=SKIN)
    c0 = tagged(state.contacts, 2)
    # step 1: 3 leaves 2, 8 comes to 0 (a new first pair), 5 leaves 4
    away = pos.copy()
    away[3] = [0.0125, 0.004]
    away[8] = [-0.0019, 0.0]
    away[5] = [0.023, 0.003]
    c1 = neighbors.build(c0, moved(p, away), cfg)
    assert list(listed(c1)) == [(0, 1), (0, 8), (4, 9)]
    assert row_changes(c0, c1) == ({(4, 9)}, {(4, 9)})
    assert_carried(c1, {k: tag(k, 2) for k in listed(c0)})
    # the new pair gets its own history before the next rebuild
    c1 = c1._replace(shear=c1.shear.at[listed(c1)[(0, 8)]].set(jnp.array([7.0, -3.0])))
    # step 2: 3 and 5 come back to where they were
    back = away.copy()
    back[3], back[5] = pos[3], pos[5]
    c2 = neighbors.build(c1, moved(p, back), cfg)
    assert list(listed(c2)) == [(0, 1), (0, 8), (2, 3), (4, 5), (4, 9)]
    assert row_changes(c1, c2)[0] == {(4, 9)}
    # (2, 3) now sits in the row (4, 9) held
    got = history(c2)
    assert np.all(got[(2, 3)] == 0) and np.all(got[(4, 5)] == 0)   # returned: zero
    np.testing.assert_array_equal(got[(0, 1)], tag((0, 1), 2))
    np.testing.assert_array_equal(got[(4, 9)], tag((4, 9), 2))
    np.testing.assert_array_equal(got[(0, 8)], [7.0, -3.0])


# --------------------------------------------------------------------------- random shuffles

@pytest.mark.parametrize("dim", [2, 3])
def test_history_follows_pairs_through_random_moves(dim):
    """Dense random packings, three successive random moves (some pairs leave,
    some enter, rows shift), and a re-allocation into a larger list: every
    listed pair's history is the value it had when last listed continuously,
    zero for pairs new to the list."""
    rng = np.random.default_rng(11 + dim)
    n = 160
    box = 0.02 if dim == 2 else 0.009
    pos = rng.uniform(0, box, size=(n, dim))
    rad = rng.uniform(0.6e-3, 1.0e-3, size=n)
    p = jdem.make_particles(pos, rad)
    cfg = jdem.make_config(p, skin=SKIN).replace(max_per_cell=16)
    c = neighbors.build(neighbors.empty(p, 8 * n), p, cfg)  # room for the moves below
    assert not bool(neighbors.overflowed(c, cfg))
    c = tagged(c, dim)
    expected = history(c)
    assert len(expected) > 2 * n if dim == 3 else len(expected) > n
    hubs, returned, seen = 0, 0, set(expected)
    for step in range(3):
        pos = pos + rng.normal(scale=4e-4, size=pos.shape)
        new = neighbors.build(c, moved(p, pos), cfg)
        assert not bool(neighbors.overflowed(new, cfg))
        after = listed(new)
        assert set(after) == brute_pairs(pos, rad, SKIN)
        kept = set(after) & set(listed(c))
        returned += len((set(after) - kept) & seen)   # listed before, left, back now
        seen |= set(after)
        assert len(kept) > 0.3 * len(after)
        assert len(set(after) - kept) > 10 and len(set(listed(c)) - kept) > 10
        _, reused = row_changes(c, new)
        assert len(reused) > 0.5 * len(kept)
        assert_carried(new, expected)
        # the next history: the survivors' values, plus a fresh tag on the new
        # pairs (offset so that it differs from the tag the pair may have had)
        shear = np.asarray(new.shear).copy()
        for k, r in after.items():
            if k not in kept:
                shear[r] = tag(k, dim) + 0.125 * (step + 1)
        c = new._replace(shear=jnp.asarray(shear))
        expected = history(c)
        i_counts = np.bincount([k[0] for k in after], minlength=n)
        hubs = max(hubs, int(i_counts.max()))
    assert hubs >= 4            # some particle i heads a run of several pairs
    assert returned > 5         # pairs back in the list after leaving it: zero, as checked
    # re-allocation into a larger list, at moved positions once more
    pos = pos + rng.normal(scale=2e-4, size=pos.shape)
    big, _ = neighbors.reallocate(c, moved(p, pos), cfg, capacity=c.i.shape[0] + 37)
    assert big.i.shape[0] == c.i.shape[0] + 37
    assert set(listed(big)) == brute_pairs(pos, rad, SKIN)
    assert len(row_changes(c, big)[1]) > 10
    assert_carried(big, expected)


# --------------------------------------------------------------------------- through the engine

def slide_and_intrude(intruder_speed):
    """2D, all velocities prescribed: particle 2 slides over the fixed particle 1
    (an elastic tangential contact building up history), particle 0 moves in on
    the fixed particle 3 at ``intruder_speed``.  When it arrives, pair (0, 3)
    enters the list ahead of (1, 2)."""
    pos = np.array([[0.006 - 2 * R - 5e-5, 0.0],       # 0: the intruder
                    [0.0, 0.0],                         # 1: fixed
                    [0.0, 2 * R - 1e-5],                # 2: slides along +x
                    [0.006, 0.0]])                      # 3: fixed
    vel = np.array([[intruder_speed, 0.0], [0.0, 0.0], [0.01, 0.0], [0.0, 0.0]])
    p = jdem.make_particles(pos, np.full(4, R), vel=vel, fixed_vel=np.ones((4, 2), bool),
                            fixed_rot=np.ones(4, bool))
    return p


def observe_pair_12(state, params, config):
    c = state.contacts
    hit = c.valid & (c.i == 1) & (c.j == 2)
    row = jnp.argmax(hit)
    return {"shear": jnp.where(jnp.any(hit), c.shear[row], 0.0), "row": row,
            "n_builds": c.n_builds}


def test_engine_history_is_independent_of_list_order():
    """The tangential force of the sliding pair (1, 2) is the same whether or not
    a pair entering ahead of it moves its row during the contact."""
    params = jdem.make_params(dim=2, dt=1e-5, kn=1e8, ks=1e6, friction=0.5)
    quiet, cfg = jdem.make_state(slide_and_intrude(0.0), skin=1e-5)
    run = jax.jit(lambda s: jdem.rollout(s, params, cfg, 80, 5, observe_pair_12))
    runs = {}
    for name, speed in (("quiet", 0.0), ("intruder", 0.05)):
        final, hist = run(quiet._replace(particles=slide_and_intrude(speed)))
        assert not bool(neighbors.overflowed(final.contacts, cfg))
        runs[name] = jax.tree_util.tree_map(np.asarray, (final, hist))
    (fq, hq), (fi, hi) = runs["quiet"], runs["intruder"]
    # both rebuilt many times; only with the intruder did the pair change rows
    assert hq["n_builds"][-1] >= 6 and hi["n_builds"][-1] > hq["n_builds"][-1]
    assert np.all(hq["row"] == 0)
    assert hi["row"][0] == 0 and hi["row"][-1] == 1
    assert (0, 3) in listed(fi.contacts) and (0, 3) not in listed(fq.contacts)
    # a real, growing elastic history on particle 1: k_t times the slide of 2 over
    # it (0.01 m/s for 400 steps of 1e-5 s), far below the slip limit mu F_n = 500 N
    sx = hq["shear"][:, 0]
    assert np.all(np.diff(sx) > 0) and abs(sx[-1] / (1e6 * 0.01 * 400 * 1e-5) - 1) < 1e-3
    np.testing.assert_array_equal(hi["shear"], hq["shear"])
