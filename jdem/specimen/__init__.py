"""Rock specimen generation: random packings of discs / spheres, compacted with
the jdem engine and bonded (002 §1.4, §2).
Citations ("002 §1.4") refer to the documents listed in REFERENCES.md.

Method
------
1. **Radii.**  Radii are drawn uniformly in ``[r_min, r_max]`` (NumPy generator
   seeded with ``seed``) until their total area (2D: discs of unit thickness,
   pi r^2) or volume (3D: 4/3 pi r^3) is closest to ``(1 - target_porosity)``
   times the container's.  These are the final radii: they are never rescaled,
   so every radius lies in ``[r_min, r_max]`` (up to the float rounding of the
   stored arrays).
2. **Loose placement.**  Random sequential addition places the particles,
   shrunk by a common factor ``s0 < 1``, without overlap inside the container
   (packing fraction 0.45 in 2D, 0.28 in 3D; a cell grid keeps it O(N)).
3. **Compaction by radius expansion** with the jdem engine
   (:func:`jdem.simulate.run`, stages of ``stage_steps`` steps).  The container
   is rigid (:func:`jdem.state.make_walls`: 4 or 6 planes; a ``"disc"`` is the
   regular 64-gon inscribed in the circle).  Contacts are linear and
   frictionless, so the packing can rearrange into a dense state; local damping
   0.4 (000 eq 3-19; it relaxed these packings faster than 0.7) plus a little
   mass-proportional damping; one inertial mass for all particles (000 §3.3.2
   density scaling: quasi-static, only the geometry matters); time step 0.6 x
   :func:`jdem.timestep.nominal_critical_timestep`.  All radii grow by a common
   factor ``s -> s (1 + g)``: ``g`` = 3 % per stage while the packing is loose,
   1 % (falling to 0.25 % as the number of touching contacts per particle
   nears 4 in 2D / 6 in 3D) beyond a packing fraction of 0.74 (2D) / 0.52 (3D).
   Growth waits while the largest overlap exceeds ``overlap_limit``, so the
   packing relaxes between stages; at full size (``s = 1``) it relaxes until
   the largest overlap (particle pairs and walls) is below 0.9 x
   ``overlap_limit`` (the "unloading": frictionless contacts at a porosity above
   jamming push apart until they barely touch).
4. **Porosity.**  With ``target_porosity`` the particle number fixes the
   porosity (step 1).  When the packing jams on the way (overlaps stop
   relaxing), it shrinks 2 %, relaxes and regrows at 0.25 % per stage, up to 3
   times; a target below the jamming porosity still jams and raises
   :class:`jdem.validate.InputError` naming ``target_porosity`` and the densest
   porosity reached.  Without a target (``None``) the generator makes the
   densest packing it can: it starts denser than random close packing, and each
   time the packing jams it removes randomly chosen particles (the volume the
   others still have to gain, plus 0.5 %) and grows on.
5. **Floaters and bonds.**  Particles with no neighbour within the gap
   tolerance are "floaters" (rattlers).  ``floaters="attach"`` (default) moves
   each along the line to its nearest connected neighbour until the two touch
   (this creates no overlap: every other gap shrinks by at most the distance
   moved, which was the smallest gap; walls are checked), so the porosity is
   kept; ``"remove"`` drops them (the porosity rises by their share);
   ``"keep"`` leaves them.  Every pair whose gap ``|x_i - x_j| - R_i - R_j`` is
   at most ``gap_tolerance`` (default 0.05 x the mean radius) is bonded with
   :func:`jdem.bond.create_bonds`.  With ``target_coordination`` the gap
   tolerance in ``[0, max_gap_tolerance]`` (default 0.5 x the mean radius) that
   brings N-bar closest to the target is used; 002 §1.4 varies N-bar through
   the packing (density, size distribution, arrangement, embedding), and
   :func:`specimen_for_coordination` also varies the packing density when the
   gap tolerance alone cannot reach the target.

Units and conventions
---------------------
SI units (m, kg/m^3).  2D discs have unit thickness.  The container's lower
corner is the origin: ``"rectangle"`` ``size=(w, h)`` is ``[0, w] x [0, h]``;
``"box"`` ``size=(w, d, h)`` is ``[0, w] x [0, d] x [0, h]`` (height along z);
``"disc"`` ``size=D`` (the diameter) is the disc of radius ``D/2`` centred at
``(D/2, D/2)``, for Brazilian tests.  The returned particles have their true
masses (``density``), zero velocities and material 0.

What is reported
----------------
``Specimen.porosity``      1 - (sum of particle areas / volumes) / container area / volume
                           (rectangle w h, box w d h, disc pi D^2 / 4)
``Specimen.coordination``  N-bar = 2 n_pairs / n_particles, n_pairs the pairs within
                           the gap tolerance (= the bonds when ``bond=True``)
``Specimen.box``           (lo, hi) of the container the packing was compacted in
``Specimen.info``          n_particles, r_min, r_max, r_mean (of the final radii),
                           max_overlap [m] and max_overlap_ratio (/ mean radius; particle
                           pairs and walls), gap_tolerance [m], n_bonds, n_pairs,
                           n_floaters (found) / _attached / _removed, n_drawn (radii
                           drawn), n_removed_jammed, n_backoffs, contact_z (touching
                           contacts per particle at the end of the compaction), steps,
                           stages, n_builds (neighbour-list builds), dt [s], scale0,
                           compaction_time and wall_time [s], shape, size,
                           target_porosity, target_coordination; for a disc also
                           centre and radius; from specimen_for_coordination also
                           attempts

Modules
-------
* :mod:`jdem.specimen.container` the container, input checks, radius draws and
  the loose random placement (steps 1–2);
* :mod:`jdem.specimen.compaction` radius growth and relaxation with the engine (step 3);
* :mod:`jdem.specimen.bonding` the gap rule, the coordination target, floaters (step 4);
* :mod:`jdem.specimen.build` the public builders :func:`generate` and
  :func:`specimen_for_coordination`;
* :mod:`jdem.specimen.edit` :func:`as_arrays`, :func:`subset`, :func:`remove`,
  :func:`excavate` (a running state, fixed capacity), :func:`flatten_disc`;
* :mod:`jdem.specimen.lattice` square, triangular (hexagonal close-packed),
  simple cubic and fcc lattices, bonded (:func:`bonded_lattice`), and the
  triangular lattice's elastic constants;
* :mod:`jdem.specimen.loads` the particles on a face, pressure and traction
  loads (:func:`pressure_load`, :func:`surface_load`);
* :mod:`jdem.specimen.plates` elastic loading plates of bonded discs on a 2D
  specimen's top and bottom faces (:func:`add_plates`, 002 Fig 7).
"""
from jdem.specimen.container import (  # noqa: F401
    DISC_SIDES,
    FLOATERS,
    MIN_POROSITY,
    SHAPES,
    Specimen,
)
from jdem.specimen.build import generate, specimen_for_coordination  # noqa: F401
from jdem.specimen.edit import as_arrays, embed, excavate, flatten_disc, remove, subset  # noqa: F401
from jdem.specimen.lattice import bonded_lattice, lattice_packing, lattice_sites  # noqa: F401
from jdem.specimen.loads import face_particles, pressure_load, surface_load  # noqa: F401
from jdem.specimen.plates import add_plates  # noqa: F401
