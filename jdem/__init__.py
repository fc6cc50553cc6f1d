"""jdem — a differentiable Discrete Element Method for rock mechanics, in JAX.

The simulation is a pure function of three inputs kept apart: ``State`` (evolves),
``Params`` (floats you may differentiate or vmap over) and ``Config`` (static).
See README.md for a tour.
"""
__version__ = "0.1.0"

from jdem.state import (Bonds, Config, Contacts, Params, Particles, State, Walls,  # noqa: F401
                        empty_bonds, make_params, make_particles, make_walls, no_walls)
from jdem.simulate import (RunResult, SimulationDiverged, advance, broadcast_batch,  # noqa: F401
                           make_config, make_state, rollout, run)
from jdem.validate import InputError  # noqa: F401
