"""Calibration of micro-parameters against laboratory curves and figures.

:func:`calibrate` fits named parameters (:data:`jdem.materials.PARAMETERS`:
``E`` [Pa], ``nu``, ``T0``, ``c0`` [Pa], ``phi`` [rad], ``eps_lim``,
``gamma_lim`` and the tied pairs ``strength`` (T0 = c0) and ``kappa``
(eps_lim = gamma_lim, 002 §2.1)) so that the pure lab tests
(:func:`jdem.lab.curve`, the same definition a production run uses) reproduce
one or several targets (:mod:`jdem.targets`: curves and scalar figures).

* Least squares on the residual vector of every target, in a bounded
  transformed space (value = lo (hi/lo)^sigmoid(u), linear when lo <= 0).
* Solvers: Levenberg-Marquardt (default) or Gauss-Newton from optimistix, with
  the Jacobian by forward mode (one ``jax.jacfwd`` pass per iteration; chosen
  for k <= 8 fitted parameters), reverse mode or central finite differences
  (for post-peak curves of large specimens, where the exact derivative through
  the break cascade is too large to steer by); Adam from optax as a
  first-order alternative.
* The set-ups must be quasi-static (:func:`jdem.lab.certify`), or the fit
  describes the loading rate, not the rock.
* An ensemble set-up (several packings, one vmapped run) contributes its
  members' mean residuals (the mean curve against the target); a member that
  diverges is reported and its residuals count as a 100 % misfit, so the
  solver steps back instead of stopping.
* Every iteration is written to a checkpoint; ``resume=`` continues from it.
* At the optimum: standard errors, 95 % intervals and the correlation matrix from
  the Gauss-Newton approximation plus, for an ensemble, the spread of the fit
  from packing to packing (what a specimen outside the ensemble would move it
  by), and the parameters the data do not determine.

Modules
-------
* :mod:`jdem.calibrate.fit` :func:`calibrate`, the loop over iterations;
* :mod:`jdem.calibrate.problem` terms, residuals, the residual function;
* :mod:`jdem.calibrate.transform` the bounded transform and default bounds;
* :mod:`jdem.calibrate.solvers` the optimistix / optax steps and Jacobians;
* :mod:`jdem.calibrate.result` :class:`CalibrationResult`, uncertainty, files, report;
* :mod:`jdem.calibrate.demo` the demonstration problem;
* :mod:`jdem.calibrate.model` :func:`fit_model`: the same transform, solver and
  uncertainty for any differentiable model (rigid blocks, waves, a rollout).
"""
from jdem.materials import PARAMETERS, check_names, material, rock_params, values_of  # noqa: F401
from jdem.targets import (LossWeights, Scalar, Target, check_scalar, curve_loss,  # noqa: F401
                          curve_residuals, load_target, scalar_residuals)
from jdem.calibrate.transform import DEFAULT_BOUNDS, DEFAULT_FACTOR  # noqa: F401
from jdem.calibrate.problem import Term, calibration_loss, peakless, term_residuals  # noqa: F401
from jdem.calibrate.result import (CalibrationResult, load_calibration, report,  # noqa: F401
                                   save_calibration)
from jdem.calibrate.fit import FORWARD_MODE_MAX, JACOBIANS, METHODS, calibrate  # noqa: F401
from jdem.calibrate.model import ModelFit, fit_model  # noqa: F401
from jdem.calibrate.demo import DEMO_TRUE, demo_problem  # noqa: F401
