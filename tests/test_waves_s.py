"""S waves at the viscous boundary and free-field columns (001 §2, §4) on small
square lattices of equal discs (Pattern A of 001 Fig 2), bond nu = 0 and fixed
rotations, so that the lattice behaves like an elastic solid with
E = rho c_P^2, nu = 0 for waves along its axes: c_S = c_P / sqrt 2.

* The S bar: the 1000 m x 50 m bar of test_absorbing.py (10 m discs) with
  ``polarisation="S"``: every disc's x velocity fixed, the pulse of 001 eq 12
  (M = 0.5 m/s, T = 0.5 s) driven along +y on the left end, the right end the
  viscous boundary of 001 eq 5 (tangential dashpot beta_2S D rho c_S).  The
  reflection at P3 is measured against the same lattice 1800 m long
  (jdem.waves.bar_pair, reflection_against_reference on the y velocity).
* The free-field model: a 80 m x 200 m lattice hit from the base by a
  vertically incident pulse through a viscous input boundary (001 eq 6), its
  lateral sides tied to one-disc-wide free-field columns (001 eq 20, 21) that
  carry the same base input.  A plane wave must leave the discs at the sides
  moving exactly like the centre of the same row.

Measured values (printed by
``.venv/bin/python -m pytest -o addopts="" -q tests/test_waves_s.py -s``):
S speed from the arrivals at P2 and P4 0.05 % (fronts) and 0.12 % (peaks)
below c_S; reflected S amplitude at P3 with beta_S = 1: 1.99 % of the incident
one (free end, fixed end: 100 %; beta_S = 0.5: 33 %); free-field sides vs
centre: 0 for the P pulse, against 13-16 % with plain viscous sides and 100 %
with fixed sides.  For an SV pulse the free field disturbs the sides by
17-55 % (strict xfail below: the column's shear is applied on the lateral
discs, where this lattice carries none).
"""
import math

import jax.numpy as jnp
import numpy as np
import pytest

from jdem import waves
from jdem.bond import bond_geometry
from jdem.simulate import make_state, run
from jdem.validate import InputError
from jdem.waves.bar import wave_speed

L, H, R = 1000.0, 50.0, 5.0          # bar length, height, disc radius [m]
RHO, CP = 2500.0, 1000.0             # 001 §2.2
CS = CP / math.sqrt(2.0)
LX = 1800.0                          # extended lattice: nothing from its end reaches P3 in time


# ----------------------------------------------------------------------------- S bar
@pytest.fixture(scope="module")
def s_pair():
    pos, rad = waves.square_packing(int(LX / (2 * R)), int(H / (2 * R)), R)
    parts, bonds = waves.lattice(pos, rad, waves.square_density(RHO), fix_rotation=True)
    return waves.bar_pair(parts, bonds, length=L, height=H, dt_factor=0.9, polarisation="S")


@pytest.fixture(scope="module")
def s_runs(s_pair):
    return waves.run_bar(s_pair.truncated), waves.run_bar(s_pair.reference)


def _half_rise(t, v, t_max):
    """Time [s] at which v first rises through half its peak before ``t_max``
    (linear interpolation between records): the arrival of the pulse's front."""
    w = t <= t_max
    half = 0.5 * np.max(v[w])
    k = int(np.argmax(w & (v >= half)))
    return t[k - 1] + (half - v[k - 1]) / (v[k] - v[k - 1]) * (t[k] - t[k - 1])


def test_s_pulse_travels_at_the_lattice_c_s(s_pair, s_runs):
    """The S speed of the lattice from its bond shear stiffness, K_s = G A_c / L
    = E_b / 2 (G = E_b / (2 (1 + nu_b)), A_c = L = 2 R; 002 eq 2) on a disc of
    mass rho (2 R)^2: c_S = 2 R sqrt(K_s / m) = c_P / sqrt 2, the value the
    boundary's dashpot uses (001 eq 5).  The pulse's front (half peak) reaches
    P2 and P4 (x = 250, 750 m) 500 m / c_S apart, within 1 % (measured -0.05 %,
    -0.12 % from the peaks: the lattice's dispersion at 35 discs per
    wavelength plus the sampling);
    the motion stays transverse and the incident amplitude is the input's."""
    model = s_pair.truncated
    st = model.state
    geo = bond_geometry(st.bonds, st.particles, model.params, 2)
    ks = np.asarray(geo.ks)[np.asarray(st.bonds.valid)]
    assert np.allclose(ks, 0.5 * RHO * CP ** 2, rtol=1e-12)
    mass = np.asarray(st.particles.mass)
    assert np.allclose(mass, RHO * (2 * R) ** 2, rtol=1e-12)
    c_lattice = 2 * R * math.sqrt(ks[0] / mass[0])
    right = model.conditions.boundaries[1]
    assert abs(c_lattice / float(right.c_s) - 1) < 1e-12
    assert abs(wave_speed(model) / c_lattice - 1) < 1e-12

    h, _ = s_runs
    t, vy = h["time"], h["vel"][:, :, 1]
    assert np.all(h["vel"][:, :, 0] == 0.0)                  # motion across the bar only
    x = model.monitor_x
    arrive = [_half_rise(t, vy[:, k], x[k] / CS + model.duration) for k in (1, 3)]
    speed = (x[3] - x[1]) / (arrive[1] - arrive[0])
    peaks = [t[int(np.argmax(np.where(t < x[k] / CS + model.duration, vy[:, k], -np.inf)))]
             for k in (1, 3)]
    speed_peak = (x[3] - x[1]) / (peaks[1] - peaks[0])
    print(f"\nS speed: fronts {speed:.2f} m/s, peaks {speed_peak:.2f} m/s, c_S {c_lattice:.2f} m/s "
          f"(errors {speed / c_lattice - 1:+.4%}, {speed_peak / c_lattice - 1:+.4%})")
    assert abs(speed / c_lattice - 1) < 0.01, speed
    assert abs(speed_peak / c_lattice - 1) < 0.01, speed_peak
    assert abs(speed / CP - 1) > 0.2                          # not the P speed
    assert abs(waves.peak(h, 2, (0.0, 1.0)) / model.amplitude - 1) < 0.01


def test_s_pulse_absorbed_by_beta_s_one(s_pair, s_runs):
    """001 eq 3, 5: equal discs in a square arrangement, beta_2S = 1: the S
    pulse leaves through the right end.  Reflected amplitude at P3, measured
    against the 1800 m lattice over the record 2 L / c_S + T: 1.99 % of the
    incident one, asserted below 5 %; the window measure after the incident
    pulse agrees.  The measure can fail: a free end (beta_S = 0) and a fixed
    end reflect the whole pulse (100 %), beta_S = 0.5 a third (a continuum:
    (1 - 0.5) / (1 + 0.5))."""
    trunc = s_pair.truncated
    h, h_ref = s_runs
    measure = lambda hist: waves.reflection_against_reference(hist, h_ref, t_max=s_pair.record,
                                                              component=1)
    good = measure(h)
    assert abs(good["incident"] / trunc.amplitude - 1) < 0.01
    window = waves.reflection(h, trunc)
    free = measure(waves.run_bar(trunc, waves.with_betas(trunc, beta_right=0.0)))
    rb = trunc.conditions.boundaries[1]
    p = trunc.state.particles
    fixed_model = trunc._replace(state=trunc.state._replace(
        particles=p._replace(fixed_vel=p.fixed_vel.at[rb.index].set(True))))
    fixed = measure(waves.run_bar(fixed_model))
    half = measure(waves.run_bar(trunc, waves.with_betas(trunc, beta_right=0.5)))
    print(f"\nS reflection at P3: beta_S = 1 {good['ratio']:.4f} (window {window['ratio']:.4f}), "
          f"free end {free['ratio']:.4f}, fixed end {fixed['ratio']:.4f}, "
          f"beta_S = 0.5 {half['ratio']:.4f}")
    assert good["ratio"] < 0.05, good["ratio"]
    assert window["ratio"] < 0.05, window["ratio"]
    assert free["ratio"] > 0.9, free["ratio"]
    assert fixed["ratio"] > 0.9, fixed["ratio"]
    assert 0.25 < half["ratio"] < 0.45, half["ratio"]


def test_ratio_iteration_finds_beta_s_one_on_the_square_lattice(s_pair):
    """001 Fig 5 on the S bar: ``calibrate_ratio`` calibrates beta_2S (the
    tangential dashpot) from the transverse velocity of the boundary discs and
    leaves beta_2P as it was.  On equal discs in a square arrangement 001 eq 3
    gives beta_2S = 1; from 0.5 the iteration reaches |M_out / M_in - 1| < 1e-3
    within 15 runs at beta_2S within 3 % of 1."""
    trunc = s_pair.truncated
    cal = waves.calibrate_ratio(trunc, beta0=0.5)
    assert cal.converged and len(cal.history) <= 15
    assert abs(cal.history[-1]["ratio"] - 1) < 1e-3
    assert abs(cal.beta - 1) < 0.03, cal.beta
    cond = waves.with_betas(trunc, beta_right=cal.beta, wave="S")
    rb = cond.boundaries[1]
    assert float(rb.beta_s) == cal.beta
    assert float(rb.beta_p) == float(trunc.conditions.boundaries[1].beta_p)


@pytest.mark.slow
def test_beta_s_is_calibrated_apart_from_beta_p_on_a_random_packing():
    """001 eq 4: on a random packing (radii 4-6 m, ratio 1.5) beta_2P and beta_2S
    differ, and one factor for both waves is seen: the S bar cut from the packing
    calibrates to beta_2S = 0.87 against beta_2P = 0.70 on the P bar (measured),
    and beta_2S = beta_2P reflects 16 % of the S pulse at P3 against 6 % with
    the calibrated beta_2S (experiments/beta_s_calibration.py)."""
    lx = LX
    parts, bonds, _ = waves.random_packing(lx, H, 4.0, 6.0, seed=1, fix_rotation=True)
    p_bar = waves.bar_pair(parts, bonds, length=L, height=H, dt_factor=0.9).truncated
    s_pair = waves.bar_pair(parts, bonds, length=L, height=H, dt_factor=0.9, polarisation="S")
    cal_p = waves.calibrate_ratio(p_bar)
    cal_s = waves.calibrate_ratio(s_pair.truncated)
    assert cal_p.converged and cal_s.converged
    assert cal_s.beta > 1.1 * cal_p.beta, (cal_s.beta, cal_p.beta)
    bar, ref = s_pair.truncated, waves.run_bar(s_pair.reference)
    reflected = {b: waves.reflection_against_reference(
        waves.run_bar(bar, waves.with_betas(bar, beta_right=b, wave="S")), ref,
        t_max=s_pair.record, component=1)["ratio"] for b in (cal_p.beta, cal_s.beta)}
    assert reflected[cal_p.beta] > 0.10
    assert reflected[cal_s.beta] < 0.5 * reflected[cal_p.beta]


# ----------------------------------------------------------------------------- free field
NX, NY = 8, 20                       # main model 80 m x 200 m of 10 m discs
M, T = 0.5, 0.5                      # 001 eq 12


def _free_field_model(lateral, wave="P"):
    """The main lattice NX x NY with a viscous input base (001 eq 6, beta = 1)
    carrying the pulse along ``direction`` (P: +y, SV: +x), and lateral sides
    ``lateral``: "free-field" (001 eq 21: dashpots to a one-disc-wide column on
    each side, far from the main model, whose base disc is an input boundary
    with the same pulse, plus the column's stress), "viscous" (001 eq 5 alone)
    or "fixed".  Returns (state, params, config, conditions, monitors, n_steps)
    with monitors row by row at three heights: the left side disc, the disc
    next to it, the centre disc, the disc next to the right side, the right
    side disc."""
    d = 2 * R
    pos, rad = waves.square_packing(NX, NY, R)
    n_main = len(rad)
    columns = []
    if lateral == "free-field":
        for xc in (-20 * d, (NX + 20) * d):
            cp, cr = waves.square_packing(1, NY, R, origin=(xc, 0.0))
            columns.append(np.arange(len(rad), len(rad) + NY))
            pos, rad = np.vstack([pos, cp]), np.concatenate([rad, cr])
    parts, bonds = waves.lattice(pos, rad, waves.square_density(RHO), fix_rotation=True)
    main = np.arange(n_main)
    if lateral == "fixed":
        for side in ("left", "right"):
            idx = waves.boundary_particles(parts, side, among=main).index
            parts = parts._replace(fixed_vel=parts.fixed_vel.at[idx].set(True))
    params = waves.wave_params(CP, RHO, bond_poisson=0.0)
    state, config = make_state(parts, bonds=bonds)
    params = params._replace(dt=jnp.asarray(waves.stable_dt(state, params, config, 0.9)))
    time, vel, disp = waves.cosine_pulse(M, T)
    up = (0.0, 1.0) if wave == "P" else (1.0, 0.0)
    v_in, u_in = waves.incident_wave(time, vel, disp, up)
    kw = dict(density=RHO, c_p=CP, c_s=CS)
    base = waves.boundary_particles(parts, "bottom", among=main)
    bounds = [waves.make_boundary(base, parts, incident_vel=v_in, incident_disp=u_in, **kw)]
    for col in columns:
        foot = waves.BoundarySet(index=col[:1], width=2 * rad[col[:1]],
                                 normal=np.array([0.0, -1.0]), tangent=np.array([1.0, 0.0]),
                                 position=0.0)
        bounds.append(waves.make_boundary(foot, parts, incident_vel=v_in, incident_disp=u_in,
                                          **kw))
    if lateral in ("free-field", "viscous"):
        for k, side in enumerate(("left", "right")):
            bset = waves.boundary_particles(parts, side, among=main)
            assert len(bset.index) == NY
            ff = (waves.free_field_coupling(parts, bonds, bset, columns[k], poisson=0.0)
                  if lateral == "free-field" else None)
            bounds.append(waves.make_boundary(bset, parts, free_field=ff, **kw))
    cond = waves.Conditions(boundaries=tuple(bounds))
    state, cond = waves.activate(state, params, config, cond)
    rows = (1, NY // 2, NY - 1)                 # heights 15, 105, 195 m
    cols = (0, 1, NX // 2, NX - 2, NX - 1)
    groups = tuple((j * NX + i,) for j in rows for i in cols)
    c = CP if wave == "P" else CS
    t_end = 2 * NY * d / c + T                  # up, reflected at the free top, back to the base
    n_steps = int(math.ceil(t_end / float(params.dt) / 500)) * 500
    return state, params, config, cond, waves.Monitors(groups), n_steps


def _side_discrepancy(lateral, wave="P"):
    """max |v_side - v_centre| over the record and over the four discs at and
    next to the sides, relative to the centre's peak, at each of the three
    heights (3,); and the centre's peak velocity along the wave's motion (3,)."""
    state, params, config, cond, mon, n = _free_field_model(lateral, wave)
    res = run(state, params, config, n, record_every=1, observe=mon, chunk_steps=500,
              progress=False, boundary=(waves.apply_conditions, cond))
    v = np.asarray(res.history["vel"]).reshape(-1, 3, 5, 2)    # (records, height, column, xy)
    centre = v[:, :, 2:3, :]
    comp = 1 if wave == "P" else 0
    peak = np.abs(centre[:, :, 0, comp]).max(axis=0)
    diff = np.abs(v - centre).max(axis=(0, 2, 3)) / peak
    return diff, peak


def test_free_field_sides_keep_the_plane_p_wave():
    """001 eq 20, 21: a P pulse entering vertically through the base of a model
    whose lateral sides are tied to free-field columns stays a plane wave: at
    15, 105 and 195 m up, the discs at and next to each side move like the
    centre of the row within 1e-6 of its peak (measured 0: the column moves
    exactly like the main lattice, so the dashpots carry nothing, and with
    nu = 0 its lateral stress is 0).  The wave is there: the peak is M at the
    base and 2 M at the free top (within 1 %).  The check can fail: plain
    viscous sides (001 eq 5, dashpots against the absolute velocity) disturb
    the sides by 13-16 % of the peak, fixed sides by 100 %."""
    ff, peak = _side_discrepancy("free-field")
    viscous, _ = _side_discrepancy("viscous")
    fixed, _ = _side_discrepancy("fixed")
    print(f"\nfree-field P: side vs centre {ff}, viscous sides {viscous}, fixed sides {fixed}; "
          f"centre peaks {peak}")
    assert abs(peak[0] / M - 1) < 0.01 and abs(peak[-1] / (2 * M) - 1) < 0.01, peak
    assert np.all(ff < 1e-6), ff
    assert np.all(viscous > 0.05), viscous
    assert np.all(fixed > 0.5), fixed


@pytest.mark.xfail(strict=True, reason=(
    "jdem.waves.free_field_force applies the column's tau_xy (measured on horizontal planes) "
    "as a traction l_x tau_xy on the lateral discs (001 eq 20), but a square lattice with "
    "fixed rotations carries no shear on its vertical planes under a vertical SV wave (the "
    "horizontal bonds do not deform), so the force pushes the side discs vertically: side vs "
    "centre 17-55 % of the peak, worse than plain viscous sides (8-12 %); free sides (no "
    "boundary) or the free field without the l_x tau_xy term give 0 (to rounding)"))
def test_free_field_sides_keep_the_plane_sv_wave():
    """The same for an SV pulse (motion along x), the case of 001 §4.2."""
    ff, _ = _side_discrepancy("free-field", "S")
    viscous, _ = _side_discrepancy("viscous", "S")
    print(f"\nfree-field SV: side vs centre {ff}, viscous sides {viscous}")
    assert np.all(ff < 1e-6), ff
    assert np.all(viscous > 0.05), viscous


def test_bar_model_rejects_an_unknown_polarisation():
    pos, rad = waves.square_packing(4, 2, R)
    parts, bonds = waves.lattice(pos, rad, waves.square_density(RHO), fix_rotation=True)
    with pytest.raises(InputError, match="polarisation"):
        waves.bar_model(parts, bonds, length=40.0, height=20.0, polarisation="SH")
    model = waves.bar_model(parts, bonds, length=40.0, height=20.0, polarisation="S")
    with pytest.raises(InputError, match="wave"):
        waves.with_betas(model, beta_right=1.0, wave="SV")
    with pytest.raises(InputError, match="component=1"):
        zero = dict(time=np.arange(3.0), vel=np.zeros((3, 5, 2)))
        waves.reflection_against_reference(zero, zero)
