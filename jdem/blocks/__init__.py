"""Rigid polygonal blocks: the book's block method (000 ch. 2, 3) in the engine.

Citations ("000 §2.3") refer to the documents listed in REFERENCES.md.

* :mod:`jdem.blocks.geometry`  convex polygons as a pytree (:class:`Blocks`)
* :mod:`jdem.blocks.detect`    broad phase on the particles' cell list, clipped
                               corner–edge / edge–edge narrow phase
* :mod:`jdem.blocks.joint`     point joint laws: Mohr–Coulomb with tension cut-off,
                               Barton's rough-joint friction
* :mod:`jdem.blocks.cycle`     the computing cycle, critical step, rollout, host run
* :mod:`jdem.blocks.generate`  a region cut by joint sets; polygons from a text file
* :mod:`jdem.blocks.cases`     the book's verification cases (incline, stack, wave)
* :mod:`jdem.blocks.coupling`  discs and blocks in one model

States and params save and reload with :func:`jdem.io.save_run` / :func:`jdem.io.load_run`.
"""
from jdem.blocks.cycle import (BlockParams, BlockState, contact_forces, critical_timestep,
                               glue_joints, make_params, make_state, recommended_timestep,
                               rollout, run, step)
from jdem.blocks.detect import pair_geometry
from jdem.blocks.generate import JointSet, bridge_mask, cut_region, read_polygons, write_polygons
from jdem.blocks.geometry import Blocks, make_blocks, polygon_properties, rectangle, world_vertices

__all__ = ["JointSet", "bridge_mask", "cut_region", "read_polygons", "write_polygons",
           "BlockParams", "BlockState", "Blocks", "contact_forces", "critical_timestep",
           "glue_joints", "make_blocks", "make_params", "make_state", "pair_geometry",
           "polygon_properties", "recommended_timestep", "rectangle", "rollout", "run", "step",
           "world_vertices"]
