"""The README's first command: ``jdem demo`` writes plots and an HDF5 file that reopens."""
import numpy as np

from jdem import cli, io


def test_demo_writes_plots_and_hdf5(tmp_path):
    path = cli.demo(tmp_path, small=True)
    assert (tmp_path / "tension.png").stat().st_size > 10_000
    assert (tmp_path / "shear.png").stat().st_size > 10_000
    hist = io.load_history(path)
    assert abs(np.max(hist["tension_stress"]) / 3e6 - 1) < 5e-3
    assert abs(np.max(hist["shear_stress"]) / (3e6 + 3e6 * np.tan(np.pi / 6)) - 1) < 5e-3
    # ... and ends with the calibration demo (15 Adam steps in the small run)
    assert (tmp_path / "calibration.png").stat().st_size > 10_000
    from jdem import calibrate

    back = calibrate.load_calibration(tmp_path / "calibration.h5")
    assert set(back["values"]) == {"E", "strength"}
    assert back["loss"] < 0.5 * back["history"]["loss"][0]
