"""Bad input is refused with jdem.validate.InputError naming the field and the value."""
import jax.numpy as jnp
import numpy as np
import pytest

import jdem
from jdem import timestep
from jdem.bond import create_bonds
from jdem.validate import InputError

POS = np.array([[0.0, 0.0], [1.9, 0.0]])   # two discs of radius 1 overlapping by 0.1
RAD = np.array([1.0, 1.0])


def _pair(**particle_kw):
    return jdem.make_state(jdem.make_particles(POS, RAD, **particle_kw))


def _bonded_pair():
    p = jdem.make_particles([[0.0, 0.0], [2.0, 0.0]], RAD, vel=[[0.01, 0.0], [-0.01, 0.0]])
    return jdem.make_state(p, bonds=create_bonds(p, 2, gap_tolerance=0.01))


def _run(state, params, config, **kw):
    kw.setdefault("record_every", 100)
    return jdem.run(state, params, config, kw.pop("n_steps", 100), progress=False, **kw)


def _with_dt(params, dt):
    return params._replace(dt=jnp.asarray(dt, params.dt.dtype))


# ----------------------------------------------------------------------------- damping
@pytest.mark.parametrize("alpha, shown", [(1.0, "1.0"), (1.5, "1.5"), (-0.25, "-0.25")])
def test_local_damping_outside_zero_to_one_is_refused(alpha, shown):
    """000 eq 3-19 needs 0 <= alpha < 1: alpha = 1 is refused, just below 1 is not."""
    with pytest.raises(InputError, match=rf"params\.local_damping must lie in \[0\.0, 1\.0\), "
                                         rf"got {shown}$"):
        jdem.make_params(dim=2, local_damping=alpha)
    jdem.make_params(dim=2, local_damping=0.999)


def _dashpot_case(state, config, field, **params_kw):
    """The undamped recommended step is refused once the dashpot is at 50 x critical;
    the recommended step of the damped estimate runs and stays bounded."""
    undamped = jdem.make_params(dim=2, **params_kw)
    crit0 = float(timestep.critical_timestep(state, undamped, config))
    dt0 = timestep.recommended(crit0)
    damped = jdem.make_params(dim=2, **params_kw, **{field: 50.0})
    with pytest.raises(InputError, match=rf"params\.dt = .* s exceeds the critical time step .*"
                                         rf"includes the damping params\.{field} = 50\b"):
        _run(state, _with_dt(damped, dt0), config)
    crit = float(timestep.critical_timestep(state, damped, config))
    assert crit < 0.02 * crit0  # (2/omega)(sqrt(1 + zeta^2) - zeta) ~ 1 / (omega zeta)
    res = _run(state, _with_dt(damped, timestep.recommended(crit)), config, n_steps=2000)
    pos = np.asarray(res.state.particles.pos)
    assert np.all(np.isfinite(pos))
    assert np.max(np.abs(pos - np.asarray(state.particles.pos))) < 0.1


def test_contact_dashpot_far_above_critical_needs_a_smaller_step():
    state, config = _pair()
    _dashpot_case(state, config, "contact_damping", kn=1e6)


def test_bond_dashpot_far_above_critical_needs_a_smaller_step():
    state, config = _bonded_pair()
    _dashpot_case(state, config, "bond_damping", kn=1e6, bond_youngs=1e6)


def test_damped_critical_step_is_the_spring_dashpot_limit():
    """One disc on a frictionless floor with its rotation fixed: one spring and one
    dashpot, so the estimate is (2 / omega)(sqrt(1 + zeta^2) - zeta) exactly, with
    the Gershgorin omega^2 = 2 (k_n + k_t) / m and zeta = c / (2 m omega)."""
    p = jdem.make_particles([[0.0, 0.9]], [1.0], fixed_rot=[True])
    walls = jdem.make_walls([[0.0, 0.0]], [[0.0, 1.0]], n_particles=1)
    state, config = jdem.make_state(p, walls=walls)
    kn, zeta = 1e6, 3.0
    params = jdem.make_params(dim=2, kn=kn, ks=kn, friction=0.0, contact_damping=zeta)
    m = float(p.mass[0])
    omega = np.sqrt(2 * (kn + kn) / m)
    zeta_eff = 2 * (2 * zeta * np.sqrt(m * kn)) / m / (2 * omega)
    expect = 2 / omega * (np.sqrt(1 + zeta_eff**2) - zeta_eff)
    np.testing.assert_allclose(float(timestep.critical_timestep(state, params, config)), expect,
                               rtol=1e-12)


# ----------------------------------------------------------------------------- particles
def test_material_index_out_of_range_is_refused():
    state, config = _pair(material=[0, 3])
    params = jdem.make_params(dim=2, kn=1e6, dt=1e-5)
    with pytest.raises(InputError, match=r"particles\.material\[1\] = 3 is out of range: "
                                         r"params has 1 material \(indices 0 to 0\)"):
        _run(state, params, config)
    with pytest.raises(InputError, match=r"particles\.material\[1\] = 3 is out of range"):
        timestep.check_timestep(state, params, config)
    with pytest.raises(InputError, match=r"material\[1\] must be a material index >= 0, got -1"):
        jdem.make_particles(POS, RAD, material=[0, -1])
    walls = jdem.make_walls([[0.0, -1.0]], [[0.0, 1.0]], n_particles=2, material=[2])
    state, config = jdem.make_state(jdem.make_particles(POS, RAD, material=[0, 1]), walls=walls)
    with pytest.raises(InputError, match=r"walls\.material\[0\] = 2 is out of range: "
                                         r"params has 2 materials \(indices 0 to 1\)"):
        _run(state, jdem.make_params(dim=2, n_materials=2, kn=1e6, dt=1e-5), config)


def test_coincident_centres_are_refused():
    with pytest.raises(InputError, match=r"pos\[2\] = \(1\.0, 2\.0\) coincides with pos\[0\]"):
        jdem.make_particles([[1.0, 2.0], [5.0, 2.0], [1.0, 2.0]], [1.0, 1.0, 1.0])
    p = jdem.make_particles(POS, RAD)
    same = p._replace(pos=p.pos.at[1].set(p.pos[0]))
    with pytest.raises(InputError, match=r"particles\.pos\[1\] = \(0\.0, 0\.0\) coincides with "
                                         r"particles\.pos\[0\]"):
        jdem.make_state(same)


def test_empty_particle_set_is_refused():
    with pytest.raises(InputError,
                       match=r"pos must hold at least one particle, got shape \(0, 2\)"):
        jdem.make_particles(np.zeros((0, 2)), np.zeros(0))
    p = jdem.make_particles(POS, RAD)
    with pytest.raises(InputError, match=r"particles must hold at least one valid particle, "
                                         r"got 0 of capacity 2"):
        jdem.make_state(p._replace(valid=jnp.zeros_like(p.valid)))


def test_vel_of_wrong_shape_is_refused():
    with pytest.raises(InputError, match=r"vel must have shape \(2, 2\), got \(1, 3\)"):
        jdem.make_particles(POS, RAD, vel=[[1.0, 2.0, 3.0]])
    with pytest.raises(InputError, match=r"angvel must have shape \(2,\), got \(2, 3\)"):
        jdem.make_particles(POS, RAD, angvel=np.zeros((2, 3)))


def test_density_of_wrong_shape_is_refused():
    with pytest.raises(InputError, match=r"density must have shape \(2,\), got \(3,\)"):
        jdem.make_particles(POS, RAD, density=[1.0, 2.0, 3.0])
    jdem.make_particles(POS, RAD, density=[1000.0, 2000.0])


# ----------------------------------------------------------------------------- run set-up
def test_gravity_of_wrong_dimension_is_refused():
    state, config = _pair()
    params = jdem.make_params(dim=3, kn=1e6, dt=1e-5, gravity=[0.0, 0.0, -9.81])
    with pytest.raises(InputError, match=r"params\.gravity must have shape \(2,\), got \(3,\)"):
        _run(state, params, config)


@pytest.mark.parametrize("shape, shown", [((0, 1), "0"), ((-2, 1), "-2"), ((1.5, 1), "1.5")])
def test_grid_shape_of_zero_or_fewer_cells_is_refused(shape, shown):
    with pytest.raises(InputError, match=rf"Config\.grid_shape\[0\] must be .*got {shown}$"):
        jdem.Config(dim=2, cell_size=3.0, grid_origin=(-3.0, -3.0), grid_shape=shape)


def test_record_every_zero_is_refused():
    state, config = _pair()
    params = jdem.make_params(dim=2, kn=1e6, dt=1e-5)
    with pytest.raises(InputError, match=r"record_every must be >= 1, got 0"):
        _run(state, params, config, record_every=0)
    with pytest.raises(InputError, match=r"n_steps must be >= 0, got -100"):
        _run(state, params, config, n_steps=-100)


def test_out_that_is_a_file_or_cannot_be_written_is_refused(tmp_path, capsys):
    import os

    from jdem import cli

    afile = tmp_path / "a_file"
    afile.write_text("x")
    assert cli.main(["ucs", "--small", "--out", str(afile)]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err
    locked = tmp_path / "locked"
    locked.mkdir()
    os.chmod(locked, 0o500)
    try:
        if os.access(locked, os.W_OK):      # running as root: permissions do not bind
            pytest.skip("permissions are not enforced for this user")
        assert cli.main(["ucs", "--small", "--out", str(locked / "sub")]) == 2
        assert "cannot be created" in capsys.readouterr().err
    finally:
        os.chmod(locked, 0o700)


def test_resume_without_a_checkpoint_is_refused(tmp_path):
    from jdem import cli

    with pytest.raises(InputError, match="--resume: no checkpoint"):
        cli._resume_file(tmp_path / "ucs_checkpoint.h5", True)
    assert cli._resume_file(tmp_path / "ucs_checkpoint.h5", False) is None


def test_rate_extrapolation_settings_are_checked(tmp_path):
    """``[fit] extrapolate_rate`` must be true or false; ``rate_factor`` above 1."""
    from jdem import calibrate
    from jdem.cli import calibrate_settings

    cfg = tmp_path / "fit.toml"
    cfg.write_text('[fit]\nextrapolate_rate = "yes"\n')
    with pytest.raises(jdem.InputError, match=r"fit.extrapolate_rate .*'yes'"):
        calibrate_settings(cfg)
    cfg.write_text("[fit]\nextrapolate_rate = true\n")
    assert calibrate_settings(cfg)["fit"]["extrapolate_rate"] is True
    with pytest.raises(jdem.InputError, match="rate_factor .* got 1.0"):
        calibrate.calibrate(None, None, dict(E=3e10), rate_factor=1.0)


def test_calibrate_jacobian_setting_is_checked(tmp_path):
    """``[fit] jacobian`` names a mode calibrate knows; ``fd_step`` lies in (0, 1)."""
    from jdem import calibrate
    from jdem.cli import calibrate_settings

    cfg = tmp_path / "fit.toml"
    cfg.write_text('[fit]\njacobian = "secant"\n')
    with pytest.raises(jdem.InputError, match=r"fit.jacobian .*'secant'"):
        calibrate_settings(cfg)
    cfg.write_text('[fit]\njacobian = "finite-difference"\n')
    assert calibrate_settings(cfg)["fit"]["jacobian"] == "finite-difference"
    assert calibrate_settings(None)["fit"]["jacobian"] == "auto"
    with pytest.raises(jdem.InputError, match="jacobian must be one of"):
        calibrate.calibrate(None, None, dict(E=3e10), jacobian="secant")
    with pytest.raises(jdem.InputError, match="fd_step .* got 2"):
        calibrate.calibrate(None, None, dict(E=3e10), fd_step=2)
