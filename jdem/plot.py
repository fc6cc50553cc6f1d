"""Every figure the library draws: single-bond curves, UCS curves, the
animation of a failure developing, the calibration report and sweep maps.  The CLI, the notebooks and the experiments
call these; matplotlib is imported only when a figure is drawn.

Functions that take ``path`` write a PNG there (with the Agg backend, so they
work without a display).  Units on the axes: stresses in MPa, moduli in GPa.
"""
from __future__ import annotations

import pathlib

import numpy as np

from jdem.validate import InputError


def _figure(figsize, *, pyplot=False):
    """A new figure: an Agg figure that leaves matplotlib's global backend alone
    (for PNG files), or with ``pyplot`` one that pyplot manages (shown inline in
    a notebook)."""
    if pyplot:
        import matplotlib.pyplot as plt

        return plt.figure(figsize=figsize)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


# ----------------------------------------------------------------------------- lab tests
def plot_single_bond(hist, analytic, title, xlabel, ylabel, path):
    """A single-bond test's stress against strain (``hist["strain"]``,
    ``hist["stress"]`` [Pa]) beside the analytic curve ``analytic`` [Pa] (002 eq 6–9),
    written as PNG to ``path``."""
    fig = _figure((5.5, 4))
    ax = fig.subplots()
    ax.plot(hist["strain"] * 100, hist["stress"] / 1e6, lw=2, label="jdem")
    ax.plot(hist["strain"] * 100, analytic / 1e6, "k--", lw=1, label="theory (002 eq 6–9)")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def plot_ucs(hist, kappas, path):
    """UCS curves, one per softening strain in ``kappas``: axial stress [Pa] and
    fracture degree against axial strain (``hist`` with (B, K) or (K,) arrays
    ``axial_strain``, ``axial_stress``, ``fracture_degree``), written as PNG to ``path``."""
    strain = np.atleast_2d(hist["axial_strain"])
    stress = np.atleast_2d(hist["axial_stress"])
    fd = np.atleast_2d(hist["fracture_degree"])
    fig = _figure((6, 4.2))
    ax = fig.subplots()
    ax2 = ax.twinx()
    for b, k in enumerate(kappas):
        line, = ax.plot(strain[b] * 1e6, stress[b] / 1e6, lw=1.6, label=f"κ = {k * 100:g} %")
        ax2.plot(strain[b] * 1e6, fd[b] * 100, ls=":", lw=1, color=line.get_color())
    ax.set_xlabel("axial strain [10⁻⁶]")
    ax.set_ylabel("axial stress [MPa]")
    ax2.set_ylabel("fracture degree [%] (dotted)")
    ax.set_title("uniaxial compression (002 §2)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def animate_failure(state, history, path, *, frames=40, fps=8):
    """A GIF of the failure pattern developing in a 2D lab test.

    ``state``: the final (unbatched) state; ``history``: that member's history
    with ``step``, ``axial_strain`` and ``axial_stress`` (K,) (a
    :func:`jdem.lab.run` history; pick a member of a batched one with
    :func:`jdem.batch.member` and ``{k: v[b] ...}``).  Left: the discs, and each
    bond drawn from the record at which it broke on (``break_step``), red in
    tension, blue in shear; right: the stress–strain curve with the current
    record.  ``frames`` records evenly spaced over the run, ``fps`` per second,
    written with matplotlib's Pillow writer.  Returns the path."""
    from matplotlib.animation import FuncAnimation, PillowWriter
    from matplotlib.collections import EllipseCollection, LineCollection

    p, b = state.particles, state.bonds
    pos = np.asarray(p.pos, np.float64)
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise InputError(f"animate_failure draws one 2D specimen, got positions of shape "
                         f"{pos.shape}")
    for key in ("step", "axial_strain", "axial_stress"):
        if key not in history or np.ndim(history[key]) != 1:
            raise InputError(f"history needs a 1D {key!r} entry (one member's records)")
    valid = np.asarray(p.valid, bool)
    rad = np.asarray(p.radius, np.float64)
    steps = np.asarray(history["step"])
    strain = np.asarray(history["axial_strain"]) * 1e6
    stress = np.asarray(history["axial_stress"]) / 1e6
    bi, bj = np.asarray(b.i), np.asarray(b.j)
    broke = np.asarray(b.valid, bool) & (np.asarray(b.break_step) >= 0)
    mode = np.asarray(b.break_mode)
    when = np.asarray(b.break_step)
    segs = np.stack([pos[bi], pos[bj]], axis=1)
    picks = np.unique(np.linspace(0, steps.size - 1, max(1, int(frames))).round().astype(int))

    fig = _figure((9, 4.6))
    ax, ax2 = fig.subplots(1, 2, gridspec_kw=dict(width_ratios=(1, 1.2)))
    ax.add_collection(EllipseCollection(2 * rad[valid], 2 * rad[valid], 0.0, units="xy",
                                        offsets=pos[valid], offset_transform=ax.transData,
                                        facecolors="0.85", edgecolors="0.6", linewidths=0.2))
    tension = LineCollection([], colors="tab:red", linewidths=1.2, label="tension")
    shear = LineCollection([], colors="tab:blue", linewidths=1.2, label="shear")
    ax.add_collection(tension)
    ax.add_collection(shear)
    lo, hi = (pos[valid] - rad[valid, None]).min(0), (pos[valid] + rad[valid, None]).max(0)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.legend(loc="upper right", fontsize=7, title="broken bonds", title_fontsize=7)
    ax2.plot(strain, stress, "k-", lw=1.2)
    marker, = ax2.plot([], [], "o", color="tab:orange")
    ax2.set_xlabel("axial strain [10⁻⁶]")
    ax2.set_ylabel("axial stress [MPa]")
    ax2.grid(alpha=0.3)
    ax.set_title("step 0: 0 bonds broken", fontsize=9)   # room for the title in the layout
    fig.tight_layout()

    def draw(k):
        done = broke & (when <= steps[k])
        tension.set_segments(segs[done & (mode == 1)])
        shear.set_segments(segs[done & (mode == 2)])
        marker.set_data([strain[k]], [stress[k]])
        ax.set_title(f"step {int(steps[k])}: {int(done.sum())} bonds broken", fontsize=9)
        return tension, shear, marker

    path = pathlib.Path(path)
    FuncAnimation(fig, draw, frames=picks, blit=False).save(path, writer=PillowWriter(fps=fps))
    return path


# ----------------------------------------------------------------------------- calibration
def plot_calibration(res, path=None, *, true_values=None):
    """The report of a :class:`jdem.calibrate.CalibrationResult` ``res``, four
    panels: target, start and fitted curves; the fit's residual stress;
    the loss history; the fitted values with their 95 % intervals and the
    correlation matrix.  Written as PNG when ``path`` is given; returns the figure."""
    c = res.curves
    fig = _figure((11, 8), pyplot=path is None)
    axes = fig.subplots(2, 2)
    ax, rx, bx, cx = axes.ravel()
    if "target_strain" in c:
        ax.plot(c["target_strain"] * 100, c["target_stress"] / 1e6, "k-", lw=2.5,
                label="target")
    for key, style, label in (("start_stress", "C1--", "start"), ("fit_stress", "C0-", "fitted")):
        if key not in c:
            continue
        s, e = np.atleast_2d(c[key]), np.atleast_2d(c["strain"])
        for m in range(s.shape[0]):
            ax.plot(e[m] * 100, s[m] / 1e6, style, lw=1.2, label=label if m == 0 else None)
            if key == "fit_stress" and "target_strain" in c:
                sim = np.interp(c["target_strain"], e[m], s[m])
                rx.plot(c["target_strain"] * 100, (sim - c["target_stress"]) / 1e6, "C0-",
                        lw=1)
    ax.set(xlabel="axial strain [%]", ylabel="axial stress [MPa]", title="stress-strain")
    ax.grid(alpha=0.3)
    ax.legend()
    rx.axhline(0, color="k", lw=0.8)
    rx.set(xlabel="axial strain [%]", ylabel="fitted - target [MPa]", title="residual")
    rx.grid(alpha=0.3)
    loss = res.history["loss"]
    bx.semilogy(np.arange(len(loss)), loss, "C0.-")
    bx.set(xlabel="iteration", ylabel="sum of squared residuals",
           title=f"{res.method}, {res.jacobian} Jacobian: {res.steps} iterations, "
                 f"{res.wall_time:.0f} s")
    bx.grid(alpha=0.3, which="both")
    names = list(res.values)
    for i, n in enumerate(names):
        v = res.values[n]
        lo, hi = res.intervals.get(n, (v, v))
        cx.errorbar([i], [1.0], yerr=[[1 - lo / v], [hi / v - 1]], fmt="o", color="C0",
                    capsize=4)
        if true_values and n in true_values:
            cx.plot([i], [true_values[n] / v], "kx", ms=9, label="true" if i == 0 else None)
        cx.plot([i], [res.start[n] / v], "C1s", ms=5, label="start" if i == 0 else None)
    cx.set_xticks(range(len(names)), names)
    cx.set(ylabel="value / fitted", title="fitted values, 95 % intervals")
    cx.grid(alpha=0.3)
    cx.legend(fontsize=8)
    if np.size(res.correlation) > 1:
        ins = cx.inset_axes([0.62, 0.55, 0.36, 0.42])
        ins.imshow(res.correlation, vmin=-1, vmax=1, cmap="RdBu_r")
        for i in range(len(names)):
            for j in range(len(names)):
                ins.text(j, i, f"{res.correlation[i, j]:.2f}", ha="center", va="center",
                         fontsize=7)
        ins.set_xticks(range(len(names)), names, fontsize=7)
        ins.set_yticks(range(len(names)), names, fontsize=7)
        ins.set_title("correlation", fontsize=8)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=110)
    return fig


# ----------------------------------------------------------------------------- sweeps
#: axis labels and the factor converting SI to the plotted unit
_UNITS = {
    "E": ("E [GPa]", 1e-9), "T0": ("T0 [MPa]", 1e-6), "c0": ("c0 [MPa]", 1e-6),
    "strength": ("T0 = c0 [MPa]", 1e-6), "phi": ("phi [deg]", 180.0 / np.pi),
    "eps_lim": ("eps_lim [-]", 1.0), "gamma_lim": ("gamma_lim [-]", 1.0),
    "kappa": ("kappa [-]", 1.0), "nu": ("nu [-]", 1.0),
    "peak_stress": ("peak stress [MPa]", 1e-6), "final_stress": ("final stress [MPa]", 1e-6),
    "tensile_strength": ("tensile strength [MPa]", 1e-6),
    "youngs_modulus": ("Young's modulus [GPa]", 1e-9),
    "critical_strain": ("critical strain [1e-3]", 1e3),
    "poisson_ratio": ("Poisson ratio [-]", 1.0),
    "fracture_degree_at_peak": ("fracture degree at peak [-]", 1.0),
    "fracture_degree_end": ("fracture degree at end [-]", 1.0),
}


def _label(name):
    return _UNITS.get(name, (name, 1.0))


def _column(table, name, what):
    if name not in table:
        raise InputError(f"{what} {name!r} is not a column of the table; columns: "
                         f"{sorted(k for k in table if np.ndim(table[k]) == 1)}")
    a = np.asarray(table[name], np.float64)
    if a.ndim != 1:
        raise InputError(f"{what} {name!r} has shape {a.shape}; plot_sweep needs a (n,) column")
    return a


def plot_sweep(table, x, y=None, value="peak_stress", ax=None, path=None):
    """Plot a column of a sweep table against one or two swept parameters.

    x, y     column names (usually swept parameters).  With ``y``: a heat map
             of ``value`` over the (x, y) grid when every combination of the
             distinct x and y values occurs exactly once, otherwise a scatter
             plot coloured by ``value``.  Without ``y``: ``value`` against x,
             a line with markers when x values are distinct, else a scatter.
    value    the column to show (default ``peak_stress``)
    ax       a matplotlib Axes to draw on; default a new Agg figure
    path     write the figure as PNG there

    Units: stresses in MPa, moduli in GPa, strains as given (critical strain
    in 1e-3).  Returns the Axes.
    """
    xs = _column(table, x, "x")
    vs = _column(table, value, "value")
    if ax is None:
        ax = _figure((5.5, 4.2)).add_subplot()
    fig = ax.figure
    vlabel, vscale = _label(value)
    xlabel, xscale = _label(x)
    if y is None:
        order = np.argsort(xs, kind="stable")
        if np.unique(xs).size == xs.size:
            ax.plot(xs[order] * xscale, vs[order] * vscale, "o-")
        else:
            ax.scatter(xs * xscale, vs * vscale)
        ax.set_ylabel(vlabel)
    else:
        ys = _column(table, y, "y")
        ylabel, yscale = _label(y)
        ux, uy = np.unique(xs), np.unique(ys)
        ix, iy = np.searchsorted(ux, xs), np.searchsorted(uy, ys)
        cells = np.full((uy.size, ux.size), np.nan)
        count = np.zeros((uy.size, ux.size), int)
        np.add.at(count, (iy, ix), 1)
        if np.all(count == 1):
            cells[iy, ix] = vs * vscale
            im = ax.imshow(cells, origin="lower", aspect="auto", cmap="viridis")
            ax.set_xticks(range(ux.size), [f"{v * xscale:.3g}" for v in ux])
            ax.set_yticks(range(uy.size), [f"{v * yscale:.3g}" for v in uy])
            for (j, i), c in np.ndenumerate(cells):
                ax.text(i, j, f"{c:.3g}", ha="center", va="center", fontsize=8,
                        color="w" if c < np.nanmean(cells) else "k")
        else:
            im = ax.scatter(xs * xscale, ys * yscale, c=vs * vscale, cmap="viridis")
        fig.colorbar(im, ax=ax, label=vlabel)
        ax.set_ylabel(ylabel)
    ax.set_xlabel(xlabel)
    ax.set_title(f"{table.attrs.get('test', 'sweep') if hasattr(table, 'attrs') else 'sweep'}: "
                 f"{vlabel.split(' [')[0]}")
    if path is not None:
        path = pathlib.Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=120, bbox_inches="tight")
    return ax


# ----------------------------------------------------------------------------- blocks
#: contact states drawn by :func:`plot_blocks`, with their colours
CONTACT_STATES = (("intact (glued)", "tab:purple"), ("sticking", "tab:blue"),
                  ("sliding", "tab:red"))


def contact_states(info):
    """Each contact point's state from :class:`jdem.blocks.ContactForces`:
    (C, 2) ints, -1 open (no force), 0 intact, 1 sticking, 2 sliding."""
    active, intact, sliding = (np.asarray(x) for x in (info.active, info.intact, info.sliding))
    state = np.where(sliding, 2, 1)
    state = np.where(intact, 0, state)
    return np.where(active, state, -1)


def plot_blocks(state, params, path=None, *, color="speed", title=None, ax=None):
    """Blocks (:class:`jdem.blocks.BlockState`) drawn as polygons.

    color  "speed": blocks coloured by |v| [m/s]; "contacts": blocks in grey,
           each touching contact point a dot coloured by its state (intact,
           sticking, sliding: :func:`contact_states`) with a line along the
           normal whose length is proportional to the normal force (the force
           chains of the jointed mass)
    Writes a PNG to ``path`` when given; returns the figure.
    """
    from matplotlib.collections import LineCollection, PolyCollection

    from jdem import blocks as bk

    if color not in ("speed", "contacts"):
        raise InputError(f"plot_blocks: color must be 'speed' or 'contacts', got {color!r}")
    b = state.blocks
    keep = np.asarray(b.valid)
    w = np.asarray(bk.world_vertices(b))
    vv = np.asarray(b.vert_valid)
    polys = [w[k][vv[k]] for k in np.flatnonzero(keep)]
    fig = ax.figure if ax is not None else _figure((7, 4))
    ax = ax if ax is not None else fig.subplots()
    if color == "speed":
        speed = np.linalg.norm(np.asarray(b.vel), axis=1)[keep]
        pc = PolyCollection(polys, array=speed, cmap="viridis", edgecolors="k", linewidths=0.3)
        ax.add_collection(pc)
        fig.colorbar(pc, ax=ax, label="speed [m/s]")
    else:
        ax.add_collection(PolyCollection(polys, facecolors="0.85", edgecolors="0.4",
                                         linewidths=0.3))
        _, _, _, info = bk.contact_forces(state, params)
        kind = contact_states(info)
        point = np.asarray(info.point)
        normal = np.broadcast_to(np.asarray(info.normal)[:, None, :], point.shape)
        fn = np.abs(np.asarray(info.fn))
        scale = 0.8 * float(np.median(np.asarray(b.radius)[keep])) / max(float(fn.max()), 1e-300)
        on = kind >= 0
        seg = np.stack([point[on] - 0.5 * scale * fn[on, None] * normal[on],
                        point[on] + 0.5 * scale * fn[on, None] * normal[on]], axis=1)
        ax.add_collection(LineCollection(seg, colors="tab:orange", linewidths=1.8))
        for k, (label, col) in enumerate(CONTACT_STATES):
            sel = kind == k
            ax.plot(point[sel][:, 0], point[sel][:, 1], "o", ms=2.5, color=col,
                    label=f"{label} ({int(sel.sum())})")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), title_fontsize=7,
                  title="contact points\n(bars: normal force)")
    ax.autoscale()
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if title:
        ax.set_title(title)
    if path is not None:
        fig.tight_layout()
        fig.savefig(path, dpi=120)
    return fig
