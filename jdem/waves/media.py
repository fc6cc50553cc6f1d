"""Elastic media for wave problems (001 §2.2, §3.1): parameters that give a
chosen P-wave speed, square and random bonded packings and random packings
with regular edges (Patterns A, B and C of 001 Fig 10) and a stable time step
for them.

Citations ("001 eq 10") refer to the documents listed in REFERENCES.md.
"""
from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from jdem import timestep
from jdem.bond import bonds_for_pairs
from jdem.specimen import generate
from jdem.specimen.bonding import near_pairs
from jdem.specimen.lattice import bond_touching, lattice_packing
from jdem.state import Params, make_params, make_particles
from jdem.validate import InputError, require_positive


def wave_params(c_p, density, *, bond_poisson=0.0, dt=1.0, dim=2) -> Params:
    """Params for elastic wave problems with linked-bar bonds (002 §1).

    The bond modulus is E_b = rho c_P^2 (001 eq 10, 11 with the whole stiffness
    in the bond): in a square arrangement of equal discs the bond stiffness
    K_n = E_b A_c / L = E_b makes the 1D P-wave speed c_P.  Bonds never break
    (strengths 1e12 Pa), friction and damping are zero (001 §2.2), unbonded
    contacts (rare, in random packings) get k_n = k_s = E_b x 1 m.
    """
    c = float(require_positive("c_p", c_p))
    rho = float(require_positive("density", density))
    e = rho * c * c
    return make_params(dim=dim, dt=dt, kn=e, ks=e, friction=0.0, bond_youngs=e,
                       bond_poisson=bond_poisson, bond_tensile=1e12, bond_cohesion=1e12,
                       bond_tensile_strain=0.0, bond_shear_strain=0.0)



def contact_modulus(c_p, density, alpha_c=0.5):
    """E_c = alpha_c rho c_P^2 [Pa] (001 eq 11, alpha_c = 0.5): the modulus 001
    §3.1 puts into eq 14 in place of the assembly's E (with nu = 0)."""
    return float(alpha_c) * float(require_positive("density", density)) * \
        float(require_positive("c_p", c_p)) ** 2



def square_packing(nx, ny, radius, *, origin=(0.0, 0.0)):
    """Centres (nx ny, 2) and radii of equal discs in a square arrangement, row by
    row from the lower left (Pattern A of 001 Fig 2), lower-left corner at ``origin``
    (:func:`jdem.specimen.lattice.lattice_packing` with ``"square"``)."""
    for name, v in (("nx", nx), ("ny", ny)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise InputError(f"{name} must be a positive integer, got {v!r}")
    return lattice_packing("square", (nx, ny), radius, origin=origin)



def square_density(density):
    """Disc density [kg/m^3] that gives the macroscopic density ``density`` in a
    square arrangement: m = rho (2r)^2, i.e. rho_disc = 4 rho / pi."""
    return 4.0 * float(require_positive("density", density)) / math.pi



def _rotation_held(particles, fix_rotation):
    """``particles`` with every rotation fixed when ``fix_rotation`` (001 §2.2)."""
    if not fix_rotation:
        return particles
    return particles._replace(fixed_rot=jnp.ones_like(particles.fixed_rot))


def lattice(pos, rad, disc_density, *, fix_rotation=False, dtype=None):
    """Particles and bonds of an assembly whose touching neighbours are bonded."""
    p = _rotation_held(make_particles(pos, rad, density=disc_density, dtype=dtype), fix_rotation)
    return p, bond_touching(p)



def random_packing(length, height, r_min, r_max, *, density=2500.0, seed=0, fix_rotation=False):
    """A bonded random packing of [0, length] x [0, height] (Pattern B of 001 Fig 2:
    radii uniform in [r_min, r_max]) from :func:`jdem.specimen.generate`, with
    disc density rho / (1 - porosity) so that the macroscopic density is
    ``density``.  Returns ``(particles, bonds, porosity)``."""
    sp = generate("rectangle", (float(length), float(height)), r_min, r_max, seed=seed)
    solid = 1.0 - sp.porosity
    p = sp.particles
    parts = _rotation_held(make_particles(np.asarray(p.pos), np.asarray(p.radius),
                                          density=density / solid), fix_rotation)
    return parts, sp.bonds, float(sp.porosity)



EDGE_SIDES = ("left", "right")


def edge_packing(length, height, r_min, r_max, edge_radius, *, sides=EDGE_SIDES,
                 density=2500.0, seed=0, fix_rotation=False, edge_gap=None):
    """Pattern C of 001 §2.3.1 (Fig 10(c)): a random interior (radii uniform in
    [r_min, r_max], :func:`jdem.specimen.generate`) between columns of equal
    discs of radius ``edge_radius`` [m] on the ``sides`` ("left", "right") of
    [0, length] x [0, height], so that every boundary disc has the same width D
    (001 Fig 11) while the interior stays random.

    ``height`` must hold a whole number of edge discs (2 edge_radius each).  The
    interior fills the box between the columns; its own bonds are those of the
    generator (gap <= its gap tolerance); a column disc is bonded to its column
    neighbours and to every interior disc within ``edge_gap`` [m] (default half
    the interior's mean radius: the column is straight, the interior's face is
    not).  Disc density is rho / (1 - porosity) over the whole bar, as in
    :func:`random_packing`.  Returns ``(particles, bonds, porosity, is_edge)``,
    ``is_edge`` (N,) bool marking the column discs.
    """
    length = float(require_positive("length", length))
    height = float(require_positive("height", height))
    r_e = float(require_positive("edge_radius", edge_radius))
    bad = [s for s in sides if s not in EDGE_SIDES]
    if bad or not sides:
        raise InputError(f"sides must be a non-empty subset of {EDGE_SIDES}, got {sides!r}")
    n_col = height / (2.0 * r_e)
    if abs(n_col - round(n_col)) > 1e-9 * n_col:
        raise InputError(f"edge_radius = {edge_radius!r}: height {height!r} holds "
                         f"{n_col:.4f} edge discs, not a whole number")
    n_col = int(round(n_col))
    x0 = 2.0 * r_e if "left" in sides else 0.0
    x1 = length - 2.0 * r_e if "right" in sides else length
    if x1 - x0 <= 4.0 * float(r_max):
        raise InputError(f"edge_radius = {edge_radius!r} leaves no room for the interior of a "
                         f"{length!r} m bar")
    sp = generate("rectangle", (x1 - x0, height), r_min, r_max, seed=seed)
    pos_in = np.asarray(sp.particles.pos, np.float64)[np.asarray(sp.particles.valid)]
    rad_in = np.asarray(sp.particles.radius, np.float64)[np.asarray(sp.particles.valid)]
    pos_in = pos_in + np.array([x0, 0.0])
    y = r_e * (1.0 + 2.0 * np.arange(n_col))
    cols = [np.stack([np.full(n_col, x), y], axis=1)
            for side, x in (("left", r_e), ("right", length - r_e)) if side in sides]
    pos = np.concatenate([pos_in, *cols])
    rad = np.concatenate([rad_in, np.full(n_col * len(cols), r_e)])
    is_edge = np.arange(rad.size) >= rad_in.size
    g_in = float(sp.info["gap_tolerance"])
    g_edge = 0.5 * float(rad_in.mean()) if edge_gap is None else float(
        require_positive("edge_gap", edge_gap))
    i, j, gap = near_pairs(pos, rad, max(g_in, g_edge))
    keep = (gap <= g_in) | ((is_edge[i] | is_edge[j]) & (gap <= g_edge))
    solid = float(np.sum(math.pi * rad ** 2)) / (length * height)
    parts = _rotation_held(make_particles(pos, rad, density=density / solid), fix_rotation)
    bonds = bonds_for_pairs(i[keep], j[keep], 2, dtype=parts.pos.dtype)
    return parts, bonds, 1.0 - solid, is_edge



def stable_dt(state, params, config, factor=0.5):
    """``factor`` times the critical time step of the bonded assembly [s]."""
    crit = float(timestep.critical_timestep(state, params._replace(dt=jnp.asarray(1.0)), config))
    if not np.isfinite(crit):
        raise InputError("stable_dt: nothing is bonded or touching")
    return factor * crit
