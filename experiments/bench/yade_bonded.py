"""The bonded benchmark's specimen and load in YADE, for the side-by-side ratio.

    yade -j 2 -n -x experiments/bench/yade_bonded.py INPUT.npz OUT.json [CHUNK_STEPS CHUNKS]

``INPUT.npz`` is written by ``benchmark.py --bonded`` (spheres, the bonded
pairs, the material, the time step and the platen speed).  YADE's cohesive
frictional model with moments (CohFrictMat, CohFrictPhys, Law2_ScGeom6D_
CohFrictPhys_CohesionMoment), bonds made on a first step for every pair
within 1.05 (r1 + r2) (aabbEnlargeFactor = interactionDetectionFactor = 1.05,
setCohesionNow) and made stress-free at their initial gap (below), then the
factors reset to 1; two frictionless wall platens,
the top one driven down at the benchmark's platen speed; NewtonIntegrator's
(local, non-viscous) damping 0.2; the same time step as jdem.  The timed
window is O.run(CHUNK_STEPS, True) repeated CHUNKS times after one warm-up
chunk.  Prints and writes steps/s; the bond count YADE made is checked against
the input's.
"""
import json
import sys
import time

import numpy as np
from yade import O, utils
from yade.wrapper import (CohFrictMat, FrictMat, ForceResetter, InsertionSortCollider, Bo1_Sphere_Aabb,
                          Bo1_Wall_Aabb, InteractionLoop, Ig2_Sphere_Sphere_ScGeom6D,
                          Ig2_Wall_Sphere_ScGeom, Ip2_CohFrictMat_CohFrictMat_CohFrictPhys,
                          Ip2_FrictMat_FrictMat_FrictPhys, Law2_ScGeom6D_CohFrictPhys_CohesionMoment,
                          Law2_ScGeom_FrictPhys_CundallStrack, NewtonIntegrator)

args = sys.argv[1:]
inp, out = args[0], args[1]
chunk = int(args[2]) if len(args) > 2 else 500
chunks = int(args[3]) if len(args) > 3 else 5
d = np.load(inp)
pos, rad = d["pos"], d["rad"]
E, nu = float(d["E"]), float(d["nu"])
# The bonds are made at their initial gap: YADE's CohFrictPhys measures the
# normal displacement from contact (u_n = penetrationDepth - unp), so a bond made
# across a gap would start in tension and break at once.  So: cohesion BIG on the
# bonding step (taken with dt ~ 0, nothing moves), then every bond's unp set to its
# initial penetration depth (stress-free) and its adhesion scaled to the strengths.
BIG = 1e20
rock = O.materials.append(CohFrictMat(
    young=E, poisson=nu, density=float(d["density"]), frictionAngle=float(d["phi"]),
    normalCohesion=BIG, shearCohesion=BIG, momentRotationLaw=True,
    isCohesive=True, label="rock"))
platen = O.materials.append(FrictMat(young=10 * E, poisson=nu, density=float(d["density"]),
                                     frictionAngle=0.0, label="platen"))
for x, r in zip(pos, rad):
    O.bodies.append(utils.sphere(tuple(float(v) for v in x), float(r), material=rock))
zlo, zhi = float((pos[:, 2] - rad).min()), float((pos[:, 2] + rad).max())
bottom = O.bodies.append(utils.wall(zlo, axis=2, sense=1, material=platen))
top = O.bodies.append(utils.wall(zhi, axis=2, sense=-1, material=platen))
f = float(d["bond_factor"])
aabb = Bo1_Sphere_Aabb(aabbEnlargeFactor=f)
ig2 = Ig2_Sphere_Sphere_ScGeom6D(interactionDetectionFactor=f)
O.engines = [
    ForceResetter(),
    InsertionSortCollider([aabb, Bo1_Wall_Aabb()]),
    InteractionLoop([ig2, Ig2_Wall_Sphere_ScGeom()],
                    [Ip2_CohFrictMat_CohFrictMat_CohFrictPhys(setCohesionNow=True,
                                                              setCohesionOnNewContacts=False),
                     Ip2_FrictMat_FrictMat_FrictPhys()],
                    [Law2_ScGeom6D_CohFrictPhys_CohesionMoment(useIncrementalForm=True,
                                                               always_use_moment_law=True),
                     Law2_ScGeom_FrictPhys_CundallStrack()]),
    NewtonIntegrator(damping=float(d["local_damping"]), gravity=(0, 0, 0)),
]
O.dt = 1e-30
O.step()                                  # the bonds: every pair within f (r1 + r2)
aabb.aabbEnlargeFactor = -1.0
ig2.interactionDetectionFactor = -1.0
n_coh = 0
for it in O.interactions:
    if it.isReal and hasattr(it.phys, "cohesionBroken") and not it.phys.cohesionBroken:
        it.phys.unp = it.geom.penetrationDepth
        it.phys.normalAdhesion *= float(d["T0"]) / BIG
        it.phys.shearAdhesion *= float(d["c0"]) / BIG
        n_coh += 1
O.dt = float(d["dt"])
O.bodies[top].state.vel = (0.0, 0.0, -float(d["platen_speed"]))
O.run(chunk, True)                        # warm-up
times = []
for _ in range(chunks):
    t0 = time.perf_counter()
    O.run(chunk, True)
    times.append(time.perf_counter() - t0)
n = len(pos)
steps = chunk / float(np.median(times))
res = dict(code="YADE", version=O.version if hasattr(O, "version") else "?", threads=O.numThreads,
           n=n, bonds_made=n_coh, bonds_input=int(d["i"].size), dt_s=O.dt, chunk_steps=chunk,
           chunks=chunks, chunk_times_s=times, steps_per_s=steps, particle_steps_per_s=n * steps,
           bond_steps_per_s=n_coh * steps,
           bonds_intact_end=sum(1 for i in O.interactions if i.isReal and hasattr(i.phys, "cohesionBroken")
                                and not i.phys.cohesionBroken))
print(json.dumps(res))
with open(out, "w") as fh:
    json.dump(res, fh, indent=1)
