#!/usr/bin/env python
"""The reduced UCS study (tests/test_ucs_reduced.py: ~2,200 discs, kappa = 0,
0.3 %, 2.4 %, local damping 0.8, 3 nm platen steps) in float32 and float64 on
one specimen, on whatever backend JAX picks; prints and writes per-member peak
stress, Young's modulus and critical strain and the float32 / float64 ratios.

    python experiments/ucs_reduced_precision.py --specimen spec.pkl --make   # generate here, save
    python experiments/ucs_reduced_precision.py --specimen spec.pkl          # load it (another machine)
    XLA_FLAGS=--xla_gpu_deterministic_ops=true python experiments/ucs_reduced_precision.py ...

A specimen made on one backend and loaded on another separates the packing
(compaction is chaotic, so each backend makes its own) from the run.
Writes ``<out>/ucs_reduced_precision_<backend>.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import pickle
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
from test_ucs_reduced import KAPPAS, RADII, SIZE, STEP  # noqa: E402

from jdem import lab  # noqa: E402
from jdem.materials import rock_params  # noqa: E402
from jdem.specimen import generate  # noqa: E402

FIGURES = ("peak_stress", "youngs_modulus", "critical_strain")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--specimen", help="pickle of the specimen (NumPy arrays)")
    ap.add_argument("--make", action="store_true", help="generate the specimen and save it there")
    ap.add_argument("--out", default="experiments/results/ucs_reduced_precision")
    args = ap.parse_args(argv)
    if args.make or not args.specimen:
        spec = generate("rectangle", SIZE, *RADII, seed=2, target_coordination=5.0)
        if args.specimen:
            pickle.dump(jax.tree_util.tree_map(np.asarray, spec), open(args.specimen, "wb"))
    else:
        spec = pickle.load(open(args.specimen, "rb"))
    out = dict(backend=jax.default_backend(), device=str(jax.devices()[0]),
               xla_flags=os.environ.get("XLA_FLAGS", ""), specimen=args.specimen,
               made_here=bool(args.make or not args.specimen), kappas=list(KAPPAS))
    for prec in ("float32", "float64"):
        t0 = time.time()
        setup = lab.UCS.setup(spec, rock_params(2, kappa=list(KAPPAS)), platen_step=STEP,
                              max_strain=2e-3, damping=lab.local(0.8), record_every=50,
                              precision=prec)
        s = lab.peak_summary(lab.run(setup, stop_stress_ratio=0.6, progress=False,
                                     warn_dynamic=False).history)
        out[prec] = {k: np.asarray(s[k], float).tolist() for k in FIGURES}
        print(out["backend"], prec, json.dumps(out[prec]), f"{time.time() - t0:.1f} s", flush=True)
    out["float32_over_float64_minus_1"] = {
        k: (np.asarray(out["float32"][k]) / np.asarray(out["float64"][k]) - 1).tolist()
        for k in FIGURES}
    for k, v in out["float32_over_float64_minus_1"].items():
        print(f"{k}: float32 / float64 - 1 = {np.round(v, 4)}")
    path = pathlib.Path(args.out)
    path.mkdir(parents=True, exist_ok=True)
    (path / f"ucs_reduced_precision_{out['backend']}.json").write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
