"""Elastic loading plates of bonded particles on the top and bottom faces of a 2D
specimen (the steel plates of 002 §1.4, Fig 7).

A plate is ``rows`` rows of equal discs in a triangular (hexagonal close-packed)
arrangement that spans the specimen's width.  Its discs carry their own material
(``material``, default :data:`jdem.materials.PLATEN`), so with per-material bond
fields in ``Params`` (:func:`jdem.materials.rock_params` ``plate_youngs``) the
plate's bonds are steel while the rock's stay rock.  Bonds:

* plate-plate: every touching pair of plate discs (the lattice's neighbours), unless
  ``bond_plate_discs=False``: then each face particle is held by a plate disc of its
  own, free sideways (the seed's UCS boundary, 002 §2.1, without a steel plate's end
  restraint);
* plate-rock: every rock particle whose gap to a disc of the plate's inner row
  is at most ``attach_gap`` [m] is bonded to it.  A bond is created at rest at
  whatever separation it has (:mod:`jdem.bond` counts the opening from
  creation), so a rock particle a little below the face is held without a
  preload.  Such a bond is a bar of two halves in series
  (:func:`jdem.bond.bond_material`): its stiffness is about that of the rock and
  its strength the rock's.

What this changes against a rigid platen: a random packing touches a flat
platen at a few particles only and the others seat first; a plate bonded to
every particle of the face loads them all from the start.  The plate's own
shortening is part of the platen-to-platen displacement; the lab tests divide
it by the rock's height (``info["plate_thickness"]``), so a strain read from the
platens is the rock's plus the plates' own, sigma x 2 x thickness / (E_plate x
height): 3e-4 of the rock's on a 2 cm block of 30 GPa with 0.5 mm plate discs.
"""
from __future__ import annotations

import numpy as np

from jdem.bond import bonds_for_pairs, create_bonds
from jdem.specimen.bonding import near_pairs
from jdem.specimen.container import Specimen
from jdem.specimen.edit import as_arrays, require_fresh
from jdem.state import make_particles
from jdem.validate import InputError

STEEL_DENSITY = 7850.0   #: kg/m^3


def plate_discs(x_lo, x_hi, face_y, radius, rows, downward):
    """``(centres (n, 2), n_inner, r)``: a plate of ``rows`` rows of touching discs
    of radius ``r`` (the nearest to ``radius`` that fits a whole number of
    discs) whose inner row (the first ``n_inner`` centres) is tangent to the line
    y = ``face_y`` with its first and last centres at x_lo and x_hi;
    ``downward``: the plate lies below the face (the bottom plate)."""
    width = x_hi - x_lo
    n_row = max(2, int(round(width / (2.0 * radius))) + 1)
    pitch = width / (n_row - 1)
    radius = 0.5 * pitch
    sign = -1.0 if downward else 1.0
    centres = []
    for k in range(rows):
        y = face_y + sign * (radius + k * np.sqrt(3.0) * radius)
        shift = 0.5 * pitch if k % 2 else 0.0
        xs = x_lo + shift + pitch * np.arange(n_row - (1 if k % 2 else 0))
        centres.append(np.stack([xs, np.full_like(xs, y)], axis=1))
    return np.concatenate(centres), n_row, radius


def add_plates(specimen, *, rows=2, radius=None, material=1, density=STEEL_DENSITY,
               attach_gap=None, bond_plate_discs=True):
    """The specimen with an elastic plate on its top face and one on its bottom.

    ``specimen``  a fresh 2D :class:`jdem.specimen.Specimen` (its bonds at rest)
    ``rows``      rows of discs per plate (>= 1; 2 gives a plate that bends as a
                  beam of thickness ~ (1 + sqrt 3) radius)
    ``radius``    plate disc radius [m] (default: the rock's mean radius), adjusted
                  to the nearest that spans the width with touching discs
    ``material``  the plate discs' material index (default 1, the platen material
                  of :func:`jdem.materials.rock_params`; the lab tests leave bonds
                  to particles of the platens' material out of the fracture degree
                  and the broken-bond counts, which are figures of the rock)
    ``density``   plate density [kg/m^3] (default steel)
    ``attach_gap`` largest gap [m] at which a rock particle is bonded to the plate
                  (default: the rock's mean radius)
    ``bond_plate_discs`` False: the plate discs are bonded to the rock only, not
                  to each other (use ``rows=1``): each face particle is then
                  held in the loading direction by the frictionless platen
                  through its own plate disc and is free sideways and in
                  rotation, as the seed's UCS boundary (002 §2.1: the bottom
                  held normally, the top driven at a velocity), without the
                  end restraint of a bonded steel plate

    The faces are the specimen box's (``Specimen.box``).  Returns a
    :class:`Specimen` with the plate discs appended after the rock particles,
    the bonds rebuilt (rock-rock as before, plus plate-plate and plate-rock) and
    in ``info``: ``n_rock`` (the first n_rock particles are rock), ``plate_rows``,
    ``plate_radius`` (as adjusted), ``plate_thickness`` (face to outer edge [m];
    the lab tests measure strains over the platen distance less two of them,
    i.e. over the rock), ``plate_material``, ``n_plate_discs``, ``n_plate_rock_bonds``
    (per plate, bottom and top) and ``attach_gap``.  ``coordination`` stays the
    rock's.
    """
    if not isinstance(specimen, Specimen):
        raise InputError("add_plates takes a jdem.specimen.Specimen (it needs the box)")
    particles, bonds, info = as_arrays(specimen)
    pos = np.asarray(particles.pos, np.float64)
    rad = np.asarray(particles.radius, np.float64)
    valid = np.asarray(particles.valid, bool)
    if pos.shape[1] != 2:
        raise InputError(f"add_plates builds 2D plates; the specimen has dimension {pos.shape[1]}")
    if int(rows) < 1:
        raise InputError(f"rows must be >= 1, got {rows!r}")
    if int(material) < 1:
        raise InputError(f"material must be >= 1 (0 is the rock), got {material!r}")
    require_fresh(bonds, "add_plates")
    pos, rad = pos[valid], rad[valid]
    mat = np.asarray(particles.material)[valid]
    r_mean = float(np.mean(rad))
    radius = r_mean if radius is None else float(radius)
    attach_gap = r_mean if attach_gap is None else float(attach_gap)
    if not (np.isfinite(radius) and radius > 0):
        raise InputError(f"radius must be > 0, got {radius!r}")
    if not (np.isfinite(attach_gap) and attach_gap >= 0):
        raise InputError(f"attach_gap must be >= 0, got {attach_gap!r}")
    (x_lo, y_lo), (x_hi, y_hi) = (np.asarray(c, np.float64) for c in specimen.box)
    bottom, n_inner, radius = plate_discs(x_lo, x_hi, y_lo, radius, int(rows), downward=True)
    top, _, _ = plate_discs(x_lo, x_hi, y_hi, radius, int(rows), downward=False)
    n_rock = pos.shape[0]
    all_pos = np.concatenate([pos, bottom, top])
    all_rad = np.concatenate([rad, np.full(len(bottom) + len(top), radius)])
    dens_rock = np.asarray(particles.mass)[valid] / (np.pi * rad ** 2)
    all_dens = np.concatenate([dens_rock, np.full(len(bottom) + len(top), float(density))])
    all_mat = np.concatenate([mat, np.full(len(bottom) + len(top), int(material))])
    new = make_particles(all_pos, all_rad, density=all_dens, material=all_mat,
                         dtype=particles.pos.dtype)

    # pairs: the rock's bonds as they were; the plates' lattice neighbours; and
    # rock particles within attach_gap of a plate's inner row
    old = np.asarray(bonds.valid, bool)
    renumber = np.cumsum(valid) - 1
    pi, pj = [renumber[np.asarray(bonds.i)[old]]], [renumber[np.asarray(bonds.j)[old]]]
    n_attached = []
    for first, plate in ((n_rock, bottom), (n_rock + len(bottom), top)):
        idx = first + np.arange(len(plate))
        if bond_plate_discs:
            lattice = create_bonds(make_particles(plate, np.full(len(plate), radius)), 2,
                                   gap_tolerance=1e-6 * radius)
            lv = np.asarray(lattice.valid, bool)
            pi.append(idx[np.asarray(lattice.i)[lv]])
            pj.append(idx[np.asarray(lattice.j)[lv]])
        inner = idx[:n_inner]
        # rock-plate pairs among the rock and the inner row (rock rows come first)
        a, b, _ = near_pairs(np.concatenate([pos, all_pos[inner]]),
                             np.concatenate([rad, all_rad[inner]]), attach_gap)
        cross = (a < n_rock) & (b >= n_rock)
        pi.append(a[cross])
        pj.append(inner[b[cross] - n_rock])
        n_attached.append(int(np.sum(cross)))
    bi, bj = np.concatenate(pi), np.concatenate(pj)
    lo, hi = np.minimum(bi, bj), np.maximum(bi, bj)
    new_bonds = bonds_for_pairs(lo, hi, 2, dtype=particles.pos.dtype)
    thickness = radius * (2.0 + np.sqrt(3.0) * (int(rows) - 1))   # face to outer edge
    out_info = dict(info, n_rock=n_rock, plate_rows=int(rows), plate_radius=radius,
                    plate_thickness=float(thickness),
                    plate_material=int(material), n_plate_discs=int(len(bottom) + len(top)),
                    plate_discs_bonded=bool(bond_plate_discs),
                    n_plate_rock_bonds=tuple(n_attached), attach_gap=attach_gap)
    return specimen._replace(particles=new, bonds=new_bonds, info=out_info)
