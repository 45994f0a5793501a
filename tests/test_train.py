"""Training: the loss goes down, checkpoints resume exactly, data parallelism matches one device, the CLI runs."""
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tignn_jax import api
from tignn_jax import data as D
from tignn_jax import graph as G
from tignn_jax import model as M
from tignn_jax import train as T

TINY = T.CONFIGS["tiny"]._replace(epochs=4, batch_size=4, lr=1e-2, warmup_steps=1, eval_every=100,
                                   ckpt_every=100)
QUIET = dict(val_split=None, progress=False, log=lambda s: None)


@pytest.fixture(scope="module")
def toy():
    return D.synthetic_beam(nx=4, ny=2, nz=2, cases=5, frames=4)


def _mean_loss(params, data, cfg):
    """Noise-free loss over all training transitions."""
    rows = D.split_rows(data, "train")
    z, f = data.z[rows], data.f[rows]
    batch = T.Batch(jnp.asarray(z[:, :-1].reshape(-1, *z.shape[2:])), jnp.asarray(f.reshape(-1, *f.shape[2:])),
                    jnp.asarray(z[:, 1:].reshape(-1, *z.shape[2:])))
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0))
    loss, _ = _jit_loss(params["weights"], batch, jax.random.PRNGKey(0), params["norm"], cfg._replace(noise=0.0),
                        jnp.asarray(data.node_type, jnp.int32), topo)
    return float(loss)


_jit_loss = jax.jit(T.loss_fn, static_argnames="cfg")


def _flat(params):
    return np.concatenate([np.ravel(np.asarray(x)) for x in jax.tree_util.tree_leaves(params["weights"])])


def test_tiny_training_reduces_the_loss(toy, tmp_path):
    # A few epochs on a smooth toy bar must fit the one-step increments better than the initial weights.
    cfg = TINY._replace(epochs=12)
    initial = T.train(toy, cfg, tmp_path / "init", stop_after_epoch=0, **QUIET)
    trained = T.train(toy, cfg, tmp_path / "run", **QUIET)
    assert _mean_loss(trained, toy, cfg) < 0.7 * _mean_loss(initial, toy, cfg)
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [x["epoch"] for x in lines] == list(range(1, 13))


def test_resumed_run_reproduces_the_uninterrupted_run(toy, tmp_path):
    # Batch order and noise depend only on (seed, epoch, step): stop after epoch 2, resume, same weights.
    whole = T.train(toy, TINY, tmp_path / "whole", **QUIET)
    T.train(toy, TINY, tmp_path / "split", stop_after_epoch=2, **QUIET)
    resumed = T.train(toy, TINY, tmp_path / "split", **QUIET)
    np.testing.assert_array_equal(_flat(whole), _flat(resumed))
    lines = [json.loads(x) for x in (tmp_path / "split" / "metrics.jsonl").read_text().splitlines()]
    assert [x["epoch"] for x in lines] == [1, 2, 3, 4]


def test_data_parallel_training_matches_one_device(tmp_path):
    # Sharding the batch over 2 (virtual CPU) devices computes the same gradient as one device.
    script = textwrap.dedent(f"""
        import jax, numpy as np
        from tignn_jax import data as D, train as T
        assert jax.local_device_count() == 2, jax.local_devices()
        data = D.synthetic_beam(nx=4, ny=2, nz=2, cases=5, frames=4)
        cfg = T.CONFIGS["tiny"]._replace(epochs=2, batch_size=4, eval_every=100, ckpt_every=100)
        flat = lambda p: np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(p["weights"])])
        quiet = dict(val_split=None, progress=False, log=lambda s: None)
        one = T.train(data, cfg, r"{tmp_path}/one", devices=jax.local_devices()[:1], **quiet)
        two = T.train(data, cfg, r"{tmp_path}/two", **quiet)
        a, b = flat(one), flat(two)
        assert np.allclose(a, b, rtol=1e-4, atol=1e-6), np.abs(a - b).max()
        print("DATA-PARALLEL OK")
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "DATA-PARALLEL OK" in out.stdout


def test_cli_trains_rolls_out_and_evaluates(toy, tmp_path):
    # `tignn train`, `tignn rollout`, `tignn evaluate` on a data file, end to end.
    from tignn_jax import cli

    path = tmp_path / "toy.npz"
    D.save(toy, path)
    run = tmp_path / "run"
    assert cli.main(["train", "--data", str(path), "--config", "tiny", "--set", "epochs=1", "--run-dir", str(run),
                     "--no-progress"]) == 0
    model = run / "best" / "model.npz"
    out = tmp_path / "pred.npz"
    assert cli.main(["rollout", "--model", str(model), "--data", str(path), "--sims", "4,5", "--out", str(out)]) == 0
    pred = np.load(out)["z"]
    assert pred.shape == (2,) + toy.z.shape[1:]
    np.testing.assert_array_equal(pred[:, 0], toy.z[3:5, 0])
    params, graph = api.load_pretrained(str(model))
    np.testing.assert_allclose(pred[0], np.asarray(api.rollout(params, api.G.from_data(toy, 3), toy.f[3])),
                               rtol=1e-5, atol=1e-5)
    report_dir = tmp_path / "eval"
    assert cli.main(["evaluate", "--model", str(model), "--data", str(path), "--splits", "train,test",
                     "--out", str(report_dir), "--no-structure"]) == 0
    report = json.loads((report_dir / "report.json").read_text())
    assert set(report) == {"train", "test"} and report["test"]["free"]["u"]["mean"] > 0
    assert (report_dir / "boxplot.png").exists()


def test_concatenated_data_sets_keep_unique_ids_and_splits(tmp_path):
    """Merging reference and interaction cases: ids stay unique, each split keeps its own cases, and a round
    trip through save/load returns the same arrays."""
    a = D.synthetic_beam(cases=3, frames=2, seed=0)
    b = D.synthetic_beam(cases=2, frames=2, seed=1)
    m = D.concatenate(a, b)
    assert m.z.shape[0] == 5 and len(set(m.sim_id.tolist())) == 5
    for name in a.splits:
        rows = D.split_rows(m, name)
        expect = np.concatenate([a.z[D.split_rows(a, name)], b.z[D.split_rows(b, name)]])
        np.testing.assert_array_equal(m.z[rows], expect)
    back = D.load(D.save(m, tmp_path / "m.npz"))
    np.testing.assert_array_equal(back.z, m.z)
    np.testing.assert_array_equal(back.sim_id, m.sim_id)
    assert {k: v.tolist() for k, v in back.splits.items()} == {k: v.tolist() for k, v in m.splits.items()}


def test_from_frame_keeps_the_later_transitions_aligned():
    d = D.synthetic_beam(cases=2, frames=5, seed=0)
    later = D.from_frame(d, 2)
    assert later.z.shape[1] == 4 and later.f.shape[1] == 3
    # transition k of the sliced set is transition k + 2 of the original: same state, force and next state
    np.testing.assert_array_equal(later.z[:, 0], d.z[:, 2])
    np.testing.assert_array_equal(later.f[:, 1], d.f[:, 3])
    np.testing.assert_array_equal(later.z[:, -1], d.z[:, -1])
    for bad in (-1, 5, 1.5):
        with pytest.raises(ValueError, match="start must be an integer frame in 0..4"):
            D.from_frame(d, bad)


def test_select_keeps_the_chosen_cases_and_their_splits():
    d = D.synthetic_beam(cases=5, frames=2, seed=0)
    part = D.select(d, [0, 3, 4])
    np.testing.assert_array_equal(part.z, d.z[[0, 3, 4]])
    assert part.sim_id.tolist() == d.sim_id[[0, 3, 4]].tolist()
    for name, ids in part.splits.items():
        assert set(ids.tolist()) == set(d.splits[name].tolist()) & set(part.sim_id.tolist())
    with pytest.raises(ValueError, match="rows must be non-empty indices in 0..4"):
        D.select(d, [5])


def test_concatenate_refuses_a_different_mesh():
    a = D.synthetic_beam(nx=4, cases=2, frames=2)
    b = D.synthetic_beam(nx=5, cases=2, frames=2)
    with pytest.raises(ValueError, match="q0"):
        D.concatenate(a, b)


def test_case_weights_equalise_relative_errors(toy):
    # Power 1: a case with half the response gets 4x the weight, so weight * scale^2 is the same for every case.
    rows = D.split_rows(toy, "train")
    data = toy._replace(z=toy.z.copy())
    data.z[rows[0], ..., :3] = data.q0 + 0.5 * (toy.z[rows[0], ..., :3] - data.q0)
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
    before = T.case_weights(toy, rows, 1.0)
    np.testing.assert_allclose(w[0] / w[1], 4 * before[0] / before[1], rtol=1e-5)
    np.testing.assert_array_equal(T.case_weights(data, rows, 0.0), 1.0)
    with pytest.raises(ValueError, match="case_weight"):
        T.case_weights(data, rows, -1.0)


def test_warm_start_begins_from_the_parent_and_records_it(toy, tmp_path):
    parent = T.train(toy, TINY, tmp_path / "parent", **QUIET)
    api.save_model(parent, tmp_path / "parent" / "best" / "model.npz")  # what a run with a val split writes
    child = T.train(toy, TINY._replace(case_weight=1.0), tmp_path / "child", stop_after_epoch=0,
                    init_from=tmp_path / "parent", **QUIET)
    # stop_after_epoch=0: no step taken, so the child's weights are the parent's final weights ...
    np.testing.assert_array_equal(_flat(parent), _flat(child))
    cfg = json.loads((tmp_path / "child" / "config.json").read_text())
    assert cfg["init_from"].endswith("model.npz") and cfg["case_weight"] == 1.0
    # ... and training from them with case weights runs and changes them.
    trained = T.train(toy, TINY._replace(case_weight=1.0), tmp_path / "child2", init_from=tmp_path / "parent",
                      **QUIET)
    assert np.all(np.isfinite(_flat(trained))) and not np.array_equal(_flat(trained), _flat(parent))
    with pytest.raises(ValueError, match="architecture differs"):
        T.train(toy, TINY._replace(hidden=12), tmp_path / "bad", init_from=tmp_path / "parent", **QUIET)
    with pytest.raises(ValueError, match="no model file"):
        T.train(toy, TINY, tmp_path / "bad2", init_from=tmp_path / "nowhere", **QUIET)


def test_force_scale_is_the_rms_of_the_loaded_nodes():
    # A point load on one node of many: the force feature of the loaded node is O(1), not O(sqrt(N)).
    data = D.synthetic_beam(nx=6, ny=2, nz=2, cases=2, frames=3)
    f = np.zeros_like(data.f)
    f[:, :, 5] = [0.0, 3.0, 4.0]          # |f| = 5 on one node in every frame
    norm = D.normalization(data._replace(f=f), np.arange(2))
    np.testing.assert_allclose(norm["f_std"], np.full(3, 5.0 / np.sqrt(3.0)), rtol=1e-6)
    unloaded = D.normalization(data._replace(f=np.zeros_like(f)), np.arange(2))
    np.testing.assert_array_equal(unloaded["f_std"], np.ones(3))


def test_normalisation_streams_over_cases_with_the_same_statistics():
    # Running sums over a few cases at a time give the statistics of all the rows' values at once.
    data = D.synthetic_beam(nx=5, ny=2, nz=2, cases=5, frames=4)
    rng = np.random.default_rng(1)
    data = data._replace(z=data.z + rng.normal(size=data.z.shape).astype(np.float32) * 0.1)
    rows = np.array([4, 0, 2, 3])
    ref = D.normalization(data, rows, chunk=len(rows))
    for chunk in (1, 3):
        got = D.normalization(data, rows, chunk=chunk)
        assert got.keys() == ref.keys()
        for k in ref:
            np.testing.assert_allclose(got[k], ref[k], rtol=1e-6, err_msg=k)
    z = data.z[rows].astype(np.float64)
    s, r = data.edges
    dq = z[..., s, :3] - z[..., r, :3]
    flat = z.reshape(-1, 12)
    np.testing.assert_allclose(ref["z_mean"], flat.mean(0), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(ref["z_std"][6:], np.maximum(flat[:, 6:].std(0), 1e-2 * flat[:, 6:].std(0).max()),
                               rtol=1e-5)
    np.testing.assert_allclose(ref["z_std"][:3], np.sqrt(np.mean((flat[:, :3] - flat[:, :3].mean(0)) ** 2)), rtol=1e-5)
    np.testing.assert_allclose(ref["dq_std"], np.sqrt(np.mean(dq ** 2)), rtol=1e-6)
    np.testing.assert_allclose(ref["dqn_std"], np.linalg.norm(dq, axis=-1).std(), rtol=1e-5)
    dev = np.abs((flat - ref["z_mean"]) / ref["z_std"]).max(0)
    np.testing.assert_allclose(ref["z_dev_max"], dev, rtol=1e-5)
    with pytest.raises(ValueError, match="chunk"):
        D.normalization(data, rows, chunk=0)


def test_warm_start_keeps_the_parent_normalisation_and_may_switch_weight_free_options(toy, tmp_path):
    parent = T.train(toy, TINY, tmp_path / "parent", **QUIET)
    api.save_model(parent, tmp_path / "parent" / "best" / "model.npz")
    # data with doubled forces would change f_std; the warm start keeps the parent's
    louder = toy._replace(f=toy.f * 2.0)
    child = T.train(louder, TINY._replace(exact_degeneracy=True), tmp_path / "child", stop_after_epoch=0,
                    init_from=tmp_path / "parent", **QUIET)
    np.testing.assert_array_equal(np.asarray(child["norm"]["f_std"]), np.asarray(parent["norm"]["f_std"]))
    assert child["config"]["exact_degeneracy"] is True
    np.testing.assert_array_equal(_flat(parent), _flat(child))


def _loss_inputs(toy, cfg):
    """(topo, node_type, norm, z [2,T+1,N,12], f [2,T,N,3], untrained weights) for calling the loss directly."""
    topo = M.topology(toy.edges[0], toy.edges[1], len(toy.q0))
    node_type = jnp.asarray(toy.node_type, jnp.int32)
    norm = {k: jnp.asarray(v) for k, v in D.normalization(toy, D.split_rows(toy, "train")).items()}
    z, f = jnp.asarray(toy.z[:2]), jnp.asarray(toy.f[:2])
    weights = M.init_weights(jax.random.PRNGKey(1), cfg.model, norm, z[0, 0], f[0, 0], node_type, topo)
    return topo, node_type, norm, z, f, weights


def test_unrolled_loss_is_the_mean_of_its_steps_from_the_model_own_states(toy):
    # unroll K: step 1 starts from the data, step 2 from the model's own prediction, each scored against the truth.
    cfg = TINY._replace(noise=0.0)
    topo, node_type, norm, z, f, weights = _loss_inputs(toy, cfg)
    key = jax.random.PRNGKey(0)
    one = lambda z0, f0, z1: float(_jit_loss(weights, T.Batch(z0, f0, z1), key, norm, cfg, node_type, topo)[0])
    two, _ = _jit_loss(weights, T.Batch(z[:, 0], f[:, 0:2], z[:, 1:3]), key, norm, cfg, node_type, topo)
    pred = jax.vmap(lambda a, b: M.step_state(weights, cfg.model, norm, a, b, node_type, topo))(z[:, 0], f[:, 0])
    expected = 0.5 * (one(z[:, 0], f[:, 0], z[:, 1]) + one(pred, f[:, 1], z[:, 2]))
    assert float(two) == pytest.approx(expected, rel=1e-5)
    # a step axis of length 1 is the plain one-step loss
    assert float(_jit_loss(weights, T.Batch(z[:, 0], f[:, 0:1], z[:, 1:2]), key, norm, cfg, node_type, topo)[0]) \
        == pytest.approx(one(z[:, 0], f[:, 0], z[:, 1]), rel=1e-6)


def test_unrolled_training_runs_resumes_and_checks_its_length(toy, tmp_path):
    cfg = TINY._replace(unroll=2)
    whole = T.train(toy, cfg, tmp_path / "whole", **QUIET)
    T.train(toy, cfg, tmp_path / "split", stop_after_epoch=1, **QUIET)
    np.testing.assert_array_equal(_flat(whole), _flat(T.train(toy, cfg, tmp_path / "split", **QUIET)))
    lines = [json.loads(x) for x in (tmp_path / "whole" / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(x["loss"]) for x in lines)
    with pytest.raises(ValueError, match="unroll must be between 1 and the 4 frames.*got 5"):
        T.train(toy, TINY._replace(unroll=5), tmp_path / "bad", **QUIET)


def test_snapshot_loss_is_the_mean_squared_relative_rollout_error(toy):
    # snapshot_loss: the loss is the mean over steps, samples and (u, v, σ) of |pred − true|² / |true|² at each
    # snapshot, the square of evaluate.relative_errors' measure, from the model's own states.
    cfg = TINY._replace(noise=0.0, snapshot_loss=True, deg_weight=0.0)
    topo, node_type, norm, z, f, weights = _loss_inputs(toy, cfg)
    rel = jnp.asarray(T.snapshot_weights(toy, np.arange(2))[:, 1:3])
    loss, metrics = _jit_loss(weights, T.Batch(z[:, 0], f[:, 0:2], z[:, 1:3], rel=rel), jax.random.PRNGKey(0),
                              norm, cfg, node_type, topo)
    step = jax.vmap(lambda a, b: M.step_state(weights, cfg.model, norm, a, b, node_type, topo))
    pred1 = step(z[:, 0], f[:, 0])
    pred = np.stack([np.asarray(z[:, 0]), np.asarray(pred1), np.asarray(step(pred1, f[:, 1]))], axis=1)
    from tignn_jax import evaluate as EV
    err = EV.relative_errors(pred, np.asarray(z[:, :3]), toy.q0)[:, 1:, 1:]     # [cases, 2, (v, σ, u)]
    expected = np.mean(err[..., [2, 0, 1]] ** 2)
    assert float(loss) == pytest.approx(expected, rel=1e-4)
    assert float(metrics["rel2_u"]) == pytest.approx(np.mean(err[..., 2] ** 2), rel=1e-4)
    with pytest.raises(ValueError, match="snapshot_loss needs"):
        T.loss_fn(weights, T.Batch(z[:, 0], f[:, 0:2], z[:, 1:3]), jax.random.PRNGKey(0), norm, cfg, node_type, topo)


def test_bptt_gradient_is_the_derivative_of_the_rollout_loss(toy):
    # With bptt the gradient of the unrolled loss matches a central finite difference of that loss along a
    # random direction (float64); the pushforward gradient (each step's input state held constant) does not.
    cfg = TINY._replace(noise=0.0, unroll=3)
    with jax.enable_x64(True):
        topo, node_type, norm, z, f, weights = _loss_inputs(toy, cfg)
        as64 = lambda t: jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), t)
        weights, norm = as64(weights), as64(norm)
        z, f = jnp.asarray(z, jnp.float64), jnp.asarray(f, jnp.float64)
        batch, key = T.Batch(z[:, 0], f[:, 0:3], z[:, 1:4]), jax.random.PRNGKey(0)
        leaves, tree = jax.tree_util.tree_flatten(weights)
        dirs = jax.tree_util.tree_unflatten(tree, [jax.random.normal(jax.random.PRNGKey(i), x.shape, x.dtype)
                                                   for i, x in enumerate(leaves)])

        loss = jax.jit(lambda w: T.loss_fn(w, batch, key, norm, cfg, node_type, topo)[0])   # compiled once

        def loss_at(eps):
            return float(loss(jax.tree.map(lambda a, d: a + eps * d, weights, dirs)))

        def directional(c):
            g = jax.jit(jax.grad(lambda w: T.loss_fn(w, batch, key, norm, c, node_type, topo)[0]))(weights)
            return sum(float(jnp.vdot(a, d)) for a, d in zip(jax.tree.leaves(g), jax.tree.leaves(dirs)))

        h = 1e-5
        fd = (loss_at(h) - loss_at(-h)) / (2 * h)
        through, held = directional(cfg._replace(bptt=True)), directional(cfg)
    assert through == pytest.approx(fd, rel=1e-5)
    assert abs(held - fd) > 1e-3 * abs(fd)


def test_v_weight_is_a_weighted_mean_of_the_feature_mses(toy):
    # loss = the mean of the squared errors with the v entries counted w times (q and v over the free nodes, σ
    # over all) + degeneracy; w = 1 is the plain loss; the reported MSEs do not change with w.
    cfg = TINY._replace(noise=0.0)
    topo, node_type, norm, z, f, weights = _loss_inputs(toy, cfg)
    batch, key = T.Batch(z[:, 0], f[:, 0], z[:, 1]), jax.random.PRNGKey(0)
    plain, m1 = _jit_loss(weights, batch, key, norm, cfg, node_type, topo)
    same, _ = _jit_loss(weights, batch, key, norm, cfg._replace(v_weight=1.0), node_type, topo)
    heavy, m4 = _jit_loss(weights, batch, key, norm, cfg._replace(v_weight=4.0), node_type, topo)
    assert float(same) == float(plain)
    assert float(plain) == pytest.approx(float(m1["mse"]) + cfg.deg_weight * float(m1["degeneracy"]), rel=1e-6)
    for k in ("mse", "mse_q", "mse_v", "mse_sigma", "degeneracy"):
        assert float(m4[k]) == pytest.approx(float(m1[k]), rel=1e-6)
    # q and v rows are masked at the clamped nodes alike, so the per-feature denominators of q and v are equal
    n_free, n = int(np.sum(toy.node_type == 0)), len(toy.node_type)
    num = n_free * 3 * (float(m1["mse_q"]) + 4 * float(m1["mse_v"])) + n * 6 * float(m1["mse_sigma"])
    expected = num / (n_free * 3 * (1 + 4) + n * 6) + float(cfg.deg_weight * m1["degeneracy"])
    assert float(heavy) == pytest.approx(expected, rel=1e-5)
    assert float(heavy) != pytest.approx(float(plain), rel=1e-3)


def test_port_gain_is_the_first_frame_velocity_per_unit_force_of_cases_starting_at_rest():
    data = D.synthetic_beam(nx=6, ny=2, nz=2, cases=2, frames=3)
    z, f = data.z.copy(), np.zeros_like(data.f)
    f[:, :, 5] = [0.0, 3.0, 4.0]
    z[:, 0, :, 3:6] = 0.0                     # both cases start at rest ...
    z[:, 1, 5, 3:6] = 2.5 * f[:, 0, 5]        # ... and the loaded node gains 2.5 × f in the first frame
    z[:, 1, :5, 3:6] = 0.0
    z[:, 1, 6:, 3:6] = 0.0
    norm = D.normalization(data._replace(z=z, f=f), np.arange(2))
    np.testing.assert_allclose(norm["port_gain"], [2.5], rtol=1e-6)
    z[:, 0, 0, 3] = 1.0                       # no case at rest: no gain, the model keeps the f / f_std scale
    assert "port_gain" not in D.normalization(data._replace(z=z, f=f), np.arange(2))


def test_evaluation_reuses_the_models_topology_on_its_own_mesh_only(toy):
    # A coarse model's Topology includes the clustering; evaluation takes the model's own when the data are on
    # the model's mesh, and builds one from the data's mesh otherwise. The rollouts are the same either way.
    from tignn_jax import evaluate as EV

    config = M.ModelConfig(hidden=8, passes=1, coarse_nodes=3)
    norm = D.normalization(toy, D.split_rows(toy, "train"))
    topo = M.model_topology(config, toy.edges[0], toy.edges[1], len(toy.q0), toy.q0)
    nt = jnp.asarray(toy.node_type, jnp.int32)
    weights = M.init_weights(jax.random.PRNGKey(0), config, norm, jnp.asarray(toy.z[0, 0]), jnp.asarray(toy.f[0, 0]),
                             nt, topo)
    params = api.make_params(config, norm, weights, toy.q0, toy.edges, toy.node_type)
    assert EV._topology(params, config, toy) is params["topo"]
    moved = toy._replace(q0=toy.q0 + 0.5)
    assert EV._topology(params, config, moved) is not params["topo"]
    rows = D.split_rows(toy, "test")
    rebuilt = EV._rollout_many(weights, config, params["norm"], jnp.asarray(toy.z[rows, 0]), jnp.asarray(toy.f[rows]),
                               nt, topo)
    np.testing.assert_allclose(EV.rollout_cases(params, toy, rows), np.asarray(rebuilt), rtol=1e-6, atol=1e-6)


def test_relative_errors_per_snapshot_and_per_case_peak():
    # Known answers: one node, three snapshots whose true velocity is 2, 0 and 1 in x, predicted with an error of
    # 0.5 in each. Per snapshot: 0.25, NaN (zero true norm), 0.5; relative to the case's peak (2): 0.25 each.
    from tignn_jax import evaluate as EV

    q0 = np.zeros((1, 3))
    true = np.zeros((3, 1, 12))
    true[:, 0, 3] = [2.0, 0.0, 1.0]
    pred = true.copy()
    pred[:, 0, 3] += 0.5
    v = EV.VARIABLES.index("v")
    snap = EV.relative_errors(pred, true, q0)[:, v]
    np.testing.assert_allclose(snap[[0, 2]], [0.25, 0.5])
    assert np.isnan(snap[1])
    np.testing.assert_allclose(EV.relative_errors(pred, true, q0, reference="peak")[:, v], [0.25, 0.25, 0.25])
    with pytest.raises(ValueError, match="reference"):
        EV.relative_errors(pred, true, q0, reference="max")


def test_a_batch_with_a_non_finite_loss_is_skipped(toy):
    # The train step leaves weights and optimiser unchanged when a batch's loss is not finite and reports it.
    cfg = TINY
    rows = D.split_rows(toy, "train")
    norm = {k: jnp.asarray(v) for k, v in D.normalization(toy, rows).items()}
    node_type = jnp.asarray(toy.node_type, jnp.int32)
    topo = M.topology(toy.edges[0], toy.edges[1], len(toy.q0))
    z, f = jnp.asarray(toy.z[:2]), jnp.asarray(toy.f[:2])
    weights = M.init_weights(jax.random.PRNGKey(1), cfg.model, norm, z[0, 0], f[0, 0], node_type, topo)
    state = {"step": jnp.zeros((), jnp.int32), "weights": weights,
             "opt_state": T.make_optimizer(cfg, 10).init(weights)}
    step = T.make_train_step(cfg, 10, norm, node_type, topo)
    good, m_good = step(state, T.Batch(z[:, 0], f[:, 0], z[:, 1]))
    bad, m_bad = step(state, T.Batch(z[:, 0], f[:, 0].at[0, 0, 0].set(jnp.nan), z[:, 1]))
    assert float(m_good["skipped"]) == 0.0 and float(m_bad["skipped"]) == 1.0
    assert float(m_bad["loss"]) == 0.0
    np.testing.assert_array_equal(_flat(bad), _flat(state))
    assert not np.array_equal(_flat(good), _flat(state))
    assert int(bad["step"]) == 1


def test_heun_training_scores_the_heun_step_and_trains(toy, tmp_path):
    """With integrator='heun' the loss's data term is the squared error of the Heun step (two rates per step),
    training lowers it, and the trained model rolls out with Heun."""
    cfg = TINY._replace(noise=0.0, integrator="heun")
    topo, node_type, norm, z, f, weights = _loss_inputs(toy, cfg)
    _, metrics = _jit_loss(weights, T.Batch(z[:, 0], f[:, 0], z[:, 1]), jax.random.PRNGKey(0), norm, cfg,
                           node_type, topo)
    pred = jax.vmap(lambda a, b: M.step_state(weights, cfg.model, norm, a, b, node_type, topo))(z[:, 0], f[:, 0])
    keep = np.ones(M.STATE_DIM) * np.ones((len(toy.q0), 1))
    keep[np.asarray(toy.node_type) != 0, :6] = 0.0
    sq = ((np.asarray(pred) - np.asarray(z[:, 1])) / np.asarray(norm["dz_std"])) ** 2 * keep
    assert float(metrics["mse"]) == pytest.approx(sq.sum() / (z.shape[0] * keep.sum()), rel=1e-4)
    trained = T.train(toy, cfg._replace(epochs=12), tmp_path / "heun", **QUIET)
    initial = T.train(toy, cfg._replace(epochs=12), tmp_path / "init", stop_after_epoch=0, **QUIET)
    assert _mean_loss(trained, toy, cfg) < 0.7 * _mean_loss(initial, toy, cfg)
    assert trained["config"]["integrator"] == "heun"


def test_stability_probe_finds_the_largest_eigenvalue_of_the_rest_step(toy):
    # Power iteration with stability_term's finite-difference probe converges to the spectral radius of the
    # step's Jacobian at rest (the dense Jacobian by reverse mode, its eigenvalues by numpy).
    cfg = TINY._replace(stability_weight=1.0, stability_eps=1e-4)
    topo = M.topology(toy.edges[0], toy.edges[1], len(toy.q0))
    rows = D.split_rows(toy, "train")
    norm = {k: jnp.asarray(v) for k, v in D.normalization(toy, rows).items()}
    node_type = jnp.asarray(toy.node_type, jnp.int32)
    weights = M.init_weights(jax.random.PRNGKey(3), cfg.model, norm, jnp.asarray(toy.z[0, 0]),
                             jnp.asarray(toy.f[0, 0]), node_type, topo)
    z_rest = jnp.asarray(G.rest_state(toy.q0))
    probe = T.initial_probes(0, len(toy.q0))
    f0 = jnp.zeros((len(toy.q0), 3))
    term = jax.jit(lambda p: T.stability_term(weights, p, norm, cfg, node_type, topo, z_rest[None], f0[None]))
    growths = []
    for _ in range(300):
        drift, growth, probe = term(probe)
        growths.append(float(growth[0]))
    std = norm["z_std"]
    step = lambda x: (M.step_state(weights, cfg.model, norm, z_rest + x * std, f0, node_type, topo) / std).ravel()
    jac = np.asarray(jax.jacrev(step)(jnp.zeros_like(z_rest))).reshape(z_rest.size, z_rest.size)
    free = np.ravel(~((np.asarray(toy.node_type) != 0)[:, None] & (np.arange(12) < 6)[None, :]))
    jac = jac[np.ix_(free, free)]   # clamped q, v are prescribed: not part of the dynamics
    rho = np.max(np.abs(np.linalg.eigvals(jac.astype(np.float64))))
    estimate = np.exp(np.mean(np.log(growths[-100:])))   # geometric mean: also for a complex pair
    assert abs(estimate / rho - 1) < 0.03, (estimate, rho)
    moved = M.step_state(weights, cfg.model, norm, z_rest, f0, node_type, topo) - z_rest
    keep = ~((toy.node_type != 0)[:, None] & (np.arange(12) < 6)[None, :])
    expected = np.sum((np.asarray(moved) / np.asarray(norm["dz_std"])) ** 2 * keep) / keep.sum()
    np.testing.assert_allclose(float(drift), expected, rtol=1e-4)


@pytest.mark.parametrize("where", [dict(stability_data=True), dict(stability_anchors=2)])
def test_stability_training_logs_the_rest_growth_and_resumes(toy, tmp_path, where):
    cfg = TINY._replace(stability_weight=1.0, stability_bound=0.5, **where)
    whole = T.train(toy, cfg, tmp_path / "whole", **QUIET)
    T.train(toy, cfg, tmp_path / "split", stop_after_epoch=2, **QUIET)
    np.testing.assert_array_equal(_flat(whole), _flat(T.train(toy, cfg, tmp_path / "split", **QUIET)))
    lines = [json.loads(x) for x in (tmp_path / "whole" / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(x["rest_growth"]) and np.isfinite(x["data_growth"]) and x["rest_drift"] >= 0
               for x in lines)


def test_stability_anchors_are_training_states_and_are_checked(toy):
    rows = D.split_rows(toy, "train")
    z, f = T.stability_anchor_states(toy, rows, 2)
    np.testing.assert_array_equal(np.asarray(z[1]), toy.z[rows[0], toy.f.shape[1] - 1])
    np.testing.assert_array_equal(np.asarray(f[0]), toy.f[rows[0], toy.f.shape[1] // 2])
    with pytest.raises(ValueError, match="even number >= 2, got 3"):
        T.stability_anchor_states(toy, rows, 3)
    with pytest.raises(ValueError, match="needs 50 training cases"):
        T.stability_anchor_states(toy, rows, 100)


def test_sigma_noise_sets_the_stress_features_own_noise_level(toy):
    # noise 0.1 on q, v and sigma_noise 1.0 on σ (× the increment std) is the noise-free loss of the batch
    # perturbed by hand with the same draw.
    rows = D.split_rows(toy, "train")
    norm = {k: jnp.asarray(v) for k, v in D.normalization(toy, rows).items()}
    topo = M.topology(toy.edges[0], toy.edges[1], len(toy.q0))
    node_type = jnp.asarray(toy.node_type, jnp.int32)
    cfg = TINY._replace(noise=0.1, sigma_noise=1.0)
    weights = M.init_weights(jax.random.PRNGKey(0), cfg.model, norm, jnp.asarray(toy.z[0, 0]),
                             jnp.asarray(toy.f[0, 0]), node_type, topo)
    batch = T.Batch(jnp.asarray(toy.z[rows[:2], 1]), jnp.asarray(toy.f[rows[:2], 1]), jnp.asarray(toy.z[rows[:2], 2]))
    key = jax.random.PRNGKey(5)
    keep = ~((toy.node_type != 0)[:, None] & (np.arange(12) < 6)[None, :])
    level = np.array([0.1] * 6 + [1.0] * 6, np.float32)
    by_hand = batch._replace(z=batch.z + jax.random.normal(key, batch.z.shape) * (level * norm["dz_std"]) * keep)
    loss, _ = _jit_loss(weights, batch, key, norm, cfg, node_type, topo)
    expected, _ = _jit_loss(weights, by_hand, key, norm, cfg._replace(noise=0.0, sigma_noise=None), node_type, topo)
    np.testing.assert_allclose(float(loss), float(expected), rtol=1e-5)
    plain, _ = _jit_loss(weights, batch, key, norm, cfg._replace(sigma_noise=None), node_type, topo)
    assert float(plain) != float(loss)
