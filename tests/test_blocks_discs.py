"""Discs and blocks in one model (jdem.blocks.coupling): the disc–polygon
geometry against its analytic values, action and reaction (momentum and
angular momentum of a disc striking a free block), and a static column: a
block resting on discs resting on a fixed block passes the whole weight down."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdem
from jdem import blocks as bk
from jdem.blocks import coupling
from jdem.validate import InputError


def _square_block(x0, y0, side, *, fixed=False, density=2500.0):
    b = bk.make_blocks([bk.rectangle(x0, y0, side, side)], density,
                       fixed=[0] if fixed else None)
    return b


def test_disc_block_geometry_matches_the_distance_to_a_square():
    """A unit square at the origin, discs of radius 0.2: beside a face, beyond a
    corner (distance to the corner, normal along the diagonal), inside near a
    face (the depth below it, that face's normal), and far away."""
    b = _square_block(0.0, 0.0, 1.0)
    centres = np.array([[1.1, 0.5], [1.1, 1.1], [0.5, 0.9], [3.0, 3.0], [0.5, -0.15]])
    p = jdem.make_particles(centres, np.full(5, 0.2))
    overlap, normal, point = map(np.asarray, coupling.disc_block_geometry(b, p))
    d = np.sqrt(0.02)
    np.testing.assert_allclose(overlap[0], [0.1, 0.2 - d, 0.3, 0.2 - np.sqrt(8.0), 0.05],
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(normal[0, 0], [1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(normal[0, 1], [np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(normal[0, 2], [0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(normal[0, 4], [0.0, -1.0], atol=1e-12)
    # the contact point: half the overlap inside the disc's surface
    np.testing.assert_allclose(point[0, 0], [1.1 - (0.2 - 0.05), 0.5], atol=1e-12)
    # rotated by 90 degrees about its centroid the square is the same set
    turned = b._replace(angle=b.angle + 0.5 * np.pi)
    np.testing.assert_allclose(np.asarray(coupling.disc_block_geometry(turned, p)[0]),
                               overlap, atol=1e-12)


def _model(disc_pos, disc_vel, radius, block, *, kn=1e6, friction=0.5, gravity=(0.0, 0.0),
           contact_damping=0.0, local_damping=0.0, block_kn=1e6, dt=None):
    parts = jdem.make_particles(np.asarray(disc_pos, float), np.full(len(disc_pos), radius),
                                density=2500.0, vel=np.asarray(disc_vel, float))
    state, config = jdem.make_state(parts)
    bstate, bconfig = bk.make_state(block)
    model = coupling.couple(state, bstate)
    params = jdem.make_params(dim=2, kn=kn, friction=friction, gravity=list(gravity),
                              contact_damping=contact_damping, local_damping=local_damping)
    bparams = bk.make_params(kn=block_kn, friction=friction, gravity=gravity,
                             contact_damping=contact_damping, local_damping=local_damping)
    if dt is None:
        dt = 0.1 * coupling.contact_limit(model, params, config)
    params = params._replace(dt=jnp.asarray(dt))
    bparams = bparams._replace(dt=jnp.asarray(dt))
    return model, params, bparams, config, bconfig


def test_a_disc_striking_a_free_block_conserves_momentum_and_angular_momentum():
    """No gravity, no damping, friction 0.5: a disc hits a free square off its
    centre line, so the block is pushed and spun and the disc slides on its
    face.  Total momentum and angular momentum about the origin (the bodies'
    spins included) are those before the impact, to round-off, after the
    disc has bounced off; the block moves and turns."""
    block = _square_block(0.0, 0.0, 0.2)
    model, params, bparams, config, bconfig = _model(
        [[-0.06, 0.16]], [[2.0, -0.5]], 0.05, block)
    start = model
    model, hist, *_ = coupling.run(model, params, bparams, config, bconfig, 4000,
                                   record_every=100, progress=False)

    def totals(m):
        p, b = m.discs.particles, m.blocks.blocks
        mom = np.asarray(p.mass @ p.vel + b.mass @ b.vel)
        cross = lambda r, v: r[:, 0] * v[:, 1] - r[:, 1] * v[:, 0]
        ang = float(np.sum(np.asarray(p.mass * cross(p.pos, p.vel) + p.inertia * p.angvel))
                    + np.sum(np.asarray(b.mass * cross(b.pos, b.vel) + b.inertia * b.angvel)))
        return mom, ang

    mom0, ang0 = totals(start)
    mom1, ang1 = totals(model)
    p0 = float(np.linalg.norm(mom0))
    assert not bool(np.any(np.asarray(model.shear)))               # they have parted
    np.testing.assert_allclose(mom1, mom0, atol=1e-9 * p0)
    assert abs(ang1 - ang0) < 1e-9 * p0 * 0.2
    b = model.blocks.blocks
    assert float(b.vel[0, 0]) > 0.05 and abs(float(b.angvel[0])) > 0.1


def test_a_block_on_discs_on_a_fixed_block_passes_its_weight_down():
    """Gravity, damping: a 0.3 m square block rests on a row of three discs,
    which rest on a fixed base block.  Settled, the discs push the upper block
    up with its weight and the base down with the weight of the block and the
    discs (to 1e-3), and every disc carries load."""
    r = 0.05
    base = bk.rectangle(-0.5, -0.2, 1.0, 0.2)
    top = bk.rectangle(-0.15, 2 * r, 0.3, 0.3)
    blocks = bk.make_blocks([base, top], 2500.0, fixed=[0])
    xs = [-0.1, 0.0, 0.1]
    model, params, bparams, config, bconfig = _model(
        [[x, r] for x in xs], [[0.0, 0.0]] * 3, r, blocks, kn=1e7, block_kn=1e7,
        gravity=(0.0, -9.81), contact_damping=0.3, local_damping=0.7, friction=0.5)
    model, hist, *_ = coupling.run(model, params, bparams, config, bconfig, 20_000,
                                   record_every=1000, progress=False)
    g = 9.81
    m_top = float(model.blocks.blocks.mass[1])
    m_discs = float(jnp.sum(model.discs.particles.mass))
    on = np.asarray(model.on_blocks)
    np.testing.assert_allclose(on[1], [0.0, m_top * g], rtol=1e-3, atol=1e-3 * m_top * g)
    np.testing.assert_allclose(on[0], [0.0, -(m_top + m_discs) * g], rtol=1e-3,
                               atol=1e-3 * m_top * g)
    _, _, _, _, _, info = coupling.disc_block_forces(
        model.blocks.blocks, model.discs.particles, model.shear, params, config)
    assert np.all(np.asarray(info.touching)[:, :3])               # every disc on both blocks
    assert np.all(np.isfinite(hist["disc_pos"]))


def test_coupled_steps_refuse_unequal_time_steps_gravities_and_unknown_materials():
    """Each refusal names the field and its value."""
    block = _square_block(0.0, 0.0, 0.2)
    model, params, bparams, config, bconfig = _model([[-0.06, 0.1]], [[0.0, 0.0]], 0.05,
                                                     block)
    with pytest.raises(InputError, match="must be\\s+equal"):
        coupling.check_timestep(model, params, bparams._replace(dt=2 * bparams.dt), config)
    with pytest.raises(InputError, match="block_material = 3"):
        coupling.check_timestep(model, params, bparams, config, block_material=3)
    fast = params._replace(dt=100 * params.dt)
    with pytest.raises(InputError, match="params.dt"):
        coupling.check_timestep(model, fast, bparams._replace(dt=fast.dt), config)
    with pytest.raises(InputError, match="block_params.gravity"):
        coupling.run(model, params, bparams._replace(gravity=jnp.asarray([0.0, -9.81])),
                     config, bconfig, 10, progress=False)


def test_the_block_velocity_after_an_impact_is_differentiable_in_the_contact_stiffness():
    """d(block velocity after a disc's impact) / d(k_n of the disc–block contact)
    through the coupled rollout (jax.grad) equals a central difference to 1e-6."""
    block = _square_block(0.0, 0.0, 0.2)
    model, params, bparams, config, bconfig = _model([[-0.0499, 0.12]], [[2.0, 0.0]], 0.05,
                                                     block, friction=0.3)

    def block_speed(kn):
        p = params._replace(kn=kn * jnp.ones_like(params.kn), ks=kn * jnp.ones_like(params.ks))
        m, _ = coupling.rollout(model, p, bparams, config, bconfig, 1, 20, sharp_corners=True,
                                coulomb_only=True)
        return m.blocks.blocks.vel[0, 0]

    kn = jnp.asarray(1e6)
    grad = float(jax.jit(jax.grad(block_speed))(kn))   # one program: eagerly, the forward
                                                       # and backward passes compile apart
    h = 1e-4 * float(kn)
    fd = (float(block_speed(kn + h)) - float(block_speed(kn - h))) / (2 * h)
    print(grad, fd, float(block_speed(kn)))
    assert float(block_speed(kn)) > 0.01                          # the block was hit
    assert abs(grad) > 0 and abs(grad / fd - 1) < 1e-6
