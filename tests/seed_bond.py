"""The single-bond values of 002 §1.3 (E 10 GPa, nu 0.22, T0 = c0 = 3 MPa,
phi 30 deg, eps_lim 0.1 %, gamma_lim 0.3 %) under the names the bond tests use;
the values themselves are defined once, in :data:`jdem.materials.SEED_PARAMS`."""
import numpy as np

from jdem.materials import SEED_PARAMS

E = SEED_PARAMS["bond_youngs"]                 # [Pa]
NU = SEED_PARAMS["bond_poisson"]
G = E / (2 * (1 + NU))                         # [Pa]
T0 = SEED_PARAMS["bond_tensile"]               # [Pa]
C0 = SEED_PARAMS["bond_cohesion"]              # [Pa]
PHI = SEED_PARAMS["bond_friction_angle"]       # [rad]
TANPHI = np.tan(PHI)
EPS_LIM = SEED_PARAMS["bond_tensile_strain"]
GAM_LIM = SEED_PARAMS["bond_shear_strain"]
