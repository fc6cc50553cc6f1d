"""The continuously yielding joint (000 §3.4.1 item 5, Hart–Cundall): the point
law against closed forms and its own identities, and the block engine against
the point law, in float64."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jdem import InputError
from jdem import blocks as bk
from jdem.blocks import joint
from jdem.blocks.cycle import history_field

FN, KS = 1e3, 1e6                                   # N, N/m
MU, MU0 = np.tan(np.deg2rad(30.0)), np.tan(np.deg2rad(45.0))


def _drive(u, roughness, *, fn=FN, kn=0.0):
    """The point law along the shear displacements ``u`` (from 0); with ``kn`` the
    normal force grows by kn times the dilation (constant normal stiffness).
    Returns (s = -F_s, u_p, ratio, dilation) after each increment."""
    out = joint.yielding_shear_path(u, fn, KS, MU, MU0, roughness, kn=kn)
    return np.stack([np.asarray(out[k]) for k in ("shear", "plastic", "ratio", "dilation")],
                    axis=1)


def test_yielding_friction_falls_from_phi0_to_phi():
    """phi_e = phi + R / (u_p + R / (phi_0 - phi)): phi_0 at u_p = 0, half-way at
    u_p = R / (phi_0 - phi), phi as u_p grows; R = 0 gives phi."""
    phi, phi0, r = np.deg2rad(30.0), np.deg2rad(45.0), 1e-3
    mu_e = lambda up, rr=r: float(joint.yielding_friction(up, MU, MU0, rr))  # noqa: E731
    assert mu_e(0.0) == pytest.approx(MU0, rel=1e-12)
    assert mu_e(r / (phi0 - phi)) == pytest.approx(np.tan(0.5 * (phi + phi0)), rel=1e-12)
    assert mu_e(1e3) == pytest.approx(np.tan(phi + r / (1e3 + r / (phi0 - phi))), rel=1e-12)
    assert mu_e(0.0, 0.0) == pytest.approx(MU, rel=1e-12)


def test_without_decay_the_curve_is_the_hyperbolic_closed_form():
    """With R -> infinity (phi_e = phi_0), monotonic shear at constant F_n solves
    ds/du = k_s (1 - s / s_m): s = s_m (1 - exp(-k_s u / s_m)); the explicit
    update converges to it at first order."""
    s_m = FN * MU0
    errors = []
    for n in (1000, 2000):
        u = np.linspace(0.0, 0.01, n + 1)
        s = _drive(u, 1e12)[:, 0]
        exact = s_m * (1.0 - np.exp(-KS * u[1:] / s_m))
        errors.append(np.max(np.abs(s - exact)) / s_m)
    assert errors[1] < 1e-3
    assert errors[0] / errors[1] == pytest.approx(2.0, rel=0.05)


def test_plastic_slip_is_the_slip_less_the_elastic_part():
    """Monotonic loading: du_p = |du| (1 - F) and ds = F k_s du add up to
    u_p = u - s / k_s at every step, whatever R."""
    u = np.linspace(0.0, 0.005, 1001)
    for r in (1e-4, 1e-3):
        out = _drive(u, r)
        np.testing.assert_allclose(out[:, 1], u[1:] - out[:, 0] / KS, rtol=0, atol=1e-15)


def test_peak_then_residual_strength():
    """With decay the curve peaks below F_n tan(phi_0) and then follows the
    falling strength F_n tan(phi_e(u_p)) down towards F_n tan(phi)."""
    u = np.linspace(0.0, 0.05, 10001)
    out = _drive(u, 1e-3)
    s, up = out[:, 0], out[:, 1]
    peak = int(np.argmax(s))
    assert 0 < peak < len(s) - 1000
    assert FN * MU < s[peak] < FN * MU0
    strength = FN * np.asarray(joint.yielding_friction(up, MU, MU0, 1e-3))
    # above the strength by at most the one step it lags behind u_p
    assert np.all(s <= strength + KS * (u[1] - u[0]))
    late = slice(len(s) // 2, None)
    np.testing.assert_allclose(s[late], strength[late], rtol=1e-3)
    assert s[-1] < 1.2 * FN * MU and s[-1] > FN * MU


def test_reversal_unloads_at_the_initial_stiffness():
    """On a reversal gamma := s / s_max (s_max now of the other sign), so F = 1:
    the joint unloads along k_s, then softens towards the opposite strength
    (the hysteresis loop of 000 fig 3-18)."""
    du = 5e-6
    u = np.concatenate([np.arange(0, 401) * du, (400 - np.arange(1, 801)) * du])
    out = _drive(u, 1e-3)
    s, ratio = out[:, 0], out[:, 2]
    s_rev, up_rev = s[399], out[399, 1]
    s_max = FN * float(joint.yielding_friction(up_rev, MU, MU0, 1e-3))
    assert ratio[400] == pytest.approx(-s_rev / s_max, rel=1e-12)
    assert (s[400] - s[399]) / -du == pytest.approx(KS, rel=1e-12)
    assert s[-1] < 0 and abs(s[-1]) < FN * MU0
    assert np.all(np.diff(s[400:]) < 0)


def test_dilation_follows_the_dilation_angle():
    """i = max(0, atan(|s| / sigma_n) - phi): no dilation while |s| < F_n tan(phi),
    then |du| tan(i) per step."""
    u = np.linspace(0.0, 0.004, 801)
    out = _drive(u, 1e-3)
    s, dil = out[:, 0], out[:, 3]
    below = s < FN * MU
    assert np.all(dil[below] == 0.0) and dil[-1] > 0
    i = np.maximum(0.0, np.arctan(s / FN) - np.arctan(MU))
    np.testing.assert_allclose(np.diff(dil), np.diff(u)[1:] * np.tan(i[1:]), rtol=1e-12,
                               atol=1e-18)


def test_the_books_initial_angle_is_refused_with_its_reason():
    with pytest.raises(InputError, match="cy_friction0.*must exceed friction"):
        bk.make_params(kn=1e9, friction=0.6, cy_friction0=0.5)
    with pytest.raises(InputError, match="cohesion.*continuously yielding"):
        bk.make_params(kn=1e9, friction=0.5, cy_friction0=1.0, cohesion=10.0)
    with pytest.raises(InputError, match="cy_roughness"):
        bk.make_params(kn=1e9, cy_friction0=1.0, cy_roughness=-1.0)


def _shear_box(cy_friction0=MU0, roughness=1e-3, *, v=0.1, overlap=1e-6, kn=1e9):
    """A 1 m block pressed 'overlap' into a fixed base and moved along it at v
    [m/s] (both prescribed: constant normal stiffness, as in a shear box whose
    lid cannot rise)."""
    base = bk.rectangle(-2.0, -1.0, 4.0, 1.0)
    lid = bk.rectangle(-0.5, -overlap, 1.0, 0.5)
    blocks = bk.make_blocks([base, lid], 2500.0, fixed=[0, 1], vel=[[0.0, 0.0], [v, 0.0]])
    state, config = bk.make_state(blocks)
    p = bk.make_params(kn=kn, ks=KS, friction=MU, cy_friction0=cy_friction0,
                       cy_roughness=roughness, gravity=(0.0, 0.0))
    return state, p._replace(dt=jnp.asarray(1e-5)), config


def _observe(state, params):
    h = state.contacts.shear * state.contacts.valid[:, None]
    field = lambda name: history_field(h, name)  # noqa: E731
    return dict(s=jnp.sum(field("shear")), plastic=jnp.max(field("plastic")),
                dilation=jnp.max(field("dilation")))


def test_shear_box_follows_the_point_law_with_dilation():
    """The engine's two points of a sheared flush contact each follow the point
    law, the normal force growing by k_n times the dilation; the force on the
    lid resists its motion."""
    state, params, config = _shear_box()
    end, hist = bk.run(state, params, config, 4000, record_every=10, observe=_observe,
                     progress=False)
    kn, overlap, du = 1e9, 1e-6, 0.1 * 1e-5
    u = np.arange(0, 4001) * du
    ref = _drive(u, 1e-3, fn=kn * overlap, kn=kn)[9::10]
    np.testing.assert_allclose(np.abs(hist["s"]), 2.0 * ref[:, 0], rtol=1e-9)
    np.testing.assert_allclose(hist["plastic"], ref[:, 1], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(hist["dilation"], ref[:, 3], rtol=1e-9, atol=1e-18)
    assert ref[-1, 3] > 0.1 * overlap                     # the dilation mattered
    assert abs(hist["s"][-1]) > 2.0 * kn * overlap * MU   # held up by the dilation
    _, force, _, _ = bk.contact_forces(end, params)
    assert float(force[1, 0]) == pytest.approx(-2.0 * ref[-1, 0], rel=1e-3)


def test_shear_force_is_differentiable_in_the_initial_friction():
    """d(shear force)/d tan(phi_0) through the rollout equals central differences;
    a higher initial angle resists more."""
    state, params, config = _shear_box()

    def force(mu0):
        p = params._replace(cy_friction0=jnp.full_like(params.cy_friction0, mu0))
        _, h = bk.rollout(state, p, config, 1, 1500, observe=_observe)
        return h["s"][-1]

    g = float(jax.jit(jax.grad(force))(MU0))      # one program: eagerly, the forward and
                                                   # backward passes compile apart
    e = 1e-6
    fd = (float(force(MU0 + e)) - float(force(MU0 - e))) / (2 * e)
    assert g == pytest.approx(fd, rel=1e-5) and g * float(force(MU0)) > 0


def test_coulomb_joints_are_unchanged_by_the_yielding_path():
    """Where no joint yields continuously, the general path and the one run()
    takes (``coulomb_only``) give the same state bit for bit."""
    state, params, config = _shear_box(cy_friction0=0.0)
    params = params._replace(friction=jnp.full_like(params.friction, 0.3))
    a, _ = bk.rollout(state, params, config, 1, 300)
    b, _ = bk.rollout(state, params, config, 1, 300, coulomb_only=True)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
