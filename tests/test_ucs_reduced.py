"""The reduced UCS study of 002 §2 (issue: "a reduced version, a few thousand
discs, runs in the test suite"): one ~2,200-disc specimen (1.8 cm x 3.6 cm, the
seed's radii and material, N-bar 5), kappa = 0, 0.3 %, 2.4 % as one batched run.

Runtime: ~20 s to generate, ~2 min to load on this project's 2-core CPU
(22,000 steps x 3 members at most; the run stops once every member has
softened below 60 % of its peak).  Its own file, so that ``--dist loadfile``
can give it a worker of its own.

Loading: the seed's local damping 0.8 (000 eq 3-19, 002 §2.1) and a fixed platen
step of 3 nm, after the lab layer's ramp of ten wave transits.  With jdem's time
step that is a loading rate (platen speed / bar wave speed) of 5.2e-5, 13 x the
certified default: fast enough for the suite, and the trends below hold at every
rate measured, but the peaks are the loading rate's, not the rock's (at kappa = 0
13.6 MPa here, 5.5 at 4e-6, 3.7-4.6 as the rate goes to zero;
experiments/results/ucs_stages_rate/NOTES.md).  The comparison with the seed's
figures is therefore made at the seed's own protocol and packing density, in
a slow test at the end.
"""
import numpy as np
import pytest

from jdem import lab
from jdem.batch import member
from jdem.materials import rock_params
from jdem.specimen import add_plates, embed, generate

SIZE = (0.018, 0.036)            # [m] width x height
RADII = (0.2e-3, 0.35e-3)        # [m] (the seed: 0.228-0.422 mm)
KAPPAS = (0.0, 3e-3, 2.4e-2)
STEP = 3e-9                      # [m] platen step


@pytest.fixture(scope="module")
def study():
    spec = generate("rectangle", SIZE, *RADII, seed=2, target_coordination=5.0)
    setup = lab.UCS.setup(spec, rock_params(2, kappa=list(KAPPAS)), platen_step=STEP,
                          max_strain=2e-3, damping=lab.local(0.8), record_every=50)
    res = lab.run(setup, stop_stress_ratio=0.6, progress=False, warn_dynamic=False)
    return spec, res.history, res.state, lab.peak_summary(res.history)


def test_reduced_study_peaks_soften_and_trend_with_kappa(study):
    """Every curve peaks inside the run and softens below 70 % of its peak; the
    peak stress and the critical strain rise with kappa across {0, 0.3 %, 2.4 %};
    the fracture degree at the peak and at the end falls (002 §2.2-2.3)."""
    spec, hist, state, s = study
    n = int(np.sum(np.asarray(spec.particles.valid)))
    print(f"{n} discs, steps {np.asarray(state.step)}, peak MPa "
          f"{np.round(s['peak_stress'] / 1e6, 2)}, critical strain {s['critical_strain']}, "
          f"fracture degree at peak {s['fracture_degree_at_peak']}, "
          f"at end {s['fracture_degree_end']}")
    assert 2000 <= n <= 3000
    assert abs(spec.coordination - 5.0) <= 0.15
    for b in range(len(KAPPAS)):
        stress = hist["axial_stress"][b]
        k = int(s["peak_index"][b])
        assert 5 < k < len(stress) - 5
        assert stress[-1] < 0.7 * s["peak_stress"][b]
        assert hist["fracture_degree"][b, -1] > hist["fracture_degree"][b, k]
    assert np.all(np.diff(s["peak_stress"]) > 0)
    assert np.all(np.diff(s["critical_strain"]) > 0)
    assert np.all(np.diff(s["fracture_degree_at_peak"]) < 0)
    assert np.all(np.diff(s["fracture_degree_end"]) < 0)


def test_reduced_study_breaks_are_counted_by_mode(study):
    """Broken bonds = tension + shear breaks in every record, never decreasing;
    the failure pattern of the final state draws each broken bond once, with both
    modes present (measured on this packing, kappa = 0: 37 % tension of 1,610)."""
    _, hist, state, _ = study
    np.testing.assert_array_equal(hist["n_broken"], hist["n_tension"] + hist["n_shear"])
    assert np.all(np.diff(hist["n_broken"], axis=1) >= 0)
    fp = lab.failure_pattern(member(state, 0))
    assert len(fp["index"]) == hist["n_broken"][0, -1]
    assert set(np.unique(fp["mode"]).tolist()) == {1, 2}
    assert np.sum(fp["mode"] == 1) == hist["n_tension"][0, -1]


# The seed's figures (002 §2.2, Fig 11) as pass bands.  The band is 3 standard
# deviations of the packing scatter measured on four packings of this study
# (experiments/ucs_seed_bands.py, experiments/results/ucs_seed_bands/, at the 3 nm step):
# peak stress 5.2 % (kappa 0) and 1.8 % (kappa 2.4 %), critical strain 3.8 % / 10.1 %.
SEED_PEAK = {0.0: 6.54e6, 2.4e-2: 20.1e6}
SEED_CRITICAL_STRAIN = {0.0: 232e-6, 2.4e-2: 861e-6}
PEAK_SCATTER = {0.0: 0.052, 2.4e-2: 0.018}
STRAIN_SCATTER = {0.0: 0.038, 2.4e-2: 0.101}
SEED_KAPPAS = (0.0, 2.4e-2)
#: the seed's 1 nm step (002 §2.1) as a loading rate, with the textbook's time step
#: (000 eq 3-26, 3-27: T_min / 10 of the stiffest single bond on the lightest disc,
#: 3.9 x jdem's): 3.9e-6 on the seed's discs, 4.5e-6 on these
SEED_RATE = 4e-6
#: the seed's discs fill 0.895 of its specimen (002 §2.1: 13,097 discs, r uniform in
#: [0.228, 0.422] mm, 5 cm x 10 cm), more than touching discs can (this packing: 0.829)
SEED_AREA_FRACTION = 13097 * np.pi * (0.228**2 + 0.228 * 0.422 + 0.422**2) / 3 * 1e-6 / 5e-3


@pytest.fixture(scope="module")
def seed_protocol():
    """The seed's UCS protocol and packing density on this packing:
    * local damping 0.8 and the seed's step as a loading rate (``SEED_RATE``);
    * its boundary, the face particles held in the loading direction and free
      sideways (002 §2.1: "bottom held normally, top driven at a quasi-static
      velocity"): one row of plate discs bonded to the rock only
      (``add_plates(..., rows=1, bond_plate_discs=False)``) between frictionless
      platens;
    * its area fraction: the radii grown at fixed centres and rebonded
      (``jdem.specimen.embed``, 002 §1.4's embedding; x 1.039, N-bar 5.0 -> 5.15).
    float64, ~5 min."""
    spec = generate("rectangle", SIZE, *RADII, seed=2, target_coordination=5.0)
    spec = add_plates(embed(spec, area_fraction=SEED_AREA_FRACTION), rows=1,
                      bond_plate_discs=False)
    setup = lab.UCS.setup(spec, rock_params(2, kappa=list(SEED_KAPPAS), plate_youngs=200e9),
                          loading_rate=SEED_RATE, max_strain=1.6e-3, damping=lab.local(0.8),
                          record_every=50, precision="float64")
    res = lab.run(setup, stop_stress_ratio=0.6, progress=False, warn_dynamic=False)
    return lab.peak_summary(res.history)


@pytest.mark.slow
def test_at_the_seeds_protocol_and_density_the_peaks_and_critical_strains_are_the_seeds(
        seed_protocol):
    """At the seed's protocol and packing density both peaks and both critical
    strains lie in the seed's bands (this test, 2026-12-07: kappa = 0 7.19 MPa
    against 6.54 (+9.9 %, band 15.6 %) at 257e-6 against 232e-6 (+10.9 %, band
    11.4 %: the figure nearest its band's edge); kappa = 2.4 % 20.18 MPa against
    20.1 (+0.4 %, band 5.4 %) at 878e-6 against 861e-6.  experiments/ucs_stages.py,
    whose run records to a larger strain, measured 7.11 MPa at 243e-6 and 20.55
    MPa at 927e-6: the brittle figures move by a few per cent with any change of
    the arithmetic).  Over four packings (2-5, experiments/results/ucs_stages_rate/
    seed_protocol_packing*) the kappa = 0 peak is 7.83 +- 0.66 MPa (+20 % on the
    seed's; this packing is the lowest) and the kappa = 2.4 % peak 19.90 +- 1.31 MPa
    (-1 %): the packing scatter at this protocol is wider than the 3 nm step's bands
    used here.  What each part of the protocol does
    (experiments/results/ucs_stages_rate/NOTES.md):
    * at the 3 nm step of the fast study above (a loading rate 13 x this one) the
      kappa = 0 peak was 13.6 MPa at 575e-6: the excess was the loading rate;
    * without the embedding (area fraction 0.829) the kappa = 0 figures were already
      the seed's (6.14 MPa, 229e-6) but the kappa = 2.4 % peak was 16.47 MPa, -18 %."""
    s = seed_protocol
    print(f"peaks {s['peak_stress'] / 1e6} MPa, critical strains {s['critical_strain']}")
    for k, kappa in enumerate(SEED_KAPPAS):
        assert abs(s["peak_stress"][k] / SEED_PEAK[kappa] - 1) < 3 * PEAK_SCATTER[kappa]
        assert abs(s["critical_strain"][k] / SEED_CRITICAL_STRAIN[kappa] - 1) \
            < 3 * STRAIN_SCATTER[kappa]


@pytest.mark.slow
def test_reduced_study_in_float32_is_within_its_own_sensitivity(study):
    """The study runs in float32 (the lab tests' default).  The issue's bar,
    float32 within 0.5 % of float64 in peak stress, modulus and critical strain,
    cannot be met here, by float32 or by float64: under the seed's protocol
    (local damping 0.8) the figures of this ~2,200-disc specimen move by more
    than that under any perturbation of the arithmetic.  Measured on an H200 on
    the same packing, float64 against float64 with deterministic (reordered)
    sums: peak 2.6 %, modulus 6.6 %, critical strain up to 9.7 %
    (experiments/results/gpu_h200/NOTES.md).  So: every member's float32 figure
    lies within twice the largest move of float64 under three nudges of the
    positions (rounded to float32: <= 1 nm; two random jitters of 0.1 nm), or
    within 0.5 %.  Twice, because three draws undersample that spread (the H200
    figures above exceed them).  Measured on CPU (kappa = 0 / 0.3 % / 2.4 %):
    float32 moves peak 1.5 / 1.8 / 0.7 %, modulus 1.8 / 0.4 / 0.6 %, critical
    strain 5.3 / 0.6 / 3.8 %; the nudged float64 runs at most 3.1 / 1.9 / 0.7 %,
    5.5 / 0.9 / 0.6 %, 4.6 / 9.7 / 4.2 % (the kappa = 0 critical strain is the one
    figure above the single spread).  Slow (~5 min more)."""
    spec, hist, _, s32 = study
    assert np.asarray(hist["axial_stress"]).dtype == np.float32

    def run(sp):
        setup = lab.UCS.setup(sp, rock_params(2, kappa=list(KAPPAS)), platen_step=STEP,
                              max_strain=2e-3, damping=lab.local(0.8), record_every=50,
                              precision="float64")
        return lab.peak_summary(lab.run(setup, stop_stress_ratio=0.6, progress=False,
                                        warn_dynamic=False).history)

    def nudged(pos):
        return spec._replace(particles=spec.particles._replace(pos=pos))

    s64 = run(spec)
    pos = np.asarray(spec.particles.pos, np.float64)
    rng = np.random.default_rng(0)
    moves = [run(nudged(pos.astype(np.float32).astype(np.float64)))] + \
        [run(nudged(pos + 1e-10 * rng.standard_normal(pos.shape))) for _ in range(2)]
    for key in ("peak_stress", "youngs_modulus", "critical_strain"):
        ref = np.asarray(s64[key])
        f32 = np.abs(np.asarray(s32[key]) / ref - 1.0)
        spread = np.max([np.abs(np.asarray(m[key]) / ref - 1.0) for m in moves], axis=0)
        print(key, "float32", f32, "float64 nudged (largest)", spread)
        assert np.all(f32 <= np.maximum(2.0 * spread, 5e-3)), (key, f32, spread)
