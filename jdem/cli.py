"""The ``jdem`` command line.

    jdem demo [--out results/demo] [--small]   first run: single-bond tension and direct
                                               shear (002 §1.3), plots + HDF5
    jdem bench [...]                           the throughput benchmark (experiments/benchmark.py)
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time


def _plot_single_bond(hist, analytic, title, xlabel, ylabel, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    ax.plot(hist["strain"] * 100, hist["stress"] / 1e6, lw=2, label="jdem")
    ax.plot(hist["strain"] * 100, analytic / 1e6, "k--", lw=1, label="theory (002 eq 6–9)")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def demo(out="results/demo", small=False):
    """Single-bond tension and direct shear with the seed's parameters."""
    import numpy as np

    from jdem import io, labtests

    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    print("jdem demo: two bonded spheres, R = 0.5 m, E = 10 GPa, T0 = c0 = 3 MPa (002 §1.3)")
    histories = {}
    for mode in ("tension", "shear"):
        kw = dict(strain_rate_per_step=1e-6) if small else {}
        hist, state, config = labtests.single_bond_test(mode, dim=3, progress=not small, **kw)
        params = labtests.seed_params(3)
        analytic = labtests.analytic_single_bond_curve(mode, hist["strain"], params)
        label = "tensile" if mode == "tension" else "shear"
        _plot_single_bond(hist, analytic, f"single linked bar: {mode}",
                          f"{label} strain [%]", f"{label} stress [MPa]", out / f"{mode}.png")
        histories[mode] = hist
        peak = float(np.max(hist["stress"]))
        print(f"  {mode:8s}: peak {peak / 1e6:.3f} MPa, final {hist['stress'][-1] / 1e6:.3f} MPa"
              f"  -> {out / (mode + '.png')}")
    path = io.save_run(out / "demo.h5", history={f"{m}_{k}": v for m, h in histories.items()
                                               for k, v in h.items()},
                       attrs={"what": "single-bond tension and direct shear, 002 §1.3"})
    print(f"  histories -> {path}  ({time.time() - t0:.0f} s)")
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(prog="jdem", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("demo", help="first run with built-in defaults: plots + HDF5")
    d.add_argument("--out", default="results/demo")
    d.add_argument("--small", action="store_true", help="coarser loading, for a smoke test")
    args = ap.parse_args(argv)
    if args.cmd == "demo":
        demo(args.out, args.small)
    return 0


if __name__ == "__main__":
    sys.exit(main())
