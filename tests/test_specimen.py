"""Specimen generation: porosity and coordination targets, overlaps, radii,
determinism, the disc shape, bonding and bad input (jdem.specimen)."""
import functools

import numpy as np
import pytest

from jdem import InputError
from jdem.specimen import Specimen, embed, generate, specimen_for_coordination

R2 = (0.3e-3, 0.5e-3)          # disc radii [m]: ~150 discs in the 1 cm square below
SQUARE = (0.01, 0.01)
R3 = (0.4e-3, 0.6e-3)          # sphere radii [m]: ~190 spheres in the 6 mm cube
CUBE = (0.006, 0.006, 0.006)


@pytest.fixture(scope="module")
def rect():
    return generate("rectangle", SQUARE, *R2, target_porosity=0.2, seed=3)


def _arrays(sp: Specimen):
    return (np.asarray(sp.particles.pos, np.float64), np.asarray(sp.particles.radius, np.float64))


def _all_gaps(pos, rad):
    """Gap of every pair i < j (brute force: the specimens here are small)."""
    i, j = np.triu_indices(len(rad), k=1)
    return i, j, np.linalg.norm(pos[j] - pos[i], axis=1) - rad[i] - rad[j]


def _check_packing(sp: Specimen, r_lo, r_hi, limit=0.01):
    """Radii in range, overlaps (pairs and walls) below limit x mean radius, and
    the porosity and info consistent with the arrays."""
    pos, rad = _arrays(sp)
    n, dim = pos.shape
    assert np.all(np.asarray(sp.particles.valid))
    assert rad.min() >= r_lo * (1 - 1e-6) and rad.max() <= r_hi * (1 + 1e-6)
    _, _, gap = _all_gaps(pos, rad)
    tol = limit * rad.mean()
    assert -gap.min() < tol
    lo, hi = sp.box
    assert np.all(pos - rad[:, None] >= lo - tol) and np.all(pos + rad[:, None] <= hi + tol)
    info = sp.info
    assert info["n_particles"] == n
    assert info["max_overlap"] == pytest.approx(max(0.0, -gap.min(), info["max_overlap"]))
    assert info["max_overlap_ratio"] < limit
    assert info["r_min"] == rad.min() and info["r_max"] == rad.max()
    assert info["steps"] > 0 and info["wall_time"] > 0
    solid = np.sum(np.pi * rad**2) if dim == 2 else np.sum(4 / 3 * np.pi * rad**3)
    volume = np.prod(hi - lo) if info["shape"] != "disc" else np.pi * info["radius"] ** 2
    assert sp.porosity == pytest.approx(1 - solid / volume, abs=1e-12)


# ----------------------------------------------------------------------------- porosity
def test_rectangle_reaches_the_porosity_without_overlap(rect):
    assert abs(rect.porosity - 0.2) <= 0.01
    assert 100 < rect.info["n_particles"] < 300
    _check_packing(rect, *R2)
    np.testing.assert_array_equal(rect.box[0], [0, 0])
    np.testing.assert_array_equal(rect.box[1], SQUARE)
    assert rect.info["steps"] > 1000  # a real compaction ran


def test_box_3d_reaches_the_porosity_without_overlap():
    sp = generate("box", CUBE, *R3, target_porosity=0.5, seed=1)
    assert sp.particles.pos.shape[1] == 3
    assert abs(sp.porosity - 0.5) <= 0.01
    assert sp.info["n_particles"] > 100
    _check_packing(sp, *R3)
    assert sp.coordination == pytest.approx(2 * sp.info["n_bonds"] / sp.info["n_particles"])


def test_unreachable_porosity_names_the_target():
    with pytest.raises(InputError, match=r"target_porosity = 0.12 .*jammed at porosity"):
        generate("rectangle", SQUARE, *R2, target_porosity=0.12, seed=3)


# ----------------------------------------------------------------------------- coordination
def test_target_coordination_is_reached_by_the_gap_tolerance():
    sp = generate("rectangle", SQUARE, *R2, target_porosity=0.2, seed=3, target_coordination=3.8)
    assert abs(sp.coordination - 3.8) <= 0.15
    assert abs(sp.porosity - 0.2) <= 0.01
    assert 0 <= sp.info["gap_tolerance"] <= 0.5 * sp.info["r_mean"] * 1.01
    assert sp.coordination == pytest.approx(2 * sp.info["n_bonds"] / sp.info["n_particles"])


def test_specimen_for_coordination_loosens_the_packing_when_needed():
    # 2.5 is below what the dense packing gives even at zero gap: a looser one is made
    sp = specimen_for_coordination(2.5, "rectangle", SQUARE, *R2, target_porosity=0.18, seed=3)
    assert abs(sp.coordination - 2.5) <= 0.15
    assert len(sp.info["attempts"]) >= 2
    assert sp.porosity > 0.19
    _check_packing(sp, *R2)
    with pytest.raises(InputError, match=r"target_N = 5.8 is not reachable .*N-bar"):
        specimen_for_coordination(5.8, "rectangle", SQUARE, *R2, target_porosity=0.2, seed=3,
                                  max_attempts=1)


# ----------------------------------------------------------------------------- determinism
def test_same_seed_gives_identical_arrays_and_other_seeds_differ(rect):
    again = generate("rectangle", SQUARE, *R2, target_porosity=0.2, seed=3)
    for a, b in zip(rect.particles, again.particles):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for a, b in zip(rect.bonds, again.bonds):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert again.porosity == rect.porosity and again.coordination == rect.coordination
    other = generate("rectangle", SQUARE, *R2, target_porosity=0.2, seed=4)
    assert other.seed == 4
    pos_a, rad_a = _arrays(rect)
    pos_b, rad_b = _arrays(other)
    assert rad_a.shape != rad_b.shape or not np.array_equal(rad_a, rad_b)
    assert pos_a.shape != pos_b.shape or not np.array_equal(pos_a, pos_b)
    assert abs(other.porosity - 0.2) <= 0.01


# ----------------------------------------------------------------------------- disc
def test_disc_particles_lie_inside_the_disc():
    d = 0.01
    sp = generate("disc", d, *R2, target_porosity=0.22, seed=0)
    pos, rad = _arrays(sp)
    centre, radius = sp.info["centre"], sp.info["radius"]
    assert radius == d / 2
    np.testing.assert_allclose(centre, [d / 2, d / 2])
    assert np.all(np.linalg.norm(pos - centre, axis=1) + rad <= radius * (1 + 1e-3))
    assert abs(sp.porosity - 0.22) <= 0.01
    _check_packing(sp, *R2)


# ----------------------------------------------------------------------------- bonds
def test_bonds_join_exactly_the_pairs_within_the_gap_tolerance(rect):
    pos, rad = _arrays(rect)
    n = len(rad)
    b = rect.bonds
    ok = np.asarray(b.valid)
    bi, bj = np.asarray(b.i)[ok], np.asarray(b.j)[ok]
    g = rect.info["gap_tolerance"]
    assert g == pytest.approx(0.05 * rect.info["r_mean"], rel=1e-3)
    assert np.all(bi < bj)
    gap = np.linalg.norm(pos[bj] - pos[bi], axis=1) - rad[bi] - rad[bj]
    assert np.all(gap <= g * (1 + 1e-9))
    i, j, all_gap = _all_gaps(pos, rad)
    within = {(a, c) for a, c, x in zip(i, j, all_gap) if x <= g}
    assert within == set(zip(bi.tolist(), bj.tolist()))
    assert rect.coordination == pytest.approx(2 * ok.sum() / n)
    assert rect.info["n_bonds"] == ok.sum()
    # floaters were attached: every particle has a bond
    assert np.all(np.bincount(np.concatenate([bi, bj]), minlength=n) >= 1)


FLOATER_POROSITY = 0.22   # looser than ``rect``: most packings leave a few floaters
FLOATER_GAP = 0.02e-3     # bonding gap tolerance [m] of the floater tests


@functools.lru_cache(maxsize=None)
def _floater_seed():
    """The first of seeds 3, 4, 5 whose FLOATER_POROSITY packing (gap FLOATER_GAP)
    leaves floaters.  Whether a packing has any is a matter of chance (seeds 0-5:
    five of six at this porosity, one of six at 0.2), and a packing without one
    would leave the floater tests nothing to check."""
    for seed in (3, 4, 5):
        sp = generate("rectangle", SQUARE, *R2, target_porosity=FLOATER_POROSITY, seed=seed,
                      bond=False, gap_tolerance=FLOATER_GAP, floaters="keep")
        if sp.info["n_floaters"] > 0:
            return seed, sp
    raise AssertionError("no packing with floaters among seeds 3, 4, 5")


def test_bond_false_and_kept_floaters():
    g = FLOATER_GAP
    _, sp = _floater_seed()
    assert int(np.sum(np.asarray(sp.bonds.valid))) == 0
    pos, rad = _arrays(sp)
    i, j, gap = _all_gaps(pos, rad)
    assert sp.info["gap_tolerance"] == g
    assert sp.coordination == pytest.approx(2 * np.sum(gap <= g) / len(rad))
    deg = np.bincount(np.concatenate([i[gap <= g], j[gap <= g]]), minlength=len(rad))
    assert sp.info["n_floaters"] == np.sum(deg == 0) > 0
    assert sp.info["n_floaters_removed"] == sp.info["n_floaters_attached"] == 0


def test_floaters_can_be_attached_or_removed():
    seed, kept = _floater_seed()
    n_free = kept.info["n_floaters"]
    kw = dict(target_porosity=FLOATER_POROSITY, seed=seed, gap_tolerance=FLOATER_GAP)
    attached = generate("rectangle", SQUARE, *R2, floaters="attach", **kw)
    removed = generate("rectangle", SQUARE, *R2, floaters="remove", **kw)
    assert n_free > 0
    assert attached.info["n_floaters"] == removed.info["n_floaters"] == n_free
    assert attached.info["n_floaters_attached"] == n_free
    assert removed.info["n_floaters_removed"] == n_free
    assert removed.info["n_particles"] == attached.info["n_particles"] - n_free
    assert removed.porosity > attached.porosity
    for sp in (attached, removed):   # every particle has a bond
        ok = np.asarray(sp.bonds.valid)
        deg = np.bincount(np.concatenate([np.asarray(sp.bonds.i)[ok], np.asarray(sp.bonds.j)[ok]]),
                          minlength=sp.info["n_particles"])
        assert np.all(deg >= 1)


# ----------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("kwargs, field", [
    (dict(r_min=0.0), "r_min"),
    (dict(r_min=-1e-3), "r_min"),
    (dict(r_min=0.6e-3, r_max=0.5e-3), "r_max"),
    (dict(shape="hexagon"), "shape"),
    (dict(size=(0.01, -0.01)), r"size\[1\]"),
    (dict(size=(0.01,)), "size"),
    (dict(shape="disc", size=0.0), "size"),
    (dict(shape="box", size=(0.01, 0.01)), "size"),
    (dict(size=(0.001, 0.01)), "size"),
    (dict(target_porosity=1.2), "target_porosity"),
    (dict(target_porosity=0.0), "target_porosity"),
    (dict(target_porosity=0.02), "target_porosity"),
    (dict(target_coordination=-1.0), "target_coordination"),
    (dict(target_coordination=4.0, gap_tolerance=1e-5), "gap_tolerance"),
    (dict(gap_tolerance=-1e-5), "gap_tolerance"),
    (dict(overlap_limit=0.0), "overlap_limit"),
    (dict(density=-1.0), "density"),
    (dict(seed=-1), "seed"),
    (dict(floaters="ignore"), "floaters"),
])
def test_bad_input_names_the_field(kwargs, field):
    args = dict(shape="rectangle", size=SQUARE, r_min=R2[0], r_max=R2[1])
    args.update(kwargs)
    with pytest.raises(InputError, match=field):
        generate(args.pop("shape"), args.pop("size"), args.pop("r_min"), args.pop("r_max"),
                 **args)


def test_bad_coordination_target_names_the_field():
    with pytest.raises(InputError, match="target_N"):
        specimen_for_coordination(7.0, "rectangle", SQUARE, *R2)
    with pytest.raises(InputError, match="tolerance"):
        specimen_for_coordination(4.0, "rectangle", SQUARE, *R2, tolerance=0.0)



# ----------------------------------------------------------------------------- embedding
def test_embedding_grows_the_radii_at_fixed_centres_and_bonds_the_new_pairs(rect):
    """jdem.specimen.embed (002 §1.4's embedding): radii x 1.1 at the same centres
    and densities, the porosity 1 - 1.21 x the solid fraction, bonds exactly the
    pairs within 1.1 x the gap tolerance (brute force), N-bar up, the largest
    overlap measured; x 1 rebonds the specimen as it was; bonds start at rest,
    so the embedded assembly carries no force."""
    import jdem

    pos, rad = _arrays(rect)
    same = embed(rect, 1.0)
    np.testing.assert_array_equal(np.asarray(same.bonds.i), np.asarray(rect.bonds.i))
    np.testing.assert_array_equal(np.asarray(same.bonds.j), np.asarray(rect.bonds.j))
    assert same.coordination == rect.coordination

    sp = embed(rect, 1.1)
    np.testing.assert_array_equal(np.asarray(sp.particles.pos), np.asarray(rect.particles.pos))
    np.testing.assert_allclose(np.asarray(sp.particles.radius), 1.1 * rad, rtol=1e-15)
    np.testing.assert_allclose(np.asarray(sp.particles.mass),
                               1.21 * np.asarray(rect.particles.mass), rtol=1e-12)
    assert sp.porosity == pytest.approx(1 - 1.21 * (1 - rect.porosity), abs=1e-12)
    assert sp.info["area_fraction"] == pytest.approx(1 - sp.porosity, abs=1e-12)
    g = 1.1 * rect.info["gap_tolerance"]
    assert sp.info["gap_tolerance"] == pytest.approx(g, rel=1e-12)
    i, j, gap = _all_gaps(pos, 1.1 * rad)
    ok = np.asarray(sp.bonds.valid)
    bonded = set(zip(np.asarray(sp.bonds.i)[ok].tolist(), np.asarray(sp.bonds.j)[ok].tolist()))
    assert bonded == {(a, c) for a, c, x in zip(i, j, gap) if x <= g}
    assert sp.coordination == pytest.approx(2 * ok.sum() / len(rad))
    assert sp.coordination > rect.coordination + 0.1
    assert sp.info["max_overlap"] == pytest.approx(-gap.min(), rel=1e-9)
    assert sp.info["max_overlap_ratio"] > 0.05
    # at rest: 50 free steps (no walls, no load) move nothing
    state, config = jdem.make_state(sp.particles, bonds=sp.bonds)
    params = jdem.make_params(dim=2, dt=1e-8, kn=1e9, ks=1e9, friction=0.5,
                              bond_youngs=30e9, bond_poisson=0.25, bond_tensile=1e7,
                              bond_cohesion=1e7)
    after = jdem.advance(state, params, config, 50)
    assert float(np.max(np.abs(np.asarray(after.particles.vel)))) == 0.0
    with pytest.raises(InputError, match="scale"):
        embed(rect, 0.9)
    with pytest.raises(InputError, match="scale"):
        embed(rect, float("nan"))
    with pytest.raises(InputError, match="Specimen"):
        embed((rect.particles, rect.bonds), 1.1)
    loaded = rect._replace(bonds=rect.bonds._replace(
        normal_force=rect.bonds.normal_force.at[0].set(1.0)))
    with pytest.raises(InputError, match="embed needs a fresh specimen"):
        embed(loaded, 1.1)
    # the seed's way to say it: the area fraction to reach (002 §2.1: 0.895)
    target = 1.1 ** 2 * (1 - rect.porosity)
    by_fraction = embed(rect, area_fraction=target)
    assert by_fraction.info["embedding"] == pytest.approx(1.1, rel=1e-12)
    assert by_fraction.info["area_fraction"] == pytest.approx(target, rel=1e-12)
    with pytest.raises(InputError, match="area_fraction"):
        embed(rect, 1.1, area_fraction=target)
    with pytest.raises(InputError, match="area_fraction"):
        embed(rect)
