#!/usr/bin/env python
"""Single linked-bar bond test of 002 §1.3 (Fig. 4-6) through the engine.

    python experiments/single_bond.py                  # 3D and 2D
    python experiments/single_bond.py --dim 3 --out results/single_bond

Two particles (R = 0.5 m, rho = 2500 kg/m^3) stacked along y and bonded with the
seed's values (E = 10 GPa, nu = 0.22, T0 = c0 = 3 MPa, phi = 30 deg,
eps_lim = 0.1 %, gamma_lim = 0.3 %):

* uniaxial tension: the upper particle is pulled up at a prescribed speed;
* direct shear: the upper particle is pressed down by 3 MPa (a free, locally
  damped normal degree of freedom, pre-loaded first) and sheared sideways at a
  prescribed speed.

Writes ``tension.png`` and ``shear.png`` (simulated vs the seed's theoretical
curve, one panel per dimension, peak and residual annotated) and
``single_bond.h5`` (every history, via ``jdem.io.save_run``; reopened at the end)
to ``--out``, and prints the peak stress, the strain at zero stress / residual
stress and their errors against the seed's values.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jdem.io  # noqa: E402
from jdem.lab import single_bond as sb  # noqa: E402

NORMAL_STRESS = 3e6


def run_case(mode, dim, progress):
    t = time.perf_counter()
    hist, state, config = sb.single_bond_test(mode, dim=dim, normal_stress=NORMAL_STRESS,
                                              progress=progress)
    wall = time.perf_counter() - t
    # the params actually run (seed values with the time step single_bond_test chose)
    params = sb.single_bond_setup(mode, dim=dim, normal_stress=NORMAL_STRESS).params
    summ = sb.single_bond_summary(hist, mode, params, NORMAL_STRESS)
    return dict(hist=hist, state=state, config=config, params=params, summary=summ, wall=wall)


def report(mode, dim, case):
    s = case["summary"]
    h = case["hist"]
    every = int(np.diff(h["step"][:2])[0]) if len(h["step"]) > 1 else 0
    print(f"\n[{dim}D {mode}]  dt = {float(case['params'].dt):.4g} s, {len(h['step'])} records "
          f"({every} steps apart), {case['wall']:.1f} s wall")
    print(f"  peak stress       {s['peak_stress'] / 1e6:9.5f} MPa   seed "
          f"{s['expected_peak_stress'] / 1e6:7.4f} MPa   error {100 * s['rel_err_peak_stress']:+.4f} %"
          f"   (at strain {100 * s['strain_at_peak']:.5f} %)")
    print(f"  break             mode {s['break_mode']} ({'tension' if s['break_mode'] == 1 else 'shear'})"
          f" at step {s['break_step']}")
    if mode == "tension":
        print(f"  strain at zero stress {100 * s['strain_at_break']:.5f} %   seed "
              f"{100 * s['expected_strain_at_break']:.4f} %   error "
              f"{100 * s['rel_err_strain_at_break']:+.4f} %")
        print(f"  stress after break    {s['residual_stress']:.3g} Pa (seed 0)")
    else:
        print(f"  residual stress   {s['residual_stress'] / 1e6:9.5f} MPa   seed "
              f"{s['expected_residual_stress'] / 1e6:7.4f} MPa   error "
              f"{100 * s['rel_err_residual_stress']:+.4f} %")
        print(f"  plastic shear strain at break {100 * s['plastic_strain_at_break']:.5f} %   seed "
              f"{100 * s['expected_plastic_strain_at_break']:.4f} %   error "
              f"{100 * s['rel_err_plastic_strain_at_break']:+.4f} %")
        sn = h["normal_stress"]
        print(f"  bond normal stress {sn.min() / 1e6:.5f} .. {sn.max() / 1e6:.5f} MPa "
              f"(applied {NORMAL_STRESS / 1e6:g} MPa vertically; the bond turns by ~gamma)")
    ana = sb.analytic_single_bond_curve(mode, h["strain"], case["params"], NORMAL_STRESS)
    err = np.max(np.abs(h["stress"] - ana)) / s["expected_peak_stress"]
    print(f"  max |simulated - theory| over the curve: {100 * err:.4f} % of the peak")


def plot(mode, cases, out):
    dims = sorted(cases)
    fig, axes = plt.subplots(1, len(dims), figsize=(6.2 * len(dims), 4.6), squeeze=False)
    for ax, dim in zip(axes[0], dims):
        c = cases[dim]
        h, s = c["hist"], c["summary"]
        x = 100 * h["strain"]
        ana = sb.analytic_single_bond_curve(mode, h["strain"], c["params"], NORMAL_STRESS)
        ax.plot(x, ana / 1e6, "k-", lw=3, alpha=0.3, label="theory (002 eq 6-9)")
        ax.plot(x, h["stress"] / 1e6, "C0-", lw=1.2, label=f"jdem {dim}D")
        ax.plot(100 * s["strain_at_peak"], s["peak_stress"] / 1e6, "ro")
        ax.annotate(f"peak {s['peak_stress'] / 1e6:.4f} MPa\n(seed {s['expected_peak_stress'] / 1e6:.3f},"
                    f" err {100 * s['rel_err_peak_stress']:+.3f} %)",
                    (100 * s["strain_at_peak"], s["peak_stress"] / 1e6), textcoords="offset points",
                    xytext=(12, -6), fontsize=8)
        if mode == "tension":
            ax.plot(100 * s["strain_at_break"], 0.0, "rs")
            ax.annotate(f"zero stress at {100 * s['strain_at_break']:.4f} %\n"
                        f"(seed {100 * s['expected_strain_at_break']:.2f} %, "
                        f"err {100 * s['rel_err_strain_at_break']:+.3f} %)",
                        (100 * s["strain_at_break"], 0.0), textcoords="offset points",
                        xytext=(-150, 30), fontsize=8)
            ax.set_xlabel("tensile strain u_n / L [%]")
            ax.set_ylabel("tensile stress -F_n / A_c [MPa]")
        else:
            after = h["broken"].astype(bool)
            xr = x[after].mean() if after.any() else x[-1]
            ax.plot(xr, s["residual_stress"] / 1e6, "rs")
            ax.annotate(f"residual {s['residual_stress'] / 1e6:.4f} MPa\n"
                        f"(seed {s['expected_residual_stress'] / 1e6:.3f}, "
                        f"err {100 * s['rel_err_residual_stress']:+.3f} %)\n"
                        f"gamma_p at break {100 * s['plastic_strain_at_break']:.4f} %",
                        (xr, s["residual_stress"] / 1e6), textcoords="offset points",
                        xytext=(-90, 25), fontsize=8)
            ax.set_xlabel("shear strain |u_s| / L [%]")
            ax.set_ylabel("shear stress |F_s| / A_c [MPa]")
        ax.set_title(f"single bond, {mode}, {dim}D")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    path = out / f"{mode}.png"
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dim", type=int, choices=(2, 3), action="append",
                    help="2 or 3 (repeatable; default both)")
    ap.add_argument("--out", default="results/single_bond", help="output folder")
    ap.add_argument("--progress", action="store_true", help="show progress bars")
    args = ap.parse_args(argv)
    dims = args.dim or [3, 2]
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    results = {mode: {} for mode in sb.MODES}
    for dim in dims:
        for mode in sb.MODES:
            results[mode][dim] = run_case(mode, dim, args.progress)
            report(mode, dim, results[mode][dim])

    figs = [plot(mode, results[mode], out) for mode in sb.MODES]

    history, attrs = {}, {"normal_stress": NORMAL_STRESS, "dims": ",".join(map(str, dims))}
    for mode in sb.MODES:
        for dim, c in results[mode].items():
            tag = f"{mode}_{dim}d"
            for k, v in c["hist"].items():
                history[f"{tag}_{k}"] = v
            for k, v in c["summary"].items():
                attrs[f"{tag}_{k}"] = v
            attrs[f"{tag}_dt"] = float(c["params"].dt)
    first = results["tension"][dims[0]]
    h5 = jdem.io.save_run(out / "single_bond.h5", history=history, params=first["params"],
                          config=first["config"], attrs=attrs)
    back = jdem.io.load_run(h5)
    assert back.history is not None and set(back.history) == set(history)
    for k, v in history.items():
        np.testing.assert_array_equal(np.asarray(back.history[k]), v, err_msg=k)
    assert back.config == first["config"]
    print(f"\nwrote {', '.join(str(f) for f in figs)}")
    print(f"wrote {h5} ({len(back.history)} history arrays, {len(back.attrs)} attrs; "
          f"reloaded and checked)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
