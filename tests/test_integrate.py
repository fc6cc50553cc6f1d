"""One explicit step of the computing cycle (000 §2.3, eq 2-15…2-17) against
updates worked out by hand from the step's inputs.

The laws that produce each force are tested elsewhere (bonds, contacts, walls);
here the question is whether the step adds every force and torque that acts on
a particle, divides by the right mass and moment of inertia, moves the
particle with the new velocity, advances the clock, takes the forces of a
boundary condition, and raises the divergence guard at the first bad step and
keeps that step.
"""
import jax.numpy as jnp
import numpy as np
import pytest

import jdem
from jdem import bond, walls as walls_mod
from jdem.integrate import max_step_travel, physics_step

R = 1e-3
DT = 1e-6


def _bonded_pair_on_a_wall():
    """Two bonded discs (radii R and 0.6 R) resting on a floor y = 0, pressed into
    it by 2 um; the pair opens along x and both discs slide and spin, so the
    bond, the floor and the applied loads all give forces and torques."""
    r = np.array([R, 0.6 * R])
    pos = np.array([[0.0, R - 2e-6], [np.sqrt(1.6 ** 2 - 0.4 ** 2) * R, 0.6 * R - 2e-6]])
    vel = np.array([[-0.05, 0.0], [0.08, 0.01]])
    angvel = np.array([3.0, -7.0])
    p = jdem.make_particles(pos, r, vel=vel, angvel=angvel)
    p = p._replace(ext_force=jnp.asarray([[0.3, -0.2], [0.0, 0.5]]),
                   ext_torque=jnp.asarray([2e-4, -1e-4]))
    bonds = bond.create_bonds(p, 2, gap_tolerance=1e-9)
    assert int(np.sum(bonds.valid)) == 1
    floor = jdem.make_walls([[0.0, 0.0]], [[0.0, 1.0]], n_particles=2)
    state, cfg = jdem.make_state(p, walls=floor, bonds=bonds)
    params = jdem.make_params(dim=2, dt=DT, kn=1e6, ks=5e5, friction=0.4,
                              gravity=[0.0, -9.81], bond_youngs=1e9)
    return state, params, cfg


def _expected_after_one_step(state, params, cfg):
    """Velocities, spins and positions of 000 eq 2-15…2-17 with the force sum
    F = F_bond + F_wall + F_applied + m g (no damping) built from the laws."""
    p = state.particles
    _, fb, tb = bond.bond_forces(state.bonds, p, params, 2, state.step, cfg.bond_section)
    _, fw, tw, _ = walls_mod.wall_forces(state.walls, p, params, cfg)
    m, inertia = np.asarray(p.mass), np.asarray(p.inertia)
    force = np.asarray(fb) + np.asarray(fw) + np.asarray(p.ext_force) \
        + m[:, None] * np.asarray(params.gravity)
    torque = np.asarray(tb) + np.asarray(tw) + np.asarray(p.ext_torque)
    vel = np.asarray(p.vel) + force / m[:, None] * DT
    angvel = np.asarray(p.angvel) + torque / inertia * DT
    return vel, angvel, np.asarray(p.pos) + vel * DT, (np.asarray(fb), np.asarray(tb),
                                                        np.asarray(fw), np.asarray(tw))


def test_one_step_adds_bond_wall_applied_and_gravity_forces_and_torques():
    state, params, cfg = _bonded_pair_on_a_wall()
    vel, angvel, pos, (fb, tb, fw, tw) = _expected_after_one_step(state, params, cfg)
    # every contribution is there and of a size that shows in the sum
    for name, part in dict(bond_force=fb, bond_torque=tb, wall_force=fw, wall_torque=tw).items():
        assert np.all(np.abs(part) > 1e-6), (name, part)
    new = physics_step(state, params, cfg)
    np.testing.assert_allclose(np.asarray(new.particles.vel), vel, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(new.particles.angvel), angvel, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(new.particles.pos), pos, rtol=1e-14, atol=1e-18)
    assert int(new.step) == 1 and float(new.time) == pytest.approx(DT, rel=1e-15)
    again = physics_step(new, params, cfg)
    assert int(again.step) == 2 and float(again.time) == pytest.approx(2 * DT, rel=1e-15)


def _free_disc(vel=(0.0, 0.0)):
    p = jdem.make_particles(np.zeros((1, 2)), [R], vel=np.asarray([vel]))
    state, cfg = jdem.make_state(p)
    return state, jdem.make_params(dim=2, dt=DT), cfg


@pytest.mark.parametrize("with_torque", [False, True])
def test_a_boundary_adds_its_force_and_torque(with_torque):
    """A boundary condition (jdem.waves' interface) returns a force, and
    optionally a torque, that act like applied loads."""
    state, params, cfg = _free_disc()
    f, t = jnp.asarray([[2e-3, -1e-3]]), jnp.asarray([5e-9])

    def boundary(s, prm, data):
        return (s, data[0], data[1]) if with_torque else (s, data[0])

    new = physics_step(state, params, cfg, boundary=(boundary, (f, t)))
    p = state.particles
    np.testing.assert_allclose(np.asarray(new.particles.vel),
                               np.asarray(f) / float(p.mass[0]) * DT, rtol=1e-12)
    spin = float(t[0]) / float(p.inertia[0]) * DT if with_torque else 0.0
    np.testing.assert_allclose(float(new.particles.angvel[0]), spin, rtol=1e-12, atol=0)


@pytest.mark.parametrize("travel, flagged", [(0.4, False), (0.6, True)])
def test_a_particle_moving_more_than_half_its_radius_per_step_is_flagged_at_once(travel, flagged):
    """000 §3.3: an explicit step resolves an approach over many steps; a particle
    covering more than half its radius in one step fails the guard.  The first
    failing step is kept while the run goes on failing."""
    state, params, cfg = _free_disc(vel=(0.6 * travel * R / DT, 0.8 * travel * R / DT))
    assert float(max_step_travel(state.particles, DT)) == pytest.approx(travel, rel=1e-12)
    for _ in range(3):
        state = physics_step(state, params, cfg)
    assert int(state.first_bad_step) == (0 if flagged else -1)
