"""ParaView export (jdem.export): the files reopen with meshio and hold the
recorded motion and bond states."""
import jax.numpy as jnp
import meshio
import numpy as np
import pytest

import jdem
from jdem import InputError, export
from jdem.specimen import lattice


def test_series_of_a_run_holds_the_recorded_motion(tmp_path):
    spec = lattice.bonded_lattice("square", (3, 2), 1e-3)
    rng = np.random.default_rng(0)
    p = spec.particles._replace(vel=jnp.asarray(rng.normal(0, 0.01, (6, 2))),
                                angvel=jnp.asarray(rng.normal(0, 1.0, 6)))
    state, config = jdem.make_state(p, bonds=spec.bonds)
    params = jdem.make_params(dim=2, dt=1e-8, bond_youngs=1e9)
    res = jdem.run(state, params, config, 400, record_every=100, progress=False,
                   observe=export.frame_observables)
    pvd = export.write_series(tmp_path, res.state, res.history, name="run")
    text = pvd.read_text()
    assert text.count("<DataSet") == 4 and 'file="run_0003.vtu"' in text
    for k in range(4):
        m = meshio.read(tmp_path / f"run_{k:04d}.vtu")
        np.testing.assert_allclose(m.points[:, :2], res.history["pos"][k])
        assert np.all(m.points[:, 2] == 0.0)                          # 2D: z = 0
        np.testing.assert_allclose(m.point_data["velocity"][:, :2], res.history["vel"][k])
        np.testing.assert_allclose(m.point_data["spin"][:, 2], res.history["angvel"][k])
        assert m.cells_dict["line"].shape == (int(np.sum(np.asarray(spec.bonds.valid))), 2)
        assert np.all(m.point_data["damage"] == 0.0)
    one = export.write_vtk(tmp_path / "end.vtu", res.state)
    np.testing.assert_allclose(meshio.read(one).points[:, :2], np.asarray(res.state.particles.pos))
    with pytest.raises(InputError, match="time"):
        export.write_series(tmp_path, res.state, {"pos": res.history["pos"]})
    with pytest.raises(InputError, match=".vtu"):
        export.write_vtk(tmp_path / "end.vtk", res.state)


def test_a_3d_state_exports_its_spheres_and_bonds(tmp_path):
    spec = lattice.bonded_lattice("fcc", (2, 2, 2), 1e-3)
    p = spec.particles._replace(angvel=jnp.ones_like(spec.particles.angvel) * jnp.arange(3.0))
    state, _ = jdem.make_state(p, bonds=spec.bonds)
    m = meshio.read(export.write_vtk(tmp_path / "fcc.vtu", state))
    np.testing.assert_allclose(m.points, np.asarray(p.pos))
    np.testing.assert_allclose(m.point_data["spin"], np.asarray(p.angvel))
    assert m.cells_dict["line"].shape[0] == spec.info["n_bonds"] > 0
