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
    # ... and ends with the calibration demo (Levenberg-Marquardt on the curve up to
    # its peak, at most 12 iterations): from E +40 % and strength -30 % back to the
    # values the target was simulated with (measured: loss 0.192 -> 1.6e-9 in 7
    # iterations, E and strength within 0.005 %)
    assert (tmp_path / "calibration.png").stat().st_size > 10_000
    from jdem import calibrate

    back = calibrate.load_calibration(tmp_path / "calibration.h5")
    assert set(back["values"]) == {"E", "strength"}
    assert abs(back["values"]["E"] / calibrate.DEMO_TRUE["E"] - 1) < 0.01
    assert abs(back["values"]["strength"] / calibrate.DEMO_TRUE["strength"] - 1) < 0.02
    assert back["steps"] <= 12
    assert back["loss"] < 1e-3 * back["history"]["loss"][0]


def test_calibrate_command_fits_a_csv_curve(tmp_path, capsys):
    """``jdem calibrate CURVE.csv --config cfg.toml --small``: E from +30 % back to
    the value the CSV curve was simulated with (within 2 %; the config asks for the
    finite-difference Jacobian, so that path runs end to end), a PNG report and an
    HDF5 result that reopens; a CSV in percent strain stops with exit code 2
    and a message naming the unit."""
    from jdem import calibrate

    setup, params, curve, true, start = calibrate.demo_problem(loading_rate=6.4e-5)
    csv = tmp_path / "lab.csv"
    csv.write_text("strain,stress_Pa\n" + "".join(f"{float(e)!r},{float(s)!r}\n" for e, s in
                                                 zip(curve["strain"], curve["stress"])))
    cfg = tmp_path / "cal.toml"
    cfg.write_text('[material]\nE = 39e9\n[fit]\nparameters = ["E"]\nsteps = 8\n'
                   'jacobian = "finite-difference"\n[fit.bounds]\nE = [10e9, 80e9]\n')
    assert cli.main(["calibrate", str(csv), "--config", str(cfg), "--small",
                     "--out", str(tmp_path / "out")]) == 0
    back = calibrate.load_calibration(tmp_path / "out" / "calibration.h5")
    assert abs(back["values"]["E"] / true["E"] - 1) < 0.02
    assert back["std_errors"]["E"] > 0 and back["jacobian"] == "finite-difference"
    assert (tmp_path / "out" / "calibration.png").stat().st_size > 10_000
    assert "E " in capsys.readouterr().out
    pct = tmp_path / "pct.csv"
    pct.write_text("".join(f"{100 * float(e)!r},{float(s)!r}\n" for e, s in
                           zip(curve["strain"], curve["stress"])))
    assert cli.main(["calibrate", str(pct), "--small", "--out", str(tmp_path / "o2")]) == 2
    assert "percent" in capsys.readouterr().err


def test_calibrate_reads_a_lateral_strain_column_when_the_csv_has_one(tmp_path):
    """Two columns: a stress curve; three: the third is the lateral strain, its
    empty cells "no reading"."""
    from jdem import calibrate

    e = np.linspace(0, 3e-3, 101)
    s = 1e10 * e * np.exp(-e / 1e-3)
    two, three = tmp_path / "two.csv", tmp_path / "three.csv"
    two.write_text("strain,stress\n" + "".join(f"{a},{b}\n" for a, b in zip(e, s)))
    three.write_text("strain,stress,lateral\n" + "".join(
        f"{a},{b},{-0.2 * a if i < 50 else ''}\n" for i, (a, b) in enumerate(zip(e, s))))
    assert calibrate.load_target(two, lateral_column="auto").lateral_strain is None
    t = calibrate.load_target(three, lateral_column="auto")
    assert np.isfinite(t.lateral_strain[:50]).all() and np.isnan(t.lateral_strain[50:]).all()


def test_warnings_reach_the_user_without_a_source_line():
    """A warning raised under ``jdem`` (e.g. a calibration that stalled) is printed
    as ``jdem <command>: UserWarning: ...``, not with the file and line of the
    code that raised it; a fresh process, because pytest records warnings."""
    import subprocess
    import sys

    code = ("import warnings, jdem.cli as c\n"
            "c.demo = lambda out, small: warnings.warn('the fit stalled')\n"
            "c.main(['demo'])\n"
            "warnings.warn('after main')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stderr.strip().splitlines()
    assert lines[0] == "jdem demo: UserWarning: the fit stalled"
    assert "cli.py" not in out.stderr
    # the default formatting is back after main returns
    assert any("after main" in line and "<string>" in line for line in lines[1:])
