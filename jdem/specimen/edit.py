"""Editing specimens: host arrays of a specimen, a subset of particles with its
bonds renumbered (:func:`subset`, :func:`remove`), excavation of a running
state at fixed capacity (:func:`excavate`), and the flattened disc of the
Brazilian test, and the embedding of a packing (:func:`embed`).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jdem.bond import create_bonds
from jdem.specimen.bonding import near_pairs
from jdem.specimen.container import Specimen, finite_number, particle_volume
from jdem.state import Particles, make_particles
from jdem.validate import InputError


def as_arrays(specimen):
    """``(particles, bonds, info)`` from a :class:`Specimen`, a ``(particles, bonds)``
    pair or a ``(particles, bonds, info)`` triple."""
    if hasattr(specimen, "particles") and hasattr(specimen, "bonds"):
        return specimen.particles, specimen.bonds, dict(getattr(specimen, "info", {}) or {})
    if len(specimen) == 3:
        particles, bonds, info = specimen
        return particles, bonds, dict(info or {})
    particles, bonds = specimen
    return particles, bonds, {}


def require_fresh(bonds, who):
    """InputError naming ``who`` unless every valid bond is intact and at rest:
    the edits that rebuild bonds (plates, embedding) start them at rest."""
    if np.any(np.asarray(bonds.broken)[np.asarray(bonds.valid)]) or \
            np.any(np.asarray(bonds.normal_force) != 0):
        raise InputError(f"{who} needs a fresh specimen (its bonds at rest, none broken)")


def subset(particles, bonds, keep):
    """The particles with ``keep`` (N,) true and the bonds between them, renumbered.

    Returns ``(particles, bonds, rows)``: ``rows`` (n,) are the kept particles'
    old indices.  Bonds with an end outside the subset are dropped; the others
    keep their state (forces, damage, flags)."""
    keep = np.asarray(keep, bool) & np.asarray(particles.valid, bool)
    rows = np.nonzero(keep)[0]
    new_index = np.cumsum(keep) - 1
    parts = Particles(*[jnp.asarray(np.asarray(a)[keep]) for a in particles])
    bi, bj = np.asarray(bonds.i), np.asarray(bonds.j)
    bv = np.asarray(bonds.valid, bool)
    inside = bv & keep[bi] & keep[bj]
    sel = np.nonzero(inside)[0]
    new_bonds = jax.tree_util.tree_map(lambda a: jnp.asarray(np.asarray(a)[sel]), bonds)
    new_bonds = new_bonds._replace(i=jnp.asarray(new_index[bi[sel]], jnp.int32),
                                   j=jnp.asarray(new_index[bj[sel]], jnp.int32))
    return parts, new_bonds, rows


def remove(particles, bonds, drop):
    """The specimen without the particles where ``drop`` (N,) is true, and
    without their bonds; the rest renumbered (:func:`subset`).  Returns
    ``(particles, bonds, rows)``.  Use it before a run (a hole in a specimen,
    a notch); for a state in the middle of a run use :func:`excavate`."""
    return subset(particles, bonds, ~np.asarray(drop, bool))


def excavate(state, drop):
    """The state with the particles where ``drop`` (N,) is true taken out,
    keeping every capacity and index (no recompilation, jit-able):

    * the particles become invalid rows (``valid`` false): they no longer move,
      touch anything or count in measurements, their velocities and applied
      loads are zeroed;
    * their bonds become invalid rows (they are not "broken": they no longer
      exist, so they leave the fracture degree's count as well);
    * their listed contacts become invalid and lose their shear history; their
      wall contacts lose theirs.

    The rest of the state is unchanged, so the run goes on from the stresses it
    had: the excavation of a tunnel in a stressed rock mass (000 §9).  Shapes:
    ``drop`` (N,) bool; a batched state takes (B, N)."""
    p = state.particles
    drop = jnp.asarray(drop, bool) & p.valid
    keep = ~drop
    zero_d = lambda a: jnp.where(drop.reshape(drop.shape + (1,) * (a.ndim - drop.ndim)),
                                 jnp.zeros_like(a), a)
    particles = p._replace(valid=keep & p.valid, vel=zero_d(p.vel), angvel=zero_d(p.angvel),
                           ext_force=zero_d(p.ext_force), ext_torque=zero_d(p.ext_torque))
    take = lambda idx: jnp.take_along_axis(drop, idx, axis=-1) if drop.ndim > 1 else drop[idx]
    b = state.bonds
    bonds = b._replace(valid=b.valid & ~(take(b.i) | take(b.j)))
    c = state.contacts
    gone = take(c.i) | take(c.j)
    contacts = c._replace(valid=c.valid & ~gone,
                          shear=jnp.where(gone[..., None], jnp.zeros_like(c.shear), c.shear))
    w = state.walls
    walls = w._replace(shear=jnp.where(drop[..., None, :, None], jnp.zeros_like(w.shear), w.shear))
    return state._replace(particles=particles, bonds=bonds, contacts=contacts, walls=walls)


def flatten_disc(specimen_disc, flat_angle_deg):
    """A Brazilian disc with two flat loading faces ("flattened Brazilian disc"):
    the particles reaching beyond the chords at +-``flat_angle_deg`` / 2 from the
    loaded (vertical) diameter are removed, with their bonds.  Returns
    ``(particles, bonds, info)`` (info with ``radius``, ``centre``,
    ``flat_angle_deg``), usable as the specimen of :data:`jdem.lab.BRAZILIAN`."""
    particles, bonds, info = as_arrays(specimen_disc)
    pos = np.asarray(particles.pos, np.float64)
    rad = np.asarray(particles.radius, np.float64)
    valid = np.asarray(particles.valid, bool)
    if "radius" in info:
        big_r = float(info["radius"])
        centre = np.asarray(info.get("centre", (big_r, big_r)), np.float64)
    else:
        lo, hi = (float(np.min(pos[valid, 1] - rad[valid])), float(np.max(pos[valid, 1] + rad[valid])))
        big_r = 0.5 * (hi - lo)
        x_lo = float(np.min(pos[valid, 0] - rad[valid]))
        x_hi = float(np.max(pos[valid, 0] + rad[valid]))
        centre = np.array([0.5 * (x_lo + x_hi), 0.5 * (hi + lo)])
    half = np.deg2rad(float(flat_angle_deg)) / 2.0
    if not 0.0 <= half < np.pi / 4:
        raise InputError(f"flat_angle_deg must lie in [0, 90), got {flat_angle_deg!r}")
    y_flat = big_r * np.cos(half)
    keep = valid & (np.abs(pos[:, 1] - centre[1]) + rad <= y_flat)
    parts, new_bonds, _ = subset(particles, bonds, keep)
    out_info = dict(info, radius=big_r, centre=tuple(float(c) for c in centre),
                    flat_angle_deg=float(flat_angle_deg))
    return parts, new_bonds, out_info


def embed(specimen, scale=None, *, area_fraction=None, gap_tolerance=None):
    """The specimen with every radius times ``scale`` (>= 1) at fixed centres, and
    rebonded: the "embedding" (颗粒间嵌入量) by which 002 §1.4 raises the mean
    coordination number beyond what a packing of touching discs has.

    ``specimen``       a fresh :class:`Specimen` (bonds at rest, none broken)
    ``scale``          radius factor >= 1; the solid area (volume) grows by
                       ``scale**dim``: the seed's 10 cm blocks hold 0.83-1.17 times
                       their area in discs (002 §1.4, cases 2-4), against ~0.83 for
                       a random packing of touching discs
    ``area_fraction``  instead of ``scale``: the solid area (volume) over the box
                       to reach (the seed's UCS specimen: 0.895, 002 §2.1); the
                       scale is (area_fraction / the specimen's own) ** (1 / dim)
    ``gap_tolerance``  [m] bond every pair whose gap is at most this (overlaps
                       have a negative gap); default: the specimen's own
                       ``info["gap_tolerance"]`` times ``scale`` (the same gap
                       relative to the radii)

    Masses keep each particle's density.  Bonds are created at rest
    (:func:`jdem.bond.create_bonds`): a bond's force is incremental, so the
    overlaps carry no stress, and bonded pairs do not touch as contacts.  A
    bond's stiffness E A_c / (R1 + R2) (002 eq 1, 2) is that of the scaled
    radii whatever the overlap.  ``porosity`` is 1 - (solid area / volume) /
    box and is negative once the discs hold more than the box;
    ``coordination`` is N-bar of the new bonds; ``info`` gains ``embedding``
    (the scale), ``area_fraction`` (solid / box), and updated ``r_min``,
    ``r_max``, ``r_mean``, ``max_overlap`` [m], ``max_overlap_ratio`` (/ the
    mean radius), ``gap_tolerance``, ``n_bonds`` and ``n_pairs``.
    """
    if not isinstance(specimen, Specimen):
        raise InputError("embed takes a jdem.specimen.Specimen (it needs the box)")
    if (scale is None) == (area_fraction is None):
        raise InputError(f"embed takes scale or area_fraction, one of them; got scale = "
                         f"{scale!r}, area_fraction = {area_fraction!r}")
    if area_fraction is not None:
        target = finite_number("area_fraction", area_fraction)
        # Specimen.porosity = 1 - solid / box (jdem.specimen.container)
        dim = specimen.particles.pos.shape[1]
        scale = (target / (1.0 - float(specimen.porosity))) ** (1.0 / dim)
    s = finite_number("scale", scale)
    if s < 1.0:
        raise InputError(f"scale must be >= 1 (embedding grows the radii), got {scale!r}")
    particles, bonds, info = as_arrays(specimen)
    require_fresh(bonds, "embed")
    valid = np.asarray(particles.valid, bool)
    pos = np.asarray(particles.pos, np.float64)[valid]
    rad = np.asarray(particles.radius, np.float64)[valid]
    dim = pos.shape[1]
    if gap_tolerance is None:
        if "gap_tolerance" not in info:
            raise InputError("embed: the specimen's info has no gap_tolerance; pass one")
        gap = float(info["gap_tolerance"]) * s
    else:
        gap = finite_number("gap_tolerance", gap_tolerance)
    density = np.asarray(particles.mass, np.float64)[valid] / particle_volume(rad, dim)
    new = make_particles(pos, rad * s, density=density,
                         material=np.asarray(particles.material)[valid],
                         dtype=particles.pos.dtype)
    new_bonds = create_bonds(new, dim, gap_tolerance=gap)
    n_bonds = int(np.sum(np.asarray(new_bonds.valid)))
    r = np.asarray(new.radius, np.float64)
    lo, hi = (np.asarray(c, np.float64) for c in specimen.box)
    box = float(np.prod(hi - lo)) if "radius" not in info else \
        float(np.pi * float(info["radius"]) ** 2)
    fraction = float(np.sum(particle_volume(r, dim))) / box
    _, _, gaps = near_pairs(pos, r, 0.0)
    overlap = max(0.0, float(-np.min(gaps, initial=0.0)))
    out_info = dict(info, embedding=s, area_fraction=fraction, r_min=float(r.min()),
                    r_max=float(r.max()), r_mean=float(r.mean()), max_overlap=overlap,
                    max_overlap_ratio=overlap / float(r.mean()), gap_tolerance=gap,
                    n_bonds=n_bonds, n_pairs=n_bonds)
    return specimen._replace(particles=new, bonds=new_bonds, porosity=1.0 - fraction,
                             coordination=2.0 * n_bonds / r.size, info=out_info)
