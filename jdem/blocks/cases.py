"""The book's verification cases for the block method, set up once for the tests
and the experiments (000 §2.2, §3.4, §9.2.1, §9.2.2).

Citations ("000 eq 9-3") refer to the documents listed in REFERENCES.md.

* :func:`incline`: a block on a fixed base under gravity tilted by the slope
  (the same as a tilted base): sliding, toppling, both or neither
  (:func:`onset_regime` from rigid-body dynamics, :func:`observed_regime` of a run).
* :func:`stack`: blocks stacked on a fixed base, to be damped to rest.
* :func:`joint_chain`: a wave across a joint (000 §9.2.1, eq 9-1..9-6) in its
  one-dimensional form: a row of square blocks glued face to face (the intact
  rock: per pair a spring k = E h / dx), one joint of stiffness K = kappa h in
  the middle, and an incident pulse from the left.  :func:`lattice_transmission`
  is the exact transmission and reflection of that row at a frequency, and
  :func:`continuum_transmission` its long-wave limit, the displacement-
  discontinuity joint |T| = (1 + (omega Z / 2 K)^2)^(-1/2) between half-spaces
  of impedance Z = rho c h.
* :func:`jointed_mass`: a wall of blocks cut by a horizontal and a vertical
  joint set, staggered (000 §9.2.2, fig 9-3) or a square grid, with the book's
  basalt joint stiffnesses; :func:`load_jointed_mass` applies the book's normal
  stresses level by level and returns the strains, to compare with
  :func:`jointed_mass_moduli_rigid` (eq 9-7…9-10 in the rigid-block limit).
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jdem.blocks.cycle import glue_joints, make_params, make_state, recommended_timestep
from jdem.blocks.geometry import make_blocks, rectangle

G = 9.81


def incline(width, height, slope_deg, phi_deg, *, kn=1e9, contact_damping=0.3, density=2500.0,
            safety=0.5):
    """A b x h block centred on a fixed 4 m base, joint friction angle ``phi_deg``,
    gravity at ``slope_deg`` from the base's normal (downhill = +x).  Returns
    ``(state, params, config)`` with a safe time step."""
    base = rectangle(-2.0, -1.0, 4.0, 1.0)
    blocks = make_blocks([base, rectangle(-width / 2, 0.0, width, height)], density, fixed=[0])
    state, config = make_state(blocks)
    th = np.deg2rad(slope_deg)
    p = make_params(kn=kn, friction=np.tan(np.deg2rad(phi_deg)), contact_damping=contact_damping,
                    gravity=G * np.array([np.sin(th), -np.cos(th)]))
    return state, p._replace(dt=jnp.asarray(recommended_timestep(blocks, p, safety))), config


def onset_regime(width, height, slope_deg, phi_deg):
    """What a block (b x h) on an incline does first, from rigid-body dynamics
    at rest: the one mode whose contact force is consistent.

    * stays: tan theta <= b / h (the weight's line inside the base) and theta <= phi;
    * topples: it turns about its downhill corner with alpha = M / I_pivot,
      I_pivot = m (b^2 + h^2) / 3, and the corner holds: the force it needs,
      F = m (a_centroid - g), is inside the friction cone |F_t| <= mu F_n;
    * slides: theta > phi and the sliding contact force (inclined at phi to the
      normal) passes through the base, mu <= b / h, so it does not turn;
    * both, otherwise.

    The static chart (slides iff theta > phi, topples iff tan theta > b / h)
    differs in its "slides and topples" region: there a block may only topple
    (the turning block's own acceleration unloads the friction) or only slide."""
    th, mu = np.deg2rad(slope_deg), np.tan(np.deg2rad(phi_deg))
    if np.tan(th) <= width / height and slope_deg <= phi_deg:
        return "stable"
    if np.tan(th) > width / height:
        alpha = G * (width / 2 * np.cos(th) - height / 2 * np.sin(th)) / \
            ((width ** 2 + height ** 2) / 3)
        f_t = alpha * (-height / 2) - G * np.sin(th)        # per unit mass
        f_n = alpha * (-width / 2) + G * np.cos(th)
        if abs(f_t) <= mu * f_n:
            return "topples"
    if slope_deg > phi_deg and mu <= width / height:
        return "slides"
    return "both"


def observed_regime(history, width, height, *, turn=0.05, slip=1e-3):
    """What a run of :func:`incline` did first: "stable", "topples", "slides" or
    "both" (``history`` from :func:`jdem.blocks.cycle.run`).

    The block turned if its angle exceeds ``turn`` [rad]; it slid if its
    downhill base corner (the pivot of a toppling block) has moved more than
    ``slip`` [m] by the record where it first turned that far (by the last
    record if it never did).  Judged there, near the onset, because a toppling
    block's friction demand changes as it turns (a pivot that holds at first
    may slip later)."""
    a = np.asarray(history["angle"][:, 1])
    corner = np.asarray(history["pos"][:, 1, 0]) + width / 2 * np.cos(a) + height / 2 * np.sin(a)
    over = np.flatnonzero(np.abs(a) > turn)
    k = int(over[0]) if over.size else len(a) - 1
    turned, slid = bool(over.size), bool(corner[k] - width / 2 > slip)
    return {(False, False): "stable", (True, False): "topples", (False, True): "slides",
            (True, True): "both"}[(turned, slid)]


def stack(rects, *, kn=5e8, friction=0.6, contact_damping=0.2, local_damping=0.7,
          density=2600.0):
    """Blocks ``rects`` = [(x0, y0, width, height), ...] above a fixed 4 m base whose
    top is y = 0.  Returns ``(state, params, config)`` (block 0 is the base)."""
    polys = [rectangle(-2.0, -1.0, 4.0, 1.0)] + [rectangle(*r) for r in rects]
    blocks = make_blocks(polys, density, fixed=[0])
    state, config = make_state(blocks)
    p = make_params(kn=kn, friction=friction, contact_damping=contact_damping,
                    local_damping=local_damping)
    return state, p._replace(dt=jnp.asarray(recommended_timestep(blocks, p))), config


class Chain(NamedTuple):
    """What a wave-across-a-joint row is made of (SI units).

    joint      index of the last block left of the joint
    mass       block mass per unit thickness [kg/m]
    k_rock     spring of a glued rock face, both contact points together [N/m]
    k_joint    spring of the face at the joint: rock and joint K = kappa h in
               series, 1 / (1 / k_rock + 1 / K) [N/m]
    dx         block width [m]
    wave_speed sqrt(k_rock / mass) dx [m/s], the long-wave speed of the row
    """

    joint: int
    mass: float
    k_rock: float
    k_joint: float
    dx: float
    wave_speed: float


def row_wave(dx, density, modulus, wavelength):
    """Block mass [kg/m], face spring k = E h / dx [N/m] and the exact frequency
    omega = 2 sqrt(k / m) sin(q dx / 2) [rad/s] of a wave of ``wavelength``
    blocks in a row of square blocks of edge ``dx`` (per unit thickness)."""
    mass = density * dx * dx
    k_rock = modulus                             # E h / dx with h = dx
    q = 2 * np.pi / (wavelength * dx)
    return mass, k_rock, 2 * np.sqrt(k_rock / mass) * np.sin(q * dx / 2)


def joint_chain(n_blocks, *, dx=0.1, density=2650.0, modulus=26.67e9, joint_stiffness=1e10,
                wavelength=20, cycles=1.0, amplitude=1e-6, start=None, safety=0.2):
    """A row of ``n_blocks`` square blocks (edge ``dx``) glued face to face, with
    a joint of specific stiffness ``joint_stiffness`` [Pa/m] between blocks
    n/2 - 1 and n/2, and a right-going Gaussian tone burst of ``wavelength``
    blocks, ``cycles`` periods of standard deviation, displacement ``amplitude``
    [m], centred at block ``start`` (default n/4).  The rock is a P-wave medium
    of modulus ``modulus`` [Pa] (000 §9.2.1 uses K = 16.667 GPa, G = 10 GPa:
    K + 4 G / 3 = 30 GPa; the default 26.67 GPa is its E).

    Returns ``(state, params, config, chain, omega)``: omega [rad/s] is the
    burst's centre frequency.  Material 0 is the left rock, 1 the right; the
    joint is the (0, 1) entry of the stiffness table.  No gravity, no damping;
    the faces are glued with strengths far above the wave's forces, so each
    acts as a linear spring both ways.
    """
    h = dx
    xs = np.arange(n_blocks) * dx
    polys = [rectangle(x, 0.0, dx, h) for x in xs]
    mat = (np.arange(n_blocks) >= n_blocks // 2).astype(np.int32)
    blocks = make_blocks(polys, density, material=mat)
    _, k_rock, omega = row_wave(dx, density, modulus, wavelength)
    # the face between the two blocks is a block width of rock plus the joint:
    # their compliances add
    k_joint = 1.0 / (1.0 / k_rock + 1.0 / (joint_stiffness * h))
    kn = np.array([[k_rock, k_joint], [k_joint, k_rock]]) / 2.0     # two points per face
    strong = 1e6 * k_rock * amplitude
    p = make_params(kn=kn, ks=kn, friction=0.0, cohesion=strong, tension=strong,
                    gravity=(0.0, 0.0))
    mass = float(blocks.mass[0])
    speed = np.sqrt(k_rock / mass) * dx
    # the burst: u(x) = A exp(-(x - x0)^2 / 2 s^2) cos(q (x - x0)), v = -c du/dx
    centre = (n_blocks // 4 if start is None else start) * dx + dx / 2
    q = 2 * np.pi / (wavelength * dx)
    sigma = cycles * wavelength * dx
    xc = np.asarray(blocks.pos[:, 0]) - centre
    env = amplitude * np.exp(-0.5 * (xc / sigma) ** 2)
    u = env * np.cos(q * xc)
    du = env * (-xc / sigma ** 2 * np.cos(q * xc) - q * np.sin(q * xc))
    # omega is the row's exact frequency of wavenumber q, so the burst travels right only
    v = -du * (omega / q)
    blocks = blocks._replace(pos=blocks.pos.at[:, 0].add(jnp.asarray(u)),
                             vel=blocks.vel.at[:, 0].set(jnp.asarray(v)))
    state, config = make_state(blocks, skin=0.2 * dx)
    state = glue_joints(state, p, config, tolerance=10 * amplitude)
    p = p._replace(dt=jnp.asarray(recommended_timestep(blocks, p, safety)))
    chain = Chain(joint=n_blocks // 2 - 1, mass=mass, k_rock=k_rock, k_joint=k_joint, dx=dx,
                  wave_speed=float(speed))
    return state, p, config, chain, float(omega)


def lattice_transmission(omega, mass, k_rock, k_joint):
    """Exact transmission and reflection amplitudes (complex, displacement) of a
    harmonic wave of frequency ``omega`` [rad/s] through one spring ``k_joint``
    in an infinite row of masses ``mass`` joined by springs ``k_rock``.

    With u_n = e^{iqn} + r e^{-iqn} left of the joint and t e^{iqn} right of it
    (omega^2 m = 2 k (1 - cos q)), the two end masses' equations give
    K (t e^{iq} - 1 - r) = k (e^{iq} + r e^{-iq} - 1 - r) and
    K (1 + r - t e^{iq}) = k (t - t e^{iq}).  Returns ``(t, r)``.
    """
    omega = np.atleast_1d(np.asarray(omega, dtype=np.float64))
    q = np.arccos(1.0 - mass * omega ** 2 / (2.0 * k_rock))
    k, kj = k_rock, k_joint
    out_t, out_r = [], []
    for e in np.exp(1j * q):
        # unknowns (r, t), the two equations above rearranged
        a = np.array([[k - kj - k / e, kj * e], [kj, k * e - k - kj * e]])
        r, t = np.linalg.solve(a, np.array([kj + k * e - k, -kj]))
        out_t.append(t)
        out_r.append(r)
    return np.array(out_t), np.array(out_r)


def continuum_transmission(omega, impedance, k_joint):
    """|T| and |R| of a linear joint of stiffness K between two like half-spaces
    of impedance Z (force per velocity): T = 1 / sqrt(1 + (omega Z / 2K)^2)."""
    x = np.asarray(omega) * impedance / (2.0 * k_joint)
    return 1.0 / np.sqrt(1.0 + x * x), x / np.sqrt(1.0 + x * x)


def monitor_velocities(state, params, *, blocks):
    """observe function for :func:`jdem.blocks.cycle.rollout`: the x velocity of
    the given blocks (a tuple of indices, bound with functools.partial)."""
    return dict(vx=state.blocks.vel[jnp.asarray(blocks), 0], step=state.step)


def wave_across_joint(stiffness_ratio, *, n_blocks=600, wavelength=20, monitor_offset=80):
    """Transmission and reflection coefficients of a joint, measured as 000
    §9.2.1 does (eq 9-2, 9-3, 9-6: T = (E_T / E_I)^(1/2), R = (E_R / E_I)^(1/2),
    E = rho c int v^2 dt at a point before and a point after the joint), for a
    joint K = omega Z / (2 ``stiffness_ratio``) (so the continuum |T| is
    (1 + stiffness_ratio^2)^(-1/2)).

    The incident burst and its reflection pass the monitor left of the joint at
    different times and are split there; the expected values weight the exact
    lattice |t(omega)|^2, |r(omega)|^2 with the recorded incident spectrum.
    Returns a dict of measured ``T``, ``R``, expected ``T_lattice``,
    ``R_lattice``, the continuum ``T_continuum``, ``R_continuum`` at the centre
    frequency, the absorption ``A`` of eq 9-1 (0 for an elastic joint) and the
    histories.
    """
    import functools

    from jdem.blocks.cycle import rollout

    dx, density, modulus = 0.1, 2650.0, 26.67e9              # joint_chain's defaults
    mass, k_rock, omega = row_wave(dx, density, modulus, wavelength)
    impedance = np.sqrt(k_rock * mass)                       # rho c h of the row [N s/m]
    joint_k = omega * impedance / (2.0 * stiffness_ratio)     # K = kappa h [N/m]
    state, p, config, chain, omega = joint_chain(n_blocks, dx=dx, density=density,
                                                 modulus=modulus, wavelength=wavelength,
                                                 joint_stiffness=joint_k / dx)
    left, right = chain.joint - monitor_offset + 1, chain.joint + monitor_offset
    observe = functools.partial(monitor_velocities, blocks=(left, right))
    start = n_blocks // 4
    transit = chain.dx / chain.wave_speed                   # one block [s]
    reach = 3.5 * wavelength                                # burst half-length [blocks]
    t_end = (right - start + reach) * transit
    n_steps = int(np.ceil(t_end / float(p.dt)))
    _, hist = rollout(state, p, config, n_steps, 1, observe)
    v = np.asarray(hist["vx"])
    t = np.asarray(hist["step"]) * float(p.dt)
    # the reflection's front reaches the left monitor after travelling to the joint and back
    split = (chain.joint - start + (chain.joint - left) - reach) * transit
    inc = t < split
    e_i = np.sum(v[inc, 0] ** 2)
    e_r = np.sum(v[~inc, 0] ** 2)
    e_t = np.sum(v[:, 1] ** 2)
    spec = np.abs(np.fft.rfft(np.where(inc, v[:, 0], 0.0))) ** 2
    w = 2 * np.pi * np.fft.rfftfreq(len(t), float(p.dt))
    band = (w > 0) & (w < 0.999 * 2.0 * np.sqrt(chain.k_rock / chain.mass))  # below cut-off
    tt, rr = lattice_transmission(w[band], chain.mass, chain.k_rock, chain.k_joint)
    total = np.sum(spec)
    t_c, r_c = continuum_transmission(omega, impedance, joint_k)
    tm, rm = np.sqrt(e_t / e_i), np.sqrt(e_r / e_i)
    return dict(T=float(tm), R=float(rm), A=float(np.sqrt(max(0.0, 1 - tm ** 2 - rm ** 2))),
                T_lattice=float(np.sqrt(np.sum(np.abs(tt) ** 2 * spec[band]) / total)),
                R_lattice=float(np.sqrt(np.sum(np.abs(rr) ** 2 * spec[band]) / total)),
                T_continuum=float(t_c), R_continuum=float(r_c), omega=omega,
                joint_stiffness=float(joint_k / chain.dx), time=t, v_left=v[:, 0], v_right=v[:, 1],
                split=float(split))


# ----------------------------------------------------------------------------- 000 §9.2.2
#: the basalt joints of 000 §9.2.2 [Pa/m]: normal and shear stiffness of the
#: horizontal (h) and vertical (v) joints; joint spacing 20 cm
BASALT_JOINTS = dict(k_nh=531.9e9, k_sh=438.9e9, k_nv=395.9e9, k_sv=438.8e9, spacing=0.20)


class JointedMass(NamedTuple):
    """A wall of rigid blocks cut by a horizontal (h) and a vertical (v) joint set,
    on a fixed base with a fixed wall on its left, both rollers (000 §9.2.2,
    fig 9-3).  Block
    0 is the base, 1 the wall, then the rows from the bottom, each from the left.
    ``rows`` lists each row's block indices; ``widths`` every block's width."""

    state: object
    params: object
    config: object
    rows: list
    widths: np.ndarray
    s_s: float
    s_n: float


def jointed_mass(nx=4, ny=5, *, s_s=0.2, s_n=0.2, stagger=True, k_nh=BASALT_JOINTS["k_nh"],
                 k_sh=BASALT_JOINTS["k_sh"], k_nv=BASALT_JOINTS["k_nv"],
                 k_sv=BASALT_JOINTS["k_sv"], friction=0.8, local_damping=0.7,
                 density=2700.0) -> JointedMass:
    """ny rows of blocks s_s wide and s_n high, no gravity.  With ``stagger`` the
    vertical joints of every other row are offset by s_s / 2 (a running bond,
    the staggered joints of fig 9-3; those rows end in half blocks), else the
    joints form a square grid where four blocks meet at each corner.

    Joint stiffnesses are per unit area [Pa/m], the blocks' face stiffness
    (``kn_face``, ``ks_face``: an edge–edge contact of length L is two points
    of k L / 2, 000 §3.4.1, fig 3-13); a corner–edge contact gets the points of
    a whole face, k s / 2.  The sets get their own stiffnesses through the
    material table: a block's material is 2 (row parity) + (column parity), so
    a horizontal joint joins materials of different row parity and a vertical
    one materials of equal row parity; the base (material 4) joins horizontally,
    the wall (5) vertically."""
    if ny < 3 or nx < 2:
        raise ValueError(f"jointed_mass needs nx >= 2 and ny >= 3, got {nx} x {ny}")
    polys = [rectangle(-s_s, -s_n, (nx + 2) * s_s, s_n),               # base
             rectangle(-s_s, 0.0, s_s, (ny + 1) * s_n)]                 # wall
    material, rows, widths = [4, 5], [], [(nx + 2) * s_s, s_s]
    for r in range(ny):
        edges = np.arange(nx + 1) * s_s
        if stagger and r % 2:
            edges = np.concatenate([[0.0], (np.arange(nx) + 0.5) * s_s, [nx * s_s]])
        row = []
        for c in range(edges.size - 1):
            row.append(len(polys))
            polys.append(rectangle(edges[c], r * s_n, edges[c + 1] - edges[c], s_n))
            material.append(2 * (r % 2) + c % 2)
            widths.append(edges[c + 1] - edges[c])
        rows.append(np.asarray(row))
    row_bit = np.array([0, 0, 1, 1, -1, -2])
    horizontal = (row_bit[:, None] != row_bit[None]) & ~np.eye(6, dtype=bool)
    horizontal[5, :] = horizontal[:, 5] = False                # the wall: vertical joints
    horizontal[4, 5] = horizontal[5, 4] = True                 # base-wall: never in contact
    kn_face, ks_face = np.where(horizontal, k_nh, k_nv), np.where(horizontal, k_sh, k_sv)
    face = np.where(horizontal, s_s, s_n)
    # base and wall are rollers (no shear, no friction), so that neither carries
    # part of the load along its face
    roller = np.zeros((6, 6), bool)
    roller[4:, :] = roller[:, 4:] = True
    ks_face = np.where(roller, 0.0, ks_face)
    mu = np.where(roller, 0.0, friction)
    blocks = make_blocks(polys, density, fixed=[0, 1], material=material)
    state, config = make_state(blocks)
    p = make_params(kn=0.5 * kn_face * face, ks=0.5 * ks_face * face, kn_face=kn_face,
                    ks_face=ks_face, friction=mu, local_damping=local_damping,
                    gravity=(0.0, 0.0))
    p = p._replace(dt=jnp.asarray(recommended_timestep(blocks, p)))
    return JointedMass(state, p, config, rows, np.asarray(widths), s_s, s_n)


def jointed_mass_moduli_rigid(k_nh, k_sh, k_nv, k_sv, s_s, s_n):
    """000 eq 9-7…9-10 in the rigid-block limit (E_i, G_i -> infinity, where the
    stress concentration factors b_nn, b_sn drop out): E_n = k_nh s_n,
    E_s = k_nv s_s, G_ns = s_s s_n k_sh k_sv / (s_s k_sv + s_n k_sh),
    nu_ns = 0 [Pa, -].  (Eq 9-8 as printed has k_sv; the s-direction modulus of
    the joints comes from the vertical joints' normal stiffness, k_nv, as eq
    9-7's comes from k_nn.)"""
    return dict(E_n=k_nh * s_n, E_s=k_nv * s_s,
                G_ns=s_s * s_n * k_sh * k_sv / (s_s * k_sv + s_n * k_sh), nu_ns=0.0)


def load_jointed_mass(case: JointedMass, sigma_n, sigma_s, *, steps_per_level=4000):
    """000 §9.2.2's loading: normal stresses on the top (sigma_n) and right
    (sigma_s) faces [Pa, compression positive], one pair per level, each relaxed
    for ``steps_per_level`` steps (dynamic relaxation, 000 §2.4), continuing
    from the last level.  Returns ``((L, 2) strains, state)``: eps_n from the
    mean vertical displacement of the top row against the bottom row over their
    (ny - 1) s_n, eps_s from the horizontal displacement of each row of whole
    blocks' last block against its first over (n - 1) s_s; compression positive.
    The base and wall joints are left out (their contacts differ at the ends of
    a staggered row)."""
    import jax

    from jdem.blocks.cycle import step

    state, p, config = case.state, case.params, case.config
    b0 = state.blocks
    pos0 = np.asarray(b0.pos)
    whole = [r for r in case.rows if np.allclose(case.widths[r], case.s_s)]

    @jax.jit
    def relax(state, ext):
        state = state._replace(blocks=state.blocks._replace(ext_force=ext))
        return jax.lax.fori_loop(0, steps_per_level, lambda _, s: step(s, p, config), state)

    def strains(pos):
        d = pos - pos0
        e_n = (d[case.rows[0], 1].mean() - d[case.rows[-1], 1].mean()) / \
            ((len(case.rows) - 1) * case.s_n)
        e_s = np.mean([(d[r[0], 0] - d[r[-1], 0]) / ((r.size - 1) * case.s_s) for r in whole])
        return e_n, e_s

    out = []
    for sn, ss in zip(np.atleast_1d(sigma_n), np.atleast_1d(sigma_s)):
        ext = np.zeros(b0.ext_force.shape)
        ext[case.rows[-1], 1] -= sn * case.widths[case.rows[-1]]
        ext[[r[-1] for r in case.rows], 0] -= ss * case.s_n
        state = relax(state, jnp.asarray(ext, b0.pos.dtype))
        out.append(strains(np.asarray(state.blocks.pos)))
    return np.asarray(out), state
