"""The 2D bond's bending section (Config.bond_section): the seed's circular
section (002 eq 5) and the unit-thickness slab of a 2D model."""
import jax.numpy as jnp
import numpy as np
import pytest

import jdem
from jdem.bond import bond_forces, bond_geometry, create_bonds
from jdem.state import Config, make_params, make_particles
from jdem.validate import InputError

E, NU = 10e9, 0.22


def _pair(r1, r2):
    parts = make_particles(np.array([[0.0, 0.0], [r1 + r2, 0.0]]), [r1, r2])
    return create_bonds(parts, 2, gap_tolerance=1e-9), parts


@pytest.mark.parametrize("r1, r2", [(1e-3, 1e-3), (0.5, 0.5), (1e-3, 0.6e-3)])
def test_slab_bending_moment_of_a_rotated_bond_is_e_i_theta_over_l(r1, r2):
    """Disc 1 turned by theta in one step: M = E I theta / L with the slab's
    I = 1 m x (2 r_min)^3 / 12, and with the circular I = pi (2 r_min)^4 / 64."""
    bonds, parts = _pair(r1, r2)
    dt, theta = 1e-6, 1e-7
    params = make_params(dim=2, dt=dt, bond_youngs=E, bond_poisson=NU)
    parts = parts._replace(angvel=jnp.asarray([theta / dt, 0.0]))
    r, length = min(r1, r2), r1 + r2
    for section, inertia in (("slab", (2 * r) ** 3 / 12), ("circular", np.pi * (2 * r) ** 4 / 64)):
        g = bond_geometry(bonds, parts, params, 2, section)
        np.testing.assert_allclose(float(g.I[0]), inertia, rtol=1e-14)
        new, _, _ = bond_forces(bonds, parts, params, 2, 0, section)
        moment = E * inertia * theta / length           # K_n I / A_c theta, 002 eq 4
        np.testing.assert_allclose(-float(new.bend[0]), moment, rtol=1e-12)
    # the seed's section against the slab: 3 pi r_min / 8 (1.2e-3 at 1 mm, scale-dependent)
    ratio = float(bond_geometry(bonds, parts, params, 2, "circular").I[0]
                  / bond_geometry(bonds, parts, params, 2, "slab").I[0])
    np.testing.assert_allclose(ratio, 3 * np.pi * (2 * r) / 16, rtol=1e-12)


def test_config_takes_the_section_and_refuses_others():
    assert Config().bond_section == "circular"
    assert Config(bond_section="slab").bond_section == "slab"
    with pytest.raises(InputError, match="bond_section must be one of"):
        Config(bond_section="square")
    with pytest.raises(InputError, match="2D section"):
        Config(dim=3, grid_origin=(0.0, 0.0, 0.0), grid_shape=(1, 1, 1), bond_section="slab")


def test_the_engine_uses_the_configured_section():
    """A bonded pair rocked by a torque: the rotation it reaches after a few
    steps is smaller with the stiffer slab by the moment-of-area ratio."""
    bonds, parts = _pair(1e-3, 1e-3)
    turned = {}
    for section in ("circular", "slab"):
        state, cfg = jdem.make_state(parts, bonds=bonds)
        cfg = cfg.replace(bond_section=section)
        p = state.particles._replace(ext_torque=jnp.asarray([1e-6, 0.0]),
                                     fixed_vel=jnp.ones((2, 2), bool))
        state = state._replace(particles=p)
        params = make_params(dim=2, dt=1e-9, bond_youngs=E, bond_poisson=NU)
        s = jdem.advance(state, params, cfg, 3)
        turned[section] = float(s.particles.angvel[0])
    assert turned["slab"] < turned["circular"]


def test_a_ucs_setup_carries_the_section_and_the_slab_is_stiffer_in_rotation():
    from jdem import lab, timestep
    from jdem.materials import rock_params
    from jdem.specimen import generate

    spec = generate("rectangle", (0.003, 0.006), 0.2e-3, 0.35e-3, seed=2)
    params = rock_params(2)
    circ = lab.UCS.setup(spec, params, max_strain=1e-4)
    slab = lab.UCS.setup(spec, params, max_strain=1e-4, bond_section="slab")
    assert (circ.plan.config.bond_section, slab.plan.config.bond_section) == ("circular", "slab")
    # the same translational springs; the slab's bending springs K_n I / A_c are far
    # stiffer (I / A_c = (2 r)^2 / 12 against the circular pi (2 r)^3 / 128 [m^3]), so
    # each bonded particle's rotational stiffness rises (the time step's row sums)
    sums = lambda su: [np.asarray(x) for x in
                       timestep._stiffness_sums(su.state, su.params, su.plan.config)]
    (tr_c, rot_c), (tr_s, rot_s) = sums(circ), sums(slab)
    np.testing.assert_array_equal(tr_s, tr_c)
    bonded = np.zeros(tr_c.shape, bool)
    b = circ.state.bonds
    bonded[np.asarray(b.i)[np.asarray(b.valid)]] = True
    bonded[np.asarray(b.j)[np.asarray(b.valid)]] = True
    assert bonded.sum() > 50
    assert np.all(rot_s[bonded] > 1.3 * rot_c[bonded])


def test_the_toml_material_section_takes_the_bond_section(tmp_path):
    from jdem import cli

    good = tmp_path / "slab.toml"
    good.write_text('[material]\nbond_section = "slab"\n')
    assert cli.ucs_settings(good)["material"]["bond_section"] == "slab"
    assert cli.ucs_settings(None)["material"]["bond_section"] == "circular"
    bad = tmp_path / "bad.toml"
    bad.write_text('[material]\nbond_section = "square"\n')
    with pytest.raises(InputError, match="material.bond_section must be one of circular, slab"):
        cli.ucs_settings(bad)
