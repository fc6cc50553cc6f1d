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
