"""Training the GENERIC graph network: the loss goes down, an interrupted run resumes to the same weights, the best
model is written and loads, warm starts begin from their parent, bad batches and bad recipes are refused."""
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from tignn_jax import data as D
from tignn_jax.simulators.generic_gnn import GenericGNN, GNNConfig
from tignn_jax.train import gnn as T
from tignn_jax.train import load_recipe

ROOT = Path(__file__).resolve().parents[1]
# one recipe for every run here, so the training step compiles once
TINY = load_recipe(ROOT / "configs" / "tiny_gnn.py")[0]._replace(epochs=4, batch_size=4, lr=1e-2, warmup_steps=1,
                                                                  eval_every=100, ckpt_every=100)
QUIET = dict(progress=False, log=lambda s: None)
NO_VAL = ("train", None)


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """A synthetic bar of 4x2x2 nodes, 5 cases of 4 frames (train 1-4, val 5), written to a data file."""
    data = D.synthetic_beam(nx=4, ny=2, nz=2, cases=5, frames=4)
    path = D.save(data, tmp_path_factory.mktemp("data") / "bar.npz")
    return {"data": data, "path": path}


@pytest.fixture(scope="module")
def validated(toy, tmp_path_factory):
    """A run with a validation split (validated at its last epoch): its folder and returned model."""
    run = tmp_path_factory.mktemp("validated")
    params = T.train(toy["path"], TINY, run, split=("train", "val"), **QUIET)
    return {"run": run, "params": params}


_jit_loss = jax.jit(T.loss_fn, static_argnames="cfg")


def _mean_loss(params, data):
    """The noise-free loss over all training transitions."""
    rows = D.split_rows(data, "train")
    z, f = data.z[rows], data.f[rows]
    batch = T.Batch(jnp.asarray(z[:, :-1].reshape(-1, *z.shape[2:])), jnp.asarray(f.reshape(-1, *f.shape[2:])),
                    jnp.asarray(z[:, 1:].reshape(-1, *z.shape[2:])))
    arrays = params["arrays"]
    loss, metrics = _jit_loss(arrays["weights"], batch, jax.random.PRNGKey(0), arrays, cfg=TINY._replace(noise=0.0))
    return float(loss), metrics


def _flat(params):
    return np.concatenate([np.ravel(np.asarray(x)) for x in jax.tree_util.tree_leaves(params["arrays"]["weights"])])


def _lines(run):
    return [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]


def test_tiny_training_reduces_the_loss(toy, tmp_path):
    # A few epochs on a smooth toy bar fit the one-step increments better than the initial weights.
    initial = T.train(toy["path"], TINY, tmp_path / "init", split=NO_VAL, stop_after_epoch=0, **QUIET)
    trained = T.train(toy["path"], TINY, tmp_path / "run", split=NO_VAL, **QUIET)
    before, _ = _mean_loss(initial, toy["data"])
    after, metrics = _mean_loss(trained, toy["data"])
    assert after < 0.7 * before
    np.testing.assert_allclose(float(metrics["loss"]), float(metrics["mse"] + TINY.deg_weight * metrics["degeneracy"]),
                               rtol=1e-6)
    lines = _lines(tmp_path / "run")
    assert [x["epoch"] for x in lines] == [1, 2, 3, 4]
    assert all(np.isfinite(x[k]) for x in lines for k in ("loss", "mse", "degeneracy", "mse_q", "mse_v", "mse_sigma"))
    assert all(x["skipped"] == 0 for x in lines)


def test_resumed_run_reproduces_the_uninterrupted_run(toy, tmp_path):
    # Batch order and noise depend only on (seed, epoch, step): stop after epoch 2, resume, the same weights.
    whole = T.train(toy["path"], TINY, tmp_path / "whole", split=NO_VAL, **QUIET)
    T.train(toy["path"], TINY, tmp_path / "split", split=NO_VAL, stop_after_epoch=2, **QUIET)
    assert [x["epoch"] for x in _lines(tmp_path / "split")] == [1, 2]
    resumed = T.train(toy["path"], TINY, tmp_path / "split", split=NO_VAL, **QUIET)
    np.testing.assert_array_equal(_flat(whole), _flat(resumed))
    assert [x["epoch"] for x in _lines(tmp_path / "split")] == [1, 2, 3, 4]
    assert json.loads((tmp_path / "split" / "config.json").read_text())["recipe"]["model"]["hidden"] == 8


def test_to_params_is_the_model_dict_of_the_simulators(toy, tmp_path):
    params = T.train(toy["path"], TINY, tmp_path / "run", split=NO_VAL, stop_after_epoch=0, **QUIET)
    data = toy["data"]
    assert params["model"] == GenericGNN(TINY.model)
    assert {"model", "arrays", "mesh", "envelope", "info"} <= set(params)
    assert set(params["arrays"]) == {"weights", "norm", "topo", "node_type"}
    norm = D.normalization(data, D.split_rows(data, "train"))
    for k in T.ENVELOPE:
        np.testing.assert_array_equal(params["envelope"][k], norm[k])
    np.testing.assert_array_equal(params["mesh"]["q0"], data.q0)
    assert params["info"]["train_config"] == TINY.as_dict()
    again = T.to_params(params["model"], params["model"].stored(params["arrays"]), params["mesh"],
                        params["envelope"], {})
    np.testing.assert_array_equal(_flat(again), _flat(params))
    with pytest.raises(ValueError, match="u_max"):
        T.to_params(params["model"], params["model"].stored(params["arrays"]), params["mesh"],
                    {k: v for k, v in params["envelope"].items() if k != "u_max"}, {})


def test_best_model_is_written_and_reproduces_its_validation_score(toy, validated):
    # The best model file holds the selected weights: rolled out on the val cases it scores what best.json says.
    from tignn_jax import api

    run, data = validated["run"], toy["data"]
    best = json.loads((run / "best.json").read_text())
    line = _lines(run)[-1]
    assert best["epoch"] == 4 and best["score"] == line["val_score"]
    assert line["val_score"] == pytest.approx(line["val_v"] + line["val_sigma"] + line["val_u"])
    loaded = api.load_model(run / "best" / "model.npz")
    assert loaded["model"] == GenericGNN(TINY.model) and loaded["info"]["best"]["epoch"] == 4
    rows = D.split_rows(data, "val")
    pred = T.rollouts(loaded["model"], loaded["arrays"], jnp.asarray(data.z[rows, 0]), jnp.asarray(data.f[rows]))
    errs = np.nanmean(T.relative_errors(pred, data.z[rows], data.q0), axis=(0, 1))
    np.testing.assert_allclose(errs[1] + errs[2] + errs[3], best["score"], rtol=1e-6)
    np.testing.assert_array_equal(_flat(loaded), _flat(validated["params"]))   # the last epoch was the best


def test_warm_start_begins_from_the_parent_with_its_statistics(toy, validated, tmp_path):
    parent = validated["params"]
    louder = toy["data"]._replace(f=toy["data"].f * 2.0)   # data whose force scale differs from the parent's
    child = T.train(louder, TINY._replace(init_from=str(validated["run"])), tmp_path / "child", split=NO_VAL,
                    stop_after_epoch=0, **QUIET)
    np.testing.assert_array_equal(_flat(child), _flat(parent))      # no step taken: the parent's weights
    np.testing.assert_array_equal(np.asarray(child["arrays"]["norm"]["f_std"]),
                                  np.asarray(parent["arrays"]["norm"]["f_std"]))
    record = json.loads((tmp_path / "child" / "config.json").read_text())
    assert record["init_from"].endswith("model.npz")
    with pytest.raises(ValueError, match="architecture differs"):
        T.train(toy["path"], TINY._replace(model=GNNConfig(hidden=12, passes=1), init_from=str(validated["run"])),
                tmp_path / "bad", split=NO_VAL, **QUIET)
    with pytest.raises(ValueError, match="no model file"):
        T.train(toy["path"], TINY._replace(init_from=str(tmp_path / "nowhere")), tmp_path / "bad2", split=NO_VAL,
                **QUIET)


def test_run_writes_the_selected_model_where_the_cli_reports_it(toy, validated, tmp_path):
    # `tignn train --config` calls run: a finished run (here the validated one, resumed) writes model/model.npz.
    from tignn_jax import api

    model = T.run(str(toy["path"]), TINY, validated["run"], progress=False)
    assert (validated["run"] / "model" / "model.npz").exists()
    np.testing.assert_array_equal(_flat(model), _flat(api.load_model(validated["run"] / "best" / "model.npz")))
    # two files concatenated (sim ids 1-5, 6-10), 4 training cases as above (the same compiled step), no selection
    twice = T.run([str(toy["path"])] * 2, TINY, tmp_path / "two", progress=False, split=([1, 2, 6, 7], None))
    assert twice["info"]["data"] == [str(toy["path"].resolve())] * 2


def test_a_batch_with_a_non_finite_loss_is_skipped(toy, tmp_path):
    # The train step leaves weights and optimiser unchanged when a batch's loss is not finite and reports it.
    data = toy["data"]
    params = T.train(toy["path"], TINY, tmp_path / "run", split=NO_VAL, stop_after_epoch=0, **QUIET)
    arrays = params["arrays"]
    weights = arrays["weights"]
    total = TINY.epochs * 16 // TINY.batch_size   # the runs' schedule (16 training transitions): one compilation
    state = {"step": jnp.zeros((), jnp.int32), "weights": weights,
             "opt_state": T.make_optimizer(TINY, total).init(weights)}
    train_step = T.make_train_step(TINY, total, arrays)
    devices = Mesh(np.array(jax.local_devices()), ("data",))   # placed as `train` places them
    state = jax.device_put(state, NamedSharding(devices, P()))
    step = lambda st, batch: train_step(st, jax.device_put(batch, NamedSharding(devices, P("data"))))
    z, f = jnp.asarray(data.z[:4]), jnp.asarray(data.f[:4])
    good, m_good = step(state, T.Batch(z[:, 0], f[:, 0], z[:, 1]))
    bad, m_bad = step(state, T.Batch(z[:, 0], f[:, 0].at[0, 0, 0].set(jnp.nan), z[:, 1]))
    assert float(m_good["skipped"]) == 0.0 and float(m_bad["skipped"]) == 1.0
    assert float(m_bad["loss"]) == 0.0 and int(bad["step"]) == 1
    flat = lambda s: np.concatenate([np.ravel(np.asarray(x)) for x in jax.tree_util.tree_leaves(s["weights"])])
    np.testing.assert_array_equal(flat(bad), flat(state))
    assert not np.array_equal(flat(good), flat(state))


def test_case_weights_equalise_relative_errors(toy):
    # Power 1: a case with half the response gets 4x the weight, so weight * scale² is the same for every case.
    base = toy["data"]
    rows = D.split_rows(base, "train")
    data = base._replace(z=base.z.copy())
    data.z[rows[0], ..., :3] = data.q0 + 0.5 * (base.z[rows[0], ..., :3] - data.q0)
    data.z[rows[0], ..., 3:] *= 0.5
    w = T.case_weights(data, rows, 1.0)
    assert w.shape == (len(rows), 12)
    np.testing.assert_allclose(w.mean(axis=0), 1.0, rtol=1e-6)
    free = data.node_type == 0
    z = data.z[rows, 1:].astype(np.float64)
    ms_u = np.mean((z[:, :, free, :3] - data.q0[free]) ** 2, axis=(1, 2, 3))
    ms_s = np.mean(z[..., 6:] ** 2, axis=(1, 2, 3))
    np.testing.assert_allclose(w[:, 0] * ms_u, (w[:, 0] * ms_u).mean(), rtol=1e-5)
    np.testing.assert_allclose(w[:, 6] * ms_s, (w[:, 6] * ms_s).mean(), rtol=1e-5)
    before = T.case_weights(base, rows, 1.0)
    np.testing.assert_allclose(w[0] / w[1], 4 * before[0] / before[1], rtol=1e-5)
    np.testing.assert_array_equal(T.case_weights(data, rows, 0.0), 1.0)
    with pytest.raises(ValueError, match="case_weight"):
        T.case_weights(data, rows, -1.0)


@pytest.mark.parametrize("field, value", [("batch_size", 0), ("epochs", -2), ("lr", 0.0), ("noise", -0.1),
                                          ("case_weight", float("nan")), ("warmup_steps", 1.5)])
def test_bad_recipe_values_raise_naming_the_value(field, value):
    with pytest.raises(ValueError) as err:
        TINY._replace(**{field: value}).check()
    assert field in str(err.value) and repr(value) in str(err.value)
    with pytest.raises(ValueError, match="activation"):
        TINY._replace(model=GNNConfig(activation="relu")).check()


def test_shipped_recipes_are_the_last_training_phases_of_the_beam_networks():
    # The records of the shipped beam networks' training (model files' info: train_config), in this recipe's form.
    fields = {"lr": 3e-4, "lr_end": 2e-5, "weight_decay": 1e-6, "batch_size": 2, "warmup_steps": 50, "noise": 0.2,
              "deg_weight": 1.0, "case_weight": 1.0, "seed": 0, "eval_every": 2}
    recipe, trainer = load_recipe(ROOT / "configs" / "beam_abaqus.py")
    assert trainer is T
    assert recipe.model == GNNConfig(hidden=64, mlp_layers=2, passes=3, activation="silu")
    assert recipe._replace(model=None)._asdict() == {**fields, "model": None, "epochs": 8, "ckpt_every": 2,
                                                      "init_from": None}


def test_relative_errors_are_per_snapshot_over_the_true_norm():
    # Known answers: one node, snapshots 0..2 whose true velocity is 2, 0 and 1 in x, predicted with an error of 0.5
    # in each: snapshot 0 is the given state (dropped), snapshot 1 has no true norm (NaN), snapshot 2 gives 0.5.
    q0 = np.zeros((1, 3))
    true = np.zeros((3, 1, 12))
    true[:, 0, 3] = [2.0, 0.0, 1.0]
    pred = true.copy()
    pred[:, 0, 3] += 0.5
    errs = T.relative_errors(pred, true, q0)
    assert errs.shape == (2, 4)
    v = T.VARIABLES.index("v")
    assert np.isnan(errs[0, v]) and errs[1, v] == pytest.approx(0.5)
    assert np.all(np.isnan(errs[:, T.VARIABLES.index("u")]))   # u = q − q0 is zero throughout
