"""Editing specimens: host arrays of a specimen, a subset of particles with its
bonds renumbered (:func:`subset`, :func:`remove`), excavation of a running
state at fixed capacity (:func:`excavate`), and the flattened disc of the
Brazilian test.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jdem.state import Particles
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
