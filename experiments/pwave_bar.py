#!/usr/bin/env python
"""P-wave bar with a viscous absorbing boundary and the ratio iteration (001 §2.2,
Fig 1-8), compared with gradient-descent calibration.

    python experiments/pwave_bar.py            # radius 2.5 m (regular), 2-3 m (random)
    python experiments/pwave_bar.py --small    # radius 5 m, 4-6 m (500 discs each)
    python experiments/pwave_bar.py --out DIR

The 1000 m x 50 m bar of 001 Fig 1: y fixed on every disc, the left end driven
with the P pulse of 001 eq 12 (M = 0.5 m/s, T = 0.5 s), the right end a
viscous boundary (001 eq 4); rho = 2500 kg/m^3, c_P = 1000 m/s, no damping,
unbreakable bonds.  The seed's discs (radius 0.25 m; 0.2-0.3 m random) would
make 200,000 discs; these runs scale the discs up (the pulse is still 500 m
long, 50-100 discs per wavelength).

* Pattern A (equal discs, square arrangement), beta = 1 (001 eq 3);
* Pattern B (random packing, radius ratio 1.5, fixed rotations): beta = 1,
  then the ratio iteration (001 Fig 5) from beta0 = 0.5, 1 and 2 (Fig 6), and
  gradient descent on the reflected energy (jax.grad through the rollout).

For each run the reflected amplitude at P3 (x = 500 m) is the largest |v_x|
after the incident pulse has passed and before the wave can come back from the
left end; the coda is the same measure stopped before a reflection from the
right end can arrive (what the random packing scatters by itself).

Reflection against a reference (the measure the tests use): the bar is cut
from a 1800 m packing (jdem.waves.bar_pair; Pattern B: the cut face is
ragged) and the reflected amplitude at P3 is max |v_truncated - v_reference|
over the record 2 L / c_P + T, over the incident peak; the packing's own
scattering is the same in both and cancels.  Reported for Pattern A (beta = 1,
0.5) and for Pattern B cut from the long packing (beta = 1, 0.5 and the
ratio-iterated beta of the cut bar).

Writes pwave_velocity.png, ratio_iteration.png, reflection_reference.png and pwave_bar.h5 to
experiments/results/pwave_bar/ (or --out).
"""
from __future__ import annotations

import argparse
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jdem.io  # noqa: E402
from jdem import waves  # noqa: E402

L, H, RHO, CP = 1000.0, 50.0, 2500.0, 1000.0


def coda(h, model):
    """Largest |v_x| at P3 after the incident pulse and before a reflection from
    the right end can arrive there, over the incident peak."""
    r = waves.reflection(h, model)
    t, v = h["time"], h["vel"][:, 2, 0]
    tp = r["window"][0] - 0.6 * model.duration
    win = (t >= r["window"][0]) & (t <= tp + model.length / r["speed"] - 0.5 * model.duration)
    return float(np.max(np.abs(v[win])) / r["incident"]) if np.any(win) else float("nan")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--small", action="store_true", help="radius 5 m / 4-6 m (500 discs each)")
    ap.add_argument("--out", default=None, help="output directory")
    ap.add_argument("--grad-steps", type=int, default=8, help="gradient-descent evaluations")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out or pathlib.Path(__file__).parent / "results" / "pwave_bar")
    out.mkdir(parents=True, exist_ok=True)
    r_reg, r_min = (5.0, 4.0) if args.small else (2.5, 2.0)
    t_start = time.perf_counter()
    hist, attrs = {}, dict(r_regular=r_reg, r_min_random=r_min)

    # --- Pattern A, beta = 1
    pos, rad = waves.square_packing(int(L / (2 * r_reg)), int(H / (2 * r_reg)), r_reg)
    reg = waves.bar_model(*waves.lattice(pos, rad, waves.square_density(RHO)), length=L, height=H,
                       dt_factor=0.9)
    h_reg = waves.run_bar(reg)
    refl = waves.reflection(h_reg, reg)
    print(f"Pattern A ({len(rad)} discs), beta = 1: incident {refl['incident']:.4f} m/s, "
          f"reflected {refl['reflected']:.5f} m/s = {refl['ratio']:.2%}")
    attrs.update(regular_reflection=refl["ratio"], regular_n=len(rad))
    hist.update(regular_time=h_reg["time"], regular_vel=h_reg["vel"][:, :, 0])

    # --- Pattern B
    parts, bonds, porosity = waves.random_packing(L, H, r_min, 1.5 * r_min, seed=1, fix_rotation=True)
    n_rand = int(np.sum(np.asarray(parts.valid)))
    rnd = waves.bar_model(parts, bonds, length=L, height=H, dt_factor=0.9)
    right = rnd.conditions.boundaries[1]
    print(f"Pattern B ({n_rand} discs, porosity {porosity:.3f}): {len(right.index)} right-boundary "
          f"discs, sum of D = {float(np.sum(right.width)):.1f} m for a {H:.0f} m boundary")
    h1 = waves.run_bar(rnd)
    r1 = waves.reflection(h1, rnd)
    print(f"  beta = 1: M_out/M_in = {waves.peak(h1, 4) / 0.5:.4f}, reflected at P3 {r1['ratio']:.2%}, "
          f"coda {coda(h1, rnd):.2%}, wave speed {r1['speed']:.0f} m/s")
    cals = {}
    for beta0 in (0.5, 1.0, 2.0):
        t0 = time.perf_counter()
        cals[beta0] = waves.calibrate_ratio(rnd, beta0=beta0)
        c = cals[beta0]
        print(f"  ratio iteration from {beta0}: beta = {c.beta:.4f}, {len(c.history)} runs, "
              f"|M_out/M_in - 1| = {abs(c.history[-1]['ratio'] - 1):.1e}, "
              f"{time.perf_counter() - t0:.0f} s")
        hist[f"ratio_iteration_{beta0}"] = np.array([[r["beta"], r["m_out"]] for r in c.history])
    beta_ratio = cals[1.0].beta
    h_ratio = waves.run_bar(rnd, waves.with_betas(rnd, beta_right=beta_ratio))
    r_ratio = waves.reflection(h_ratio, rnd)
    e_ratio, _ = waves.reflected_energy(rnd, beta_ratio)
    t0 = time.perf_counter()
    grad = waves.calibrate_gradient(rnd, beta0=1.0, steps=args.grad_steps)
    t_grad = time.perf_counter() - t0
    h_grad = waves.run_bar(rnd, waves.with_betas(rnd, beta_right=grad.beta))
    r_grad = waves.reflection(h_grad, rnd)
    e_grad = min(g["loss"] for g in grad.history)
    e_one, _ = waves.reflected_energy(rnd, 1.0)
    print(f"  ratio iteration: beta = {beta_ratio:.4f}, reflected energy {e_ratio:.3e}, "
          f"P3 reflected {r_ratio['ratio']:.2%}, M_out/M_in {waves.peak(h_ratio, 4) / 0.5:.4f}")
    print(f"  gradient descent: beta = {grad.beta:.4f} after {len(grad.history)} evaluations "
          f"({t_grad:.0f} s), reflected energy {e_grad:.3e} (beta = 1: {e_one:.3e}), "
          f"P3 reflected {r_grad['ratio']:.2%}, M_out/M_in {waves.peak(h_grad, 4) / 0.5:.4f}")
    hist["gradient_iterations"] = np.array([[g["beta"], g["loss"], g["grad"]] for g in grad.history])
    hist.update(random_time=h_ratio["time"], random_vel_beta1=h1["vel"][:, :, 0],
                random_vel_ratio=h_ratio["vel"][:, :, 0], random_vel_grad=h_grad["vel"][:, :, 0])
    attrs.update(random_n=n_rand, porosity=porosity, beta_ratio=beta_ratio, beta_grad=grad.beta,
                 reflected_energy_ratio=e_ratio, reflected_energy_grad=e_grad,
                 reflected_energy_beta1=e_one, p3_reflected_beta1=r1["ratio"],
                 p3_reflected_ratio=r_ratio["ratio"], p3_reflected_grad=r_grad["ratio"],
                 p3_coda=coda(h_ratio, rnd), wave_speed=r1["speed"])

    # --- reflection against an extended reference (bar cut from an 1800 m packing)
    lx = 1.8 * L
    pos, rad = waves.square_packing(int(lx / (2 * r_reg)), int(H / (2 * r_reg)), r_reg)
    pair_a = waves.bar_pair(*waves.lattice(pos, rad, waves.square_density(RHO)), length=L, height=H,
                         dt_factor=0.9)
    ref_a = waves.run_bar(pair_a.reference)
    new_a = {}
    for beta in (1.0, 0.5):
        h = waves.run_bar(pair_a.truncated, waves.with_betas(pair_a.truncated, beta_right=beta))
        new_a[beta] = waves.reflection_against_reference(h, ref_a, t_max=pair_a.record)
        print(f"Pattern A vs reference, beta = {beta}: reflected {new_a[beta]['ratio']:.2%} "
              f"(at {new_a[beta]['time']:.2f} s)")
    parts_l, bonds_l, _ = waves.random_packing(lx, H, r_min, 1.5 * r_min, seed=1, fix_rotation=True)
    pair_b = waves.bar_pair(parts_l, bonds_l, length=L, height=H, dt_factor=0.9)
    cut = pair_b.truncated
    rb_cut = cut.conditions.boundaries[1]
    print(f"Pattern B cut from a {lx:.0f} m packing: {int(np.sum(np.asarray(cut.state.particles.valid)))}"
          f" discs, {len(rb_cut.index)} exposed right-boundary discs, sum of D = "
          f"{float(np.sum(rb_cut.width)):.1f} m")
    ref_b = waves.run_bar(pair_b.reference)
    cal_cut = waves.calibrate_ratio(cut, beta0=1.0)
    print(f"  ratio iteration on the cut bar: beta = {cal_cut.beta:.4f} in {len(cal_cut.history)} runs"
          f" (converged {cal_cut.converged})")
    new_b = {}
    for name, beta in (("beta1", 1.0), ("beta05", 0.5), ("ratio", cal_cut.beta)):
        h = waves.run_bar(cut, waves.with_betas(cut, beta_right=beta))
        new_b[name] = waves.reflection_against_reference(h, ref_b, t_max=pair_b.record)
        print(f"  Pattern B cut vs reference, beta = {beta:.4f}: reflected {new_b[name]['ratio']:.2%} "
              f"(at {new_b[name]['time']:.2f} s), M_out/M_in {waves.peak(h, 4) / 0.5:.4f}")
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for ax, (ref_h, res, title) in zip(axes, (
            (ref_a, new_a, "Pattern A at P3"), (ref_b, new_b, "Pattern B (cut) at P3"))):
        ax.plot(ref_h["time"], ref_h["vel"][:, 2, 0], "k", lw=1, label="reference (1800 m)")
        for key, r in res.items():
            ax.plot(ref_h["time"], r["difference"], lw=1,
                    label=f"truncated - reference, {key} ({r['ratio']:.1%})")
        ax.axvline(pair_a.record if ax is axes[0] else pair_b.record, color="gray", ls=":")
        ax.set_title(title, fontsize=10)
        ax.set_ylabel("v_x [m/s]")
        ax.legend(fontsize=7)
    axes[-1].set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(out / "reflection_reference.png", dpi=120)
    hist.update(reference_time=ref_b["time"], random_cut_reference_vel=ref_b["vel"][:, :, 0],
                random_cut_difference_ratio=new_b["ratio"]["difference"])
    attrs.update(ref_regular_beta1=new_a[1.0]["ratio"], ref_regular_beta05=new_a[0.5]["ratio"],
                 ref_random_beta1=new_b["beta1"]["ratio"], ref_random_beta05=new_b["beta05"]["ratio"],
                 ref_random_ratio=new_b["ratio"]["ratio"], beta_ratio_cut=cal_cut.beta,
                 cut_boundary_discs=len(rb_cut.index), cut_boundary_sum_d=float(np.sum(rb_cut.width)))

    # --- figures
    fig, axes = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    for ax, (t, v, title) in zip(axes, (
            (h_reg["time"], h_reg["vel"][:, :, 0], f"Pattern A, beta = 1 (P3 reflected {refl['ratio']:.1%})"),
            (h1["time"], h1["vel"][:, :, 0], f"Pattern B, beta = 1 (P3 after the pulse {r1['ratio']:.1%})"),
            (h_ratio["time"], h_ratio["vel"][:, :, 0],
             f"Pattern B, ratio-iterated beta = {beta_ratio:.3f} (P3 after the pulse {r_ratio['ratio']:.1%})"))):
        for j in range(5):
            ax.plot(t, v[:, j], label=f"P{j + 1}")
        ax.set_title(title, fontsize=10)
        ax.set_ylabel("v_x [m/s]")
    axes[0].legend(fontsize=8, ncol=5)
    axes[-1].set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(out / "pwave_velocity.png", dpi=120)

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for beta0, c in cals.items():
        axes[0].plot([r["iteration"] for r in c.history], [r["m_out"] for r in c.history], "o-",
                     label=f"beta0 = {beta0}")
    axes[0].axhline(0.5, color="k", lw=0.8)
    axes[0].set_xlabel("iteration")
    axes[0].set_ylabel("M_out at P5 [m/s]")
    axes[0].set_title("Ratio iteration (001 Fig 5, 6)")
    axes[0].legend()
    axes[1].plot([g["beta"] for g in grad.history], [g["loss"] for g in grad.history], "s-",
                 label="gradient descent path")
    axes[1].axvline(beta_ratio, color="r", ls="--", label=f"ratio iteration {beta_ratio:.3f}")
    axes[1].set_xlabel("beta_2P")
    axes[1].set_ylabel("reflected energy fraction")
    axes[1].set_yscale("log")
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(out / "ratio_iteration.png", dpi=120)
    attrs["wall_time_s"] = time.perf_counter() - t_start
    jdem.io.save_run(out / "pwave_bar.h5", history=hist, attrs=attrs)
    print(f"wall time {attrs['wall_time_s']:.0f} s; wrote {out}")


if __name__ == "__main__":
    main()
