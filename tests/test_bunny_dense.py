"""The dense bunny training set: its positions keep away from the held-out ones, and `concat_data --train-later`
makes every later case a training case while the first file keeps its val and test cases."""
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from fem import cases, scenes
from tignn_jax import data as D

ROOT = Path(__file__).resolve().parents[1]


def _script(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_dense_positions_keep_their_distance_from_the_held_out_ones():
    dense, held = _script("bunny_dense_positions").dense_positions(5.5)
    scene = scenes.bunny_scene()
    surface, _ = cases.free_surface(scene)
    _, picked = cases.point_load_forces(scene, n_cases=100, seed=0)
    assert np.array_equal(held, picked[80:])
    assert np.isin(dense, surface).all() and len(np.unique(dense)) == len(dense)
    d = np.linalg.norm(scene.points[dense][:, None] - scene.points[held][None], axis=-1)
    assert d.min() >= 5.5
    # every free surface node at that distance is in it, the data set's own training positions (5.54 away) too
    d_all = np.linalg.norm(scene.points[surface][:, None] - scene.points[held][None], axis=-1).min(axis=1)
    assert len(dense) == int((d_all >= 5.5).sum()) == 705
    assert np.isin(picked[:80], dense).all()
    with pytest.raises(ValueError, match="min_distance"):
        _script("bunny_dense_positions").dense_positions(-1.0)


def test_concat_train_later(tmp_path):
    first = D.synthetic_beam(cases=5)._replace(splits={"train": np.array([1, 2, 3]), "val": np.array([4]),
                                                       "test": np.array([5])})
    later = D.synthetic_beam(cases=3)._replace(splits={"train": np.array([1]), "val": np.array([2]),
                                                       "test": np.array([3])})
    later = later._replace(z=later.z + 1.0)
    paths = [D.save(first, tmp_path / "a.npz"), D.save(later, tmp_path / "b.npz")]
    concat = _script("concat_data")
    out = concat.main([str(p) for p in paths] + ["--out", str(tmp_path / "all.npz"), "--train-later"])
    got = D.load(out)
    assert got.sim_id.tolist() == [1, 2, 3, 4, 5, 6, 7, 8]
    assert got.splits["train"].tolist() == [6, 7, 8]
    assert got.splits["val"].tolist() == [4] and got.splits["test"].tolist() == [5]
    np.testing.assert_array_equal(got.z[5:], later.z)
    # without the flag the splits are the union, the later set's ids shifted
    got = D.load(concat.main([str(p) for p in paths] + ["--out", str(tmp_path / "u.npz")]))
    assert got.splits["train"].tolist() == [1, 2, 3, 6] and got.splits["test"].tolist() == [5, 8]
    with pytest.raises(ValueError, match="--train-later"):
        concat.main([str(paths[0]), "--out", str(tmp_path / "one.npz"), "--train-later"])


def test_case_errors_per_case_and_chunk_independent():
    import tignn_jax
    from tignn_jax import evaluate as EV

    params, graph = tignn_jax.load_pretrained("bunny-linear")
    z0 = np.asarray(graph.nodes["z"], np.float32)
    n = len(z0)
    rng = np.random.default_rng(0)
    f = np.zeros((3, 3, n, 3), np.float32)
    f[:, :, rng.integers(0, n, 20)] = rng.normal(size=(3, 3, 20, 3)).astype(np.float32) * 0.1
    data = D.Dataset(q0=z0[:, :3], edges=np.stack([np.asarray(graph.senders), np.asarray(graph.receivers)]),
                     node_type=np.asarray(graph.nodes["node_type"]), z=np.repeat(z0[None, None], 3, 1).repeat(3, 0),
                     f=f, dt=0.05, sim_id=np.array([1, 2, 3], np.int32), splits={})
    truth = np.array(EV.rollout_cases(params, data, np.arange(3)))
    truth[1, 1:, :, :3] += 0.01 * np.abs(truth[1, 1:, :, :3] - z0[:, :3]).max()   # case 2 off by a shift
    data = data._replace(z=truth)
    case_errors = _script("case_errors").case_errors
    a, b = case_errors(params, data, np.arange(3), chunk=2), case_errors(params, data, np.arange(3), chunk=1)
    for k in (1, 2, 3):   # chunks change only the float32 batch arithmetic
        np.testing.assert_allclose([a[k][v] for v in EV.VARIABLES], [b[k][v] for v in EV.VARIABLES], rtol=1e-3,
                                   atol=1e-3)
    assert a[1]["u"] < 1e-3 and a[3]["u"] < 1e-3 and a[2]["u"] > 1e-2
