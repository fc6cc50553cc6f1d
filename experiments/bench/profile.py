"""The parts of a step timed on their own, through jdem's public functions,
and a cost model that adds them up to the measured step."""
from __future__ import annotations

import jax
import jax.numpy as jnp

from jdem import bond as bond_mod, contact, integrate, neighbors
from jdem import walls as walls_mod
from jdem.kinematics import segment_add
from bench.timing import block, time_fn

def profile_case(state, params, config, repeats, log=print, detail=True, loop_steps=100,
                 quick=False):
    """Time the parts of a step on the final state of the timed run.

    Main figures ("loop.*") are per call inside a jitted ``lax.fori_loop`` whose
    carry feeds each call's output (or a 1e-30 nudge of the positions that
    depends on it) back into the next call, so XLA cannot hoist the work out of
    the loop and buffers are reused as in the real step loop.  The plain names
    are one jitted call from Python each (new output buffers every call); on
    this CPU that adds a large fixed cost, so they overstate the in-loop cost.
    """
    n = state.particles.pos.shape[0]
    dtype = state.particles.pos.dtype
    build_fn = lambda c, p, b: neighbors.build(c, p, config, b)  # noqa: E731
    fresh = block(jax.jit(build_fn)(state.contacts, state.particles, state.bonds))
    st = state._replace(contacts=fresh)  # just rebuilt: the common no-rebuild path
    stale = st._replace(contacts=fresh._replace(pos_at_build=jnp.full_like(fresh.pos_at_build, jnp.inf)))
    p, c, w = st.particles, st.contacts, st.walls
    r_cheap, r_build = repeats, max(3, repeats // 3)
    never = config.replace(skin=1e3)  # needs_rebuild is always false: cond never rebuilds
    tiny = 1e-30
    out = {}

    def rec(name, fn, *a, r=r_cheap, desc="", per=1):
        try:
            res, val = time_fn(fn, *a, repeats=r)
            res["best_ms"] /= per
            res["median_ms"] /= per
        except Exception as exc:  # the API may be changing under us; keep the rest
            log(f"  profile {name}: failed ({type(exc).__name__}: {exc})")
            out[name] = dict(error=f"{type(exc).__name__}: {exc}")
            return None
        res["what"] = desc
        res["per_call_in_loop"] = per > 1
        out[name] = res
        log(f"  profile {name:38s} best {res['best_ms']:9.3f} ms   median {res['median_ms']:9.3f} ms")
        return val

    def rec_loop(name, body, init, consts, iters, r, desc):
        """body(carry, consts) -> carry, run ``iters`` times in one jitted fori_loop."""
        fn = lambda init, consts: jax.lax.fori_loop(  # noqa: E731
            0, iters, lambda _, x: body(x, consts), init)
        return rec(name, fn, init, consts, r=r, per=iters, desc=desc + f" (per call, fori_loop of {iters})")

    def nudge(pp, by):
        return pp._replace(pos=pp.pos + by.astype(dtype) * tiny)

    # positions are nudged by the previous output so that the geometry cannot be hoisted
    def loop_contact(x, pr):
        cc, pp, f, t = x
        pp = nudge(pp, f[0, 0])
        cc, fo, to, _ = contact.contact_forces(cc, pp, pr, config)
        return cc, pp, f + fo, t + to

    def loop_bonds(x, pr):
        bb, pp, f, t = x
        pp = nudge(pp, f[0, 0])
        bb, fo, to = bond_mod.bond_forces(bb, pp, pr, config.dim, jnp.zeros((), jnp.int32),
                                          config.bond_section)
        return bb, pp, f + fo, t + to

    def loop_walls(x, pr):
        ww, pp, f, t = x
        pp = nudge(pp, f[0, 0])
        ww, fo, to, _ = walls_mod.wall_forces(ww, pp, pr, config)
        return ww, pp, f + fo, t + to

    def loop_needs(x, k):
        pp, acc = x
        need = neighbors.needs_rebuild(k, pp, config).astype(jnp.int32)
        return nudge(pp, need), acc + need

    def loop_build(x, k):
        cc, pp = x
        pp = nudge(pp, cc.n_builds)
        return build_fn(cc, pp, k), pp

    def forced(s):
        return s._replace(contacts=s.contacts._replace(
            pos_at_build=jnp.full_like(s.contacts.pos_at_build, jnp.inf)))

    zf, zt = jnp.zeros_like(p.pos), jnp.zeros_like(p.angvel)
    li, lb = 20, 5  # iterations per timed loop: cheap parts, rebuilds
    rec("dispatch_overhead", lambda x: x + 1, jnp.zeros(()), desc="trivial jitted call")
    rec_loop("loop.contact_forces", loop_contact, (c, p, zf, zt), params, li, r_cheap,
             "(1) jdem.contact.contact_forces over the whole capacity")
    if int(st.bonds.i.shape[0]):
        rec_loop("loop.bond_forces", loop_bonds, (st.bonds, p, zf, zt), params, li, r_cheap,
                 "(0) jdem.bond.bond_forces (002 eq 3-13) over every bond row")
    rec_loop("loop.wall_forces", loop_walls, (w, p, zf, zt), params, li, r_cheap,
             "(2) jdem.walls.wall_forces, W x N dense")
    rec_loop("loop.needs_rebuild", loop_needs, (p, jnp.zeros((), jnp.int32)), c, li, r_cheap,
             "(3) jdem.neighbors.needs_rebuild")
    rec_loop("loop.build", loop_build, (c, p), st.bonds, lb, r_build, "(4) jdem.neighbors.build")
    rec_loop("loop.step", lambda x, pr: integrate.step(x, pr, never), st, params, li, r_build,
             "(5) jdem.integrate.step, cond never takes the rebuild branch")
    if not quick:
        rec_loop("loop.step_with_rebuild", lambda x, pr: integrate.step(forced(x), pr, config), st,
                 params, lb, r_build, "(5b) integrate.step, cond takes the rebuild branch every step")
        rec_loop("loop.physics_step", lambda x, pr: integrate.physics_step(x, pr, config), st, params,
                 li, r_build, "integrate.physics_step (no neighbour test, no cond)")
        # the same functions called once from Python (fresh output buffers each call)
        rec("contact_forces", lambda c, p, pr: contact.contact_forces(c, p, pr, config), c, p, params,
            desc="(1) standalone call")
        rec("wall_forces", lambda w, p, pr: walls_mod.wall_forces(w, p, pr, config), w, p, params,
            desc="(2) standalone call")
        rec("needs_rebuild", lambda c, p: neighbors.needs_rebuild(c, p, config), c, p,
            desc="(3) standalone call")
        rec("build", build_fn, c, p, st.bonds, r=r_build, desc="(4) standalone call")
        rec("step", lambda s, pr: integrate.step(s, pr, config), st, params,
            desc="(5) standalone call, list fresh (cond skips the rebuild)")
        rec("step_with_rebuild", lambda s, pr: integrate.step(s, pr, config), stale, params,
            r=r_build, desc="(5b) standalone call, cond takes the rebuild branch")
    if quick or not detail:
        return out

    # --- inside contact_forces: the gathers and the scatter-adds on their own
    i, j = c.i, c.j
    rec("contact.gathers", lambda p: (p.pos[i], p.pos[j], p.vel[i], p.vel[j], p.angvel[i],
                                      p.angvel[j], p.radius[i], p.radius[j], p.mass[i], p.mass[j],
                                      p.material[i], p.material[j]), p,
        desc="the 12 per-pair gathers of contact_forces (standalone call)")
    fi = jnp.ones((i.shape[0],) + p.pos.shape[1:], p.pos.dtype)
    ti = jnp.ones((i.shape[0],) + p.angvel.shape[1:], p.pos.dtype)
    touching = contact.pair_geometry(c, p).touching  # contact_forces sums touching rows only
    add = lambda rows, index: segment_add(rows, index, n, where=touching)
    rec("contact.scatter_adds", lambda f, t, v: (add(f, i) - add(f, j), add(t, i) + add(t, j),
                                                 add(v, i) + add(v, j)),
        fi, ti, touching.astype(jnp.int32), desc="the 6 segment_add scatters of contact_forces (standalone call)")

    # --- inside build (private helpers; skipped if they change), each in a fori_loop
    def rec_part(name, fn, k, desc, iters=lb):
        """fn(particles, k) -> pytree; the loop nudges the positions by one element of
        the previous output so that nothing can be hoisted."""
        shapes = jax.eval_shape(fn, p, k)
        init = (p, jax.tree_util.tree_map(lambda sd: jnp.zeros(sd.shape, sd.dtype), shapes))

        def body(x, k):
            pp, prev = x
            pp = nudge(pp, jax.tree_util.tree_leaves(prev)[-1].reshape(-1)[0])
            return pp, fn(pp, k)

        return rec_loop(name, body, init, k, iters, r_build, desc)

    try:
        grid = neighbors.search_grid(config, p.pos.dtype)
        cand, _ = jax.jit(lambda p: neighbors.candidates(p, config, grid))(p)

        def cand_mask(pp, cand):
            return neighbors.candidate_mask(pp, cand, config, grid)

        mask = block(jax.jit(cand_mask)(p, cand))
        out["build_candidates_shape"] = list(cand.shape)
        out["build_candidates_filled"] = float(jnp.mean(cand < n))
        out["build_candidates_kept"] = int(jnp.sum(mask))
        rec_part("loop.build.cell_table", lambda pp, k: neighbors.cell_table(pp, config, grid), 0,
                 "sort particles into cells (one int32 key), fill the (cells, K) table")
        rec_part("loop.build.candidates", lambda pp, k: neighbors.candidates(pp, config, grid), 0,
                 "cell table + (N, 3^d K) candidate gather (includes cell_table)")
        rec_part("loop.build.mask", lambda pp, k: cand_mask(pp, k), cand,
                 "distance test of every candidate (gather of candidate positions and radii)")

        def history(x, cc):
            acc, prev = x
            cc = cc._replace(shear=cc.shear + acc)  # depends on the carry: not hoistable
            shear = neighbors.carry_history(cc, cc.i, cc.j, cc.valid, n)
            return shear[0, 0], shear

        rec_loop("loop.build.history_search", history, (jnp.zeros((), dtype), c.shear), c, lb,
                 r_build, "each new pair scans the old rows of its particle i for the tangential history")
        parts = [out.get(k, {}).get("best_ms") for k in
                 ("loop.build", "loop.build.candidates", "loop.build.mask", "loop.build.history_search")]
        if None not in parts:
            rest = max(0.0, parts[0] - parts[1] - parts[2] - parts[3])
            out["loop.build.compact_and_order"] = dict(
                best_ms=rest, median_ms=rest, repeats=0, compile_s=0.0, per_call_in_loop=True,
                what="derived: build - candidates - mask - history_search (compaction of the "
                     "candidate mask into the pair list through bit sets and binary searches, "
                     "sort of the kept pairs, bookkeeping)")
            log(f"  profile {'loop.build.compact_and_order (derived)':38s} best {rest:9.3f} ms")
    except Exception as exc:
        log(f"  build breakdown skipped ({type(exc).__name__}: {exc})")
        out["build_breakdown_error"] = f"{type(exc).__name__}: {exc}"
    return out


def cost_model(res):
    """Split the measured per-step time of the timed window into its parts.

    Uses the in-loop figures: ms/step = contact + walls + rebuild test + rest of
    the no-rebuild step + (one rebuild) x (rebuilds per step).
    """
    prof = res["profile"]
    best = lambda k: prof.get(k, {}).get("best_ms")  # noqa: E731
    steps = res["steps_timed"]
    per_step = res["throughput"]["aggregate"]["ms_per_step"]
    rb_per_step = res["rebuilds_timed"] / steps
    keys = ("loop.contact_forces", "loop.wall_forces", "loop.needs_rebuild", "loop.build", "loop.step")
    if None in [best(k) for k in keys]:
        return dict(measured_ms_per_step=per_step, rebuilds_per_step=rb_per_step)
    cf, wf, nr, bd, st = (best(k) for k in keys)
    bf = best("loop.bond_forces") or 0.0
    parts = {
        "bond_forces": bf,
        "contact_forces": cf,
        "wall_forces": wf,
        "needs_rebuild": nr,
        "rest of the no-rebuild step (integration, cond, copies)": max(0.0, st - bf - cf - wf - nr),
        "build (amortised)": bd * rb_per_step,
    }
    predicted = sum(parts.values())
    out = dict(measured_ms_per_step=per_step, rebuilds_per_step=rb_per_step,
               parts_ms_per_step=parts, predicted_ms_per_step=predicted,
               shares={k: v / predicted for k, v in parts.items()},
               no_rebuild_step_ms=st, build_ms=bd)
    if res["rebuilds_timed"]:
        out["implied_build_ms_from_window"] = (per_step - st) / rb_per_step
    # what this loop would give at other rebuild intervals: ms/step = step + build / interval
    res["throughput_vs_rebuild_interval"] = {
        str(iv): res["n"] / ((st + (bd / iv if iv else 0.0)) * 1e-3) for iv in (5, 10, 20, 50, 100, 0)}
    return out
