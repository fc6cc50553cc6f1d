"""Round trips and error handling of jdem.io (HDF5 save / load / restart)."""
import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jdem import io
from jdem.state import (Config, Contacts, State, empty_bonds, make_params, make_particles,
                        make_walls, no_walls)
from jdem.validate import InputError


@pytest.fixture(autouse=True, scope="module")
def x64():
    """Run this module under float64, then restore the flag so other test modules
    keep whatever precision they were collected with."""
    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", old)


def build_state(walls=True, n_bonds=3):
    rng = np.random.default_rng(0)
    n, c = 4, 5
    pos = rng.uniform(0.0, 1.0, (n, 2))
    parts = make_particles(pos, rng.uniform(0.01, 0.05, n), capacity=n + 2,
                           material=[0, 1, 0, 1], fixed_vel=[[True, False]] * n)
    known = dict(
        i=jnp.array([0, 0, 1, 2, 0], jnp.int32), j=jnp.array([1, 2, 3, 3, 0], jnp.int32),
        valid=jnp.array([True, True, False, True, False]),
        shear=jnp.asarray(rng.standard_normal((c, 2))),
        pos_at_build=parts.pos + 1e-17, radius_at_build=parts.radius,
        n_pairs=jnp.int32(4), n_builds=jnp.int32(7))
    # Contacts' scalar counters are still evolving (e.g. max_in_cell); fill any
    # other field with a 0-d int32 so the test follows state.py.
    contacts = Contacts(**{f: known.get(f, jnp.int32(3)) for f in Contacts._fields})
    w = (make_walls([[0.0, 0.0], [0.0, 1.0]], [[0.0, 1.0], [0.0, -1.0]], n_particles=n + 2,
                    servo=[False, True], target_stress=[0.0, 1e6])
         if walls else no_walls(2, n + 2))
    state = State(particles=parts, contacts=contacts, walls=w, bonds=empty_bonds(2, n_bonds),
                  step=jnp.int32(12), time=jnp.float64(1.0 / 3.0), first_bad_step=jnp.int32(-1))
    params = make_params(2, n_materials=2, kn=[1e8, 2e8], gravity=[0.0, -9.81])
    config = Config(dim=2, contact_model="hertz", skin=1e-3, cell_size=0.1,
                    grid_origin=(-0.5, 0.25), grid_shape=(10, 12), max_per_cell=4)
    return state, params, config


def assert_same(a, b):
    """Same dtype, same shape, bit-identical values."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype and a.shape == b.shape
    assert a.tobytes() == b.tobytes()
    if a.dtype.kind != "f":
        assert np.array_equal(a, b)


def assert_tree_same(a, b):
    assert type(a) is type(b)
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        assert isinstance(y, jax.Array)
        assert_same(x, y)


@pytest.mark.parametrize("walls,n_bonds", [(True, 3), (False, 0)])
def test_round_trip_exact(tmp_path, walls, n_bonds):
    state, params, config = build_state(walls, n_bonds)
    assert state.time.dtype == jnp.float64 and params.kn.dtype == jnp.float64
    history = {"energy": jnp.linspace(0.0, 1.0, 11) ** 0.5,
               "batched": np.arange(24, dtype=np.float32).reshape(2, 3, 4),
               "nan_and_int": np.array([np.nan, -0.0, np.inf]),
               "count": np.array([1, 2, 3], np.int32), "flag": np.bool_(True),
               "empty": np.zeros((0, 3), np.int64)}
    attrs = {"name": "uniaxial", "seed": 42, "porosity": 0.1 + 0.2, "converged": True}
    out = io.save_run(tmp_path / "a" / "b" / "run.h5", state=state, params=params,
                      config=config, history=history, attrs=attrs)
    assert out.is_file()

    run = io.load_run(out)
    assert isinstance(run, io.RunData)
    assert_tree_same(state, run.state)
    assert_tree_same(params, run.params)
    assert run.state.particles.valid.dtype == jnp.bool_
    assert run.state.contacts.n_pairs.shape == ()
    assert run.state.walls.shear.shape == state.walls.shear.shape
    assert run.config == config
    assert type(run.config.grid_origin) is tuple and type(run.config.grid_shape[0]) is int
    assert type(run.config.grid_origin[0]) is float
    assert list(run.history) == list(history)
    for k in history:
        assert_same(history[k], run.history[k])
    assert run.attrs == attrs
    assert all(type(run.attrs[k]) is type(v) for k, v in attrs.items())

    assert_tree_same(state, io.load_state(out))
    assert list(io.load_history(out)) == list(history)


def test_partial_file_and_metadata(tmp_path):
    params = make_params(3)
    config3 = Config(dim=3, grid_origin=(0.0, 0.0, 0.0), grid_shape=(2, 3, 4))
    path = io.save_run(tmp_path / "p.h5", params=params, config=config3)
    run = io.load_run(path)
    assert run.state is None and run.history is None and run.attrs is None
    assert run.config == config3
    assert_tree_same(params, run.params)
    assert io.load_history(path) == {}
    with pytest.raises(io.CorruptFileError, match="state missing"):
        io.load_state(path)
    with h5py.File(path, "r") as f:
        assert f.attrs["format_version"] == io.FORMAT_VERSION
        assert isinstance(f.attrs["jdem_version"], str)
        assert f["config"].attrs["_class"] == "Config"
    with pytest.raises(FileExistsError):
        io.save_run(path, params=params, overwrite=False)
    with pytest.raises(InputError):
        io.save_run(tmp_path / "q.h5", attrs={"format_version": 3})


def test_only_large_arrays_compressed(tmp_path):
    big = np.random.default_rng(1).standard_normal(200_000)  # 1.6 MB
    path = io.save_run(tmp_path / "h.h5", history={"big": big, "small": big[:10]})
    with h5py.File(path, "r") as f:
        assert f["history/big"].compression == "gzip"
        assert f["history/small"].compression is None
    assert_same(big, io.load_history(path)["big"])


def test_missing_file(tmp_path):
    path = tmp_path / "nope.h5"
    with pytest.raises(FileNotFoundError, match="nope.h5"):
        io.load_run(path)


def test_random_bytes(tmp_path):
    path = tmp_path / "junk.h5"
    path.write_bytes(np.random.default_rng(2).bytes(4096))
    with pytest.raises(io.CorruptFileError, match="junk.h5"):
        io.load_run(path)
    assert issubclass(io.CorruptFileError, InputError)


def test_truncated_file(tmp_path):
    state, params, config = build_state()
    path = io.save_run(tmp_path / "t.h5", state=state, params=params, config=config)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(io.CorruptFileError, match="t.h5"):
        io.load_run(path)


def test_missing_dataset(tmp_path):
    state, _, _ = build_state()
    path = io.save_run(tmp_path / "m.h5", state=state)
    with h5py.File(path, "r+") as f:
        del f["state/particles/pos"]
    with pytest.raises(io.CorruptFileError, match="particles/pos") as err:
        io.load_run(path)
    assert "state/particles/pos missing" in str(err.value) and "m.h5" in str(err.value)


def test_flipped_byte_inside_a_dataset_is_caught_by_its_checksum(tmp_path):
    """Numeric datasets carry a Fletcher-32 checksum: one flipped byte in the
    stored positions raises CorruptFileError naming the dataset (it used to load
    as wrong numbers)."""
    state, params, config = build_state()
    path = io.save_run(tmp_path / "c.h5", state=state, params=params, config=config,
                       history={"stress": np.linspace(0.0, 1.0, 50)})
    with h5py.File(path, "r") as f:
        ds = f["state/particles/pos"]
        assert ds.fletcher32 and f["history/stress"].fletcher32
        offset = ds.id.get_chunk_info(0).byte_offset
    data = bytearray(path.read_bytes())
    data[offset + 3] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(io.CorruptFileError, match="particles/pos.*c.h5"):
        io.load_run(path)
    assert_same(np.linspace(0.0, 1.0, 50), io.load_history(path)["stress"])   # the rest reads


def test_nested_history_and_attrs_are_groups(tmp_path):
    """Dicts in ``history`` and ``attrs`` become HDF5 groups (any depth) and come
    back as dicts; plain h5py sees the groups and attributes."""
    hist = {"loss": np.arange(3.0), "curves": {"strain": np.linspace(0, 1, 4),
                                                "deep": {"x": np.ones((2, 2), np.int32)}}}
    attrs = {"what": "test", "fit": {"E": 3e10, "names": ["E"], "inner": {"k": 1}}}
    path = io.save_run(tmp_path / "n.h5", history=hist, attrs=attrs)
    rd = io.load_run(path)
    np.testing.assert_array_equal(rd.history["loss"], hist["loss"])
    np.testing.assert_array_equal(rd.history["curves"]["strain"], hist["curves"]["strain"])
    assert rd.history["curves"]["deep"]["x"].dtype == np.int32
    assert rd.attrs == {"what": "test", "fit": {"E": 3e10, "names": ["E"], "inner": {"k": 1}}}
    with h5py.File(path, "r") as f:
        assert f["attrs/fit"].attrs["E"] == 3e10
        assert f["history/curves/deep/x"].shape == (2, 2)
        assert f.attrs["format_version"] == 2
    with pytest.raises(InputError, match="names"):
        io.save_run(tmp_path / "bad.h5", history={"a": {"b/c": np.zeros(2)}})


def test_a_float64_file_is_not_rounded_silently_in_a_float32_process(tmp_path):
    state, params, config = build_state()
    path = io.save_run(tmp_path / "f64.h5", state=state, params=params, config=config)
    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.raises(io.PrecisionError, match="pos .*float64 but JAX runs in float32"):
            io.load_run(path)
        back = io.load_run(path, allow_downcast=True)        # explicit opt-in
        assert back.state.particles.pos.dtype == jnp.float32
    finally:
        jax.config.update("jax_enable_x64", True)
    assert io.load_run(path).state.particles.pos.dtype == jnp.float64


def test_a_config_without_dim_or_of_another_dimension_is_refused(tmp_path):
    state, params, config = build_state()
    path = io.save_run(tmp_path / "run.h5", state=state, params=params, config=config)
    with h5py.File(path, "a") as f:
        del f["config"].attrs["dim"]
    with pytest.raises(io.CorruptFileError, match="no 'dim'"):
        io.load_run(path)
    with h5py.File(path, "a") as f:     # a consistent 3D config beside a 2D state
        f["config"].attrs["dim"] = 3
        f["config"].attrs["grid_origin"] = "[0.0, 0.0, 0.0]"
        f["config"].attrs["grid_shape"] = "[10, 12, 1]"
    with pytest.raises(io.CorruptFileError, match="dimension 2 but config.dim = 3"):
        io.load_run(path)
