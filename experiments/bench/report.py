"""The benchmark's report: Markdown tables and the printed summary."""
from __future__ import annotations

from pathlib import Path

import numpy as np

def _m(x):
    return "n/a" if x is None else f"{x / 1e6:.3f} M"


def _ms(x):
    return "n/a" if x is None else f"{x:.3f}"


def summary_table(cases):
    head = ("| case | N | particle-steps/s (median / best / window) | steps/s (median) | ms/step "
            "| listed pairs (mean) | capacity | touching (mean) | coord. | pair-updates/s listed "
            "| touching-updates/s | rebuilds in window (steps/rebuild) | target |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for c in cases:
        tp = c["throughput"]
        tgt = c.get("target")
        tgt_s = "-"
        if tgt:
            ratio = tp["median"]["particle_steps_per_s"] / tgt["target"]
            tgt_s = f">= {tgt['target'] / 1e6:.1f} M ({ratio:.2f}x of target)"
        spr = c["steps_per_rebuild"]
        lines.append(
            f"| {c['dim']}D {c['packing']['lattice']} | {c['n']:,} | "
            f"{_m(tp['median']['particle_steps_per_s'])} / {_m(tp['best']['particle_steps_per_s'])} / "
            f"{_m(tp['aggregate']['particle_steps_per_s'])} | {tp['median']['steps_per_s']:.1f} | "
            f"{tp['median']['ms_per_step']:.2f} | {c['listed_pairs_mean']:,.0f} | {c['neighbour_capacity']:,} | "
            f"{c['touching_contacts_mean']:,.0f} | {c['coordination']['timed_mean']:.2f} | "
            f"{_m(tp['median']['listed_pair_updates_per_s'])} | "
            f"{_m(tp['median']['touching_contact_updates_per_s'])} | "
            f"{c['rebuilds_timed']} ({'-' if spr is None else f'{spr:.1f}'}) | {tgt_s} |")
    return "\n".join(lines)


def profile_table(c):
    prof = c.get("profile")
    if not prof:
        return "(profile skipped)"
    per_step = c["throughput"]["aggregate"]["ms_per_step"]
    lines = ["Times per call, best and median of repeats.  `loop.*`: inside a jitted `fori_loop` (as in the "
             "real step loop); plain names: one jitted call from Python (fresh output buffers every call, "
             "which costs extra here).", "",
             "| part | timed | best ms | median ms | % of measured ms/step | what |",
             "|---|---|---|---|---|---|"]
    for name, r in prof.items():
        if not isinstance(r, dict):
            continue
        if "error" in r:
            lines.append(f"| {name} | | error | | | {r['error']} |")
            continue
        how = "in loop" if r.get("per_call_in_loop") else "standalone"
        lines.append(f"| {name} | {how} | {r['best_ms']:.3f} | {r['median_ms']:.3f} | "
                     f"{100 * r['best_ms'] / per_step:.0f}% | {r['what']} |")
    cm = c.get("cost_model", {})
    tvi = c.get("throughput_vs_rebuild_interval")
    if tvi:
        lines += ["", "Particle-steps/s this loop would reach at other rebuild intervals "
                  "(ms/step = loop.step + loop.build / interval; 0 = never):", "",
                  "| steps per rebuild | " + " | ".join(tvi) + " |", "|---|" + "---|" * len(tvi),
                  "| particle-steps/s | " + " | ".join(_m(v) for v in tvi.values()) + " |"]
    if cm.get("parts_ms_per_step"):
        lines += ["", f"Cost model per step (in-loop best times; build amortised over "
                  f"{c['rebuilds_timed']} rebuilds / {c['steps_timed']} steps):", "",
                  "| part | ms/step | share |", "|---|---|---|"]
        for k, v in cm["parts_ms_per_step"].items():
            lines.append(f"| {k} | {v:.3f} | {100 * cm['shares'][k]:.0f}% |")
        lines.append(f"| **predicted** | {cm['predicted_ms_per_step']:.3f} | |")
        lines.append(f"| **measured (timed window)** | {cm['measured_ms_per_step']:.3f} | |")
        if "implied_build_ms_from_window" in cm:
            lines.append(f"\nOne rebuild as implied by the window, (measured - loop.step) / rebuilds per step: "
                         f"{cm['implied_build_ms_from_window']:.1f} ms (loop.build: {cm['build_ms']:.1f} ms).")
    if "build_candidates_shape" in prof:
        lines += ["", f"Rebuild: candidate array {prof['build_candidates_shape']} "
                  f"({100 * prof['build_candidates_filled']:.0f}% of slots hold a particle), "
                  f"{prof['build_candidates_kept']:,} pairs kept "
                  f"({100 * prof['build_candidates_kept'] / np.prod(prof['build_candidates_shape']):.1f}% "
                  f"of the candidates)."]
    return "\n".join(lines)


def sweep_table(rows):
    lines = ["| setting | XLA_FLAGS added | CPUs | case | particle-steps/s median (best) | rebuilds/steps "
             "| cores busy | contact ms | wall ms | build ms | step ms |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['label']} | `{r['xla_flags']}` | {r['cpus'] or 'all'} | failed | | | | | | | |")
            continue
        for c in r["cases"]:
            lines.append(
                f"| {r['label']} | `{r['xla_flags'] or '-'}` | {r['cpus'] or 'all'} | {c['dim']}D {c['n']:,} | "
                f"{_m(c['particle_steps_per_s_median'])} ({_m(c['particle_steps_per_s_best'])}) | "
                f"{c['rebuilds_timed']}/{c['steps_timed']} | {c['cpu_cores_busy']:.2f} | "
                f"{_ms(c['contact_forces_ms'])} | {_ms(c['wall_forces_ms'])} | {_ms(c['build_ms'])} | "
                f"{_ms(c['step_ms'])} |")
    return "\n".join(lines)


def write_markdown(path, report):
    env = report["environment"]
    lines = [
        "# jdem step-loop benchmark", "",
        f"Produced by `{env['command']}` on {env['date_utc']}"
        + (f" ({env['device_label']})" if env["device_label"] else "") + ".",
        "This file and `benchmark.json` are overwritten on every run.", "",
        "## Environment", "",
        "| | |", "|---|---|",
        f"| device label | {env['device_label'] or '-'} |",
        f"| backend / device | {env['backend']} / {env['device']} |",
        f"| CPU | {env['cpu_model']} ({', '.join(env['cpu_isa']) or 'no AVX info'}) |",
        f"| cores | {env['cpu_count']} ({env['cpus_usable']} usable by this process) |",
        f"| jax / jaxlib / jdem | {env['jax_version']} / {env['jaxlib_version']} / {env['jdem_version']} "
        f"(sha1 of jdem/*.py: {env['jdem_source_sha1']}) |",
        f"| dtype | {env['dtype']} |",
        f"| XLA_FLAGS | `{env['xla_flags'] or '-'}` |",
        f"| load average (1 min) at start / end | {env['load_average_start'][0]:.2f} / "
        f"{env['load_average_end'][0]:.2f} |",
        "",
        *([f"**Warning: the machine was shared** (1-min load average {env['load_average_start'][0]:.1f} at the "
           f"start, {env['load_average_end'][0]:.1f} at the end, on {env['cpu_count']} cores): other processes took "
           "CPU time during the measurements, so these figures are lower bounds and vary run to run.", ""]
          if max(env["load_average_start"][0], env["load_average_end"][0]) > env["cpu_count"] - 0.5 else []),
        "Throughput of the jitted `lax.fori_loop` over `jdem.integrate.step`, compile time "
        "excluded; neighbour-list rebuilds inside the step via `lax.cond`.  *median* / *best*: "
        "the median / fastest timed chunk; *window*: all timed steps over all timed time. "
        "Pair-updates/s = listed pairs x steps/s; touching-updates/s = touching contacts x steps/s.",
        "",
        "## Results", "",
        summary_table(report["cases"]), "",
    ]
    for c in report["cases"]:
        pk = c["packing"]
        lines += [
            f"## {c['dim']}D, {c['n']:,} particles", "",
            f"- packing: {pk['lattice']} lattice, spacing {pk['spacing_m'] * 1e3:.4g} mm "
            f"({pk['spacing_over_mean_diameter']} x mean diameter), jitter {pk['jitter_over_spacing']} x spacing, "
            f"radii uniform in [{pk['radius_range_m'][0] * 1e3:.1f}, {pk['radius_range_m'][1] * 1e3:.1f}] mm, "
            f"{pk['n_walls']} walls, no gravity, {pk['contact_model']} law, kn = ks = {pk['kn']:.3g} N/m, "
            f"friction {pk['friction']}, density {pk['density']:.0f}, initial velocity spread "
            f"{pk['v0_m_per_s']} m/s, seed {pk['seed']}",
            f"- dt = {pk['dt_s']:.4g} s = `{pk['dt_rule']}` (critical {pk['critical_dt_s']:.4g} s, "
            f"nominal {pk['nominal_critical_dt_s']:.4g} s)",
            f"- neighbour list: capacity {c['neighbour_capacity']:,}, listed pairs mean {c['listed_pairs_mean']:,.0f} "
            f"(min {c['listed_pairs_min']:,}, max {c['listed_pairs_max']:,}), max_per_cell "
            f"{c['config']['max_per_cell']}, grid {c['config']['grid_shape']}, cell {c['config']['cell_size_m'] * 1e3:.4g} mm, "
            f"skin {c['config']['skin_m'] * 1e3:.4g} mm, re-allocations {c['regrows']}",
            f"- coordination number (jdem.measure.coordination_number): initial {c['coordination']['initial']:.2f}, "
            f"timed window mean {c['coordination']['timed_mean']:.2f} "
            f"(min {c['coordination']['timed_min']:.2f}, max {c['coordination']['timed_max']:.2f})",
            f"- rebuilds (`state.contacts.n_builds`): {c['n_builds_before']} before, {c['n_builds_after']} after the "
            f"timed window = {c['rebuilds_timed']} in {c['steps_timed']} steps; per chunk {c['chunk_rebuilds']}",
            f"- compile {c['compile_s']:.1f} s, warm-up chunk {c['warmup_s']:.2f} s, chunk of {c['chunk_steps']} steps: "
            f"{', '.join(f'{t:.3f}' for t in c['chunk_times_s'])} s; CPU cores busy on average "
            f"{c['cpu_cores_busy']:.2f}; load average {c['load_average_1min'][0]:.2f} -> {c['load_average_1min'][1]:.2f}",
            f"- final state finite: {c['final_finite']}; list overflowed: {c['overflowed']}",
            "",
            "### Where the step time goes", "",
            profile_table(c), "",
        ]
    if report.get("sweep"):
        lines += ["## XLA flag / core-count sweep (child processes, fewer chunks)", "",
                  sweep_table(report["sweep"]), "",
                  "`intra_op_parallelism_threads` is not an XLA flag (XLA rejects `--intra_op_parallelism_threads`; "
                  "a bare token is ignored); the CPU thread pool follows the process's CPU affinity, "
                  "which `--cpus` sets.", ""]
    Path(path).write_text("\n".join(lines))


def print_summary(report):
    print()
    print("=" * 100)
    env = report["environment"]
    print(f"jdem benchmark  {env['date_utc']}  jax {env['jax_version']}  {env['dtype']}  "
          f"{env['backend']}:{env['device']}  CPU '{env['cpu_model']}' x{env['cpu_count']}"
          + (f"  [{env['device_label']}]" if env["device_label"] else ""))
    print(f"XLA_FLAGS='{env['xla_flags']}'")
    hdr = (f"{'case':>12} {'N':>9} {'Mpst/s med':>11} {'best':>8} {'window':>8} {'steps/s':>8} "
           f"{'pairs':>9} {'cap':>9} {'touch':>9} {'Mpair/s':>8} {'Mtouch/s':>8} {'rebuilds':>9} {'target':>22}")
    print(hdr)
    for c in report["cases"]:
        tp = c["throughput"]
        tgt = c.get("target")
        ts = "-"
        if tgt:
            ts = f">={tgt['target'] / 1e6:.1f}M ({tp['median']['particle_steps_per_s'] / tgt['target']:.2f}x)"
        print(f"{str(c['dim']) + 'D ' + c['packing']['lattice']:>12} {c['n']:>9,} "
              f"{tp['median']['particle_steps_per_s'] / 1e6:>11.3f} {tp['best']['particle_steps_per_s'] / 1e6:>8.3f} "
              f"{tp['aggregate']['particle_steps_per_s'] / 1e6:>8.3f} {tp['median']['steps_per_s']:>8.1f} "
              f"{c['listed_pairs_mean']:>9,.0f} {c['neighbour_capacity']:>9,} {c['touching_contacts_mean']:>9,.0f} "
              f"{tp['median']['listed_pair_updates_per_s'] / 1e6:>8.2f} "
              f"{tp['median']['touching_contact_updates_per_s'] / 1e6:>8.2f} "
              f"{c['rebuilds_timed']:>4}/{c['steps_timed']:<4} {ts:>22}")
        if tgt:
            print(f"{'':>12} reference: {tgt['reference']}")
    for c in report["cases"]:
        prof = c.get("profile")
        if not prof:
            continue
        print(f"\n{c['dim']}D N={c['n']:,}: profile (best of repeats, ms); measured "
              f"{c['throughput']['aggregate']['ms_per_step']:.3f} ms/step over the window")
        for name, r in prof.items():
            if isinstance(r, dict) and "best_ms" in r:
                print(f"  {name:26s} {r['best_ms']:10.3f}  (median {r['median_ms']:.3f})")
        cm = c.get("cost_model", {})
        if c.get("throughput_vs_rebuild_interval"):
            print("  M particle-steps/s at rebuild every 5/10/20/50/100/never steps: " + " / ".join(
                f"{v / 1e6:.2f}" for v in c["throughput_vs_rebuild_interval"].values()))
        if cm.get("parts_ms_per_step"):
            print("  cost model per step: " + ", ".join(
                f"{k} {v:.2f} ms ({100 * cm['shares'][k]:.0f}%)" for k, v in cm["parts_ms_per_step"].items())
                + f"; predicted {cm['predicted_ms_per_step']:.2f} vs measured {cm['measured_ms_per_step']:.2f}")
    if report.get("sweep"):
        print("\nsweep:")
        for r in report["sweep"]:
            for c in r.get("cases", []):
                print(f"  {r['label']:26s} {c['dim']}D {c['n']:>8,}  {c['particle_steps_per_s_median'] / 1e6:7.3f} M "
                      f"particle-steps/s  build {_ms(c['build_ms'])} ms  step {_ms(c['step_ms'])} ms  "
                      f"contact {_ms(c['contact_forces_ms'])} ms  walls {_ms(c['wall_forces_ms'])} ms")
    print("=" * 100)
