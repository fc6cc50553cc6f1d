"""jdem — a differentiable Discrete Element Method for rock mechanics, in JAX.

The simulation is a pure function of three inputs kept apart: ``State`` (evolves),
``Params`` (floats you may differentiate or vmap over) and ``Config`` (static).
See README.md for a tour.
"""
__version__ = "0.1.0"


def _cpu_fusion_flag():
    """Turn off XLA:CPU's YNNPACK fusions unless the user set XLA_FLAGS for them.

    jaxlib 0.10 hands small reductions (sums over the W walls, over the 3
    components) to YNNPACK calls that break XLA's loop fusion; for the 3D step
    loop that costs about a third of the time (experiments/benchmark.py, 20,000
    spheres: 0.69 M -> 1.07 M particle-steps/s with the flag).  XLA reads the
    flag when its backend starts, so it only takes effect if jdem is imported
    before the first computation.  Set ``JDEM_KEEP_XLA_FLAGS=1`` to leave
    XLA_FLAGS alone.  Only applied to the jaxlib series where the flag was
    checked to exist (an unknown flag would abort XLA).
    """
    import os
    from importlib import metadata

    flags = os.environ.get("XLA_FLAGS", "")
    if os.environ.get("JDEM_KEEP_XLA_FLAGS") or "ynn_fusion_type" in flags:
        return
    try:
        version = tuple(int(v) for v in metadata.version("jaxlib").split(".")[:2])
    except (metadata.PackageNotFoundError, ValueError):
        return
    if version == (0, 10):
        os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_experimental_ynn_fusion_type=").strip()


_cpu_fusion_flag()

from jdem.state import (Bonds, Config, Contacts, Params, Particles, State, Walls,  # noqa: F401
                        empty_bonds, make_params, make_particles, make_walls, no_walls)
from jdem.simulate import (RunResult, SimulationDiverged, advance,  # noqa: F401
                           make_config, make_state, rollout, run)
from jdem.batch import broadcast_batch, member  # noqa: F401
from jdem.validate import InputError  # noqa: F401
