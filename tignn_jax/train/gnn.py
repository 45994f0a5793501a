"""Training the thermodynamics-informed graph network (`tignn_jax.simulators.GenericGNN`) on one-step transitions.

A sample is a transition (z_k, f_k) → z_{k+1} of a training case. The loss is, as in Hernández et al. (2022,
arXiv:2203.01874), the mean squared error of the model's next state, per feature in units of the training
increments' standard deviation dz_std (the clamped nodes' q and v excluded), plus ``deg_weight`` times the mean
squared degeneracy residuals L ∇S and M ∇E in the same units::

    loss = mean_{b, i, a} ((z_next − z_true) / dz_std)²  +  deg_weight · mean ((L∇S)² + (M∇E)²) · (s / dz_std)².

Gaussian noise of ``noise`` × dz_std is added to the free entries of the input state while the target stays the
true next state, so the model learns to pull a perturbed state back (noise injection, as in MeshGraphNets).

The rollout error that selects the model is relative per case, while the loss is in global units, so cases with a
small response weigh little in it. ``case_weight`` = p > 0 multiplies each case's squared errors by
(s̄ / s_c)^(2p) per variable (u, v, σ), s_c the case's RMS displacement, velocity or stress and s̄ their mean
over the training cases (weights normalised to mean 1); p = 1 makes the loss a mean of relative squared errors.

Optimiser: AdamW after global-norm clipping at 1, the learning rate warmed up linearly from lr / 100 to ``lr``
over ``warmup_steps`` and decayed by a cosine to ``lr_end`` at the end of ``epochs``. Batches of transitions are
vmapped and sharded along the batch axis over the local devices (weights replicated). A batch whose loss or
gradient is not finite leaves weights and optimiser unchanged and is counted in the metric "skipped".

Every ``eval_every`` epochs the validation cases are rolled out from their first state under their true forces;
the score is the mean relative error (over snapshots 1..T, all nodes) of v + σ + u, and the best model so far is
written to ``run_dir``/best/model.npz (`tignn_jax.api.save_model`). Orbax checkpoints at epoch boundaries hold the
step, weights and optimiser state; batch order and noise are functions of (seed, epoch, step), so a resumed run
reproduces the uninterrupted one. A run may start from a trained model's weights and statistics (``init_from``,
a warm restart with a fresh schedule).
"""
from __future__ import annotations

import json
import time
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from tignn_jax import data as D
from tignn_jax.api import ENVELOPE, make_params
from tignn_jax.simulators.generic_gnn import STATE_DIM, GenericGNN, GNNConfig, prescribed, state_scale
from tignn_jax.train import is_count, is_number

VARIABLES = ("q", "v", "sigma", "u")


class TrainConfig(NamedTuple):
    """A training recipe for `GenericGNN`.

    Attributes:
      model: the architecture (`GNNConfig`).
      lr: peak learning rate, reached after ``warmup_steps``.
      lr_end: learning rate at the end of the cosine decay (the last step of ``epochs``).
      weight_decay: AdamW's decoupled weight decay.
      batch_size: transitions per step (a multiple of the number of local devices).
      epochs: passes over the training transitions.
      warmup_steps: steps of the linear warm-up from lr / 100.
      noise: input-noise std as a fraction of the per-feature increment std dz_std.
      deg_weight: weight of the degeneracy residuals in the loss.
      case_weight: the power p of the per-case loss weights (0: every case alike).
      seed: of the initial weights, the batch order and the noise.
      eval_every: epochs between validations (and best-model updates).
      ckpt_every: epochs between checkpoints (the last epoch of a run always gets one).
      init_from: a model file (or a run folder holding best/model.npz) to start from, with its normalisation
        statistics (part of the function its weights compute); its architecture must be ``model``. None: new
        weights drawn with ``seed``.
    """
    model: GNNConfig = GNNConfig()
    lr: float = 3e-3
    lr_end: float = 2e-5
    weight_decay: float = 1e-6
    batch_size: int = 2
    epochs: int = 30
    warmup_steps: int = 100
    noise: float = 0.2
    deg_weight: float = 1.0
    case_weight: float = 0.0
    seed: int = 0
    eval_every: int = 2
    ckpt_every: int = 2
    init_from: str | None = None

    def check(self) -> TrainConfig:
        """Returns the config unchanged.

        Raises:
          ValueError: naming the field and its value, for a non-positive count or learning rate, or a negative
            weight or noise level (and `GNNConfig.check`'s errors).
        """
        if not isinstance(self.model, GNNConfig):
            raise ValueError(f"model must be a GNNConfig, got {self.model!r}")
        self.model.check()
        for field in ("batch_size", "epochs", "eval_every", "ckpt_every"):
            value = getattr(self, field)
            if not is_count(value):
                raise ValueError(f"{field} must be a positive integer, got {value!r}")
        if not is_count(self.warmup_steps, 0):
            raise ValueError(f"warmup_steps must be a non-negative integer, got {self.warmup_steps!r}")
        for field in ("lr", "lr_end"):
            value = getattr(self, field)
            if not (is_number(value) and value > 0):
                raise ValueError(f"{field} must be a positive number, got {value!r}")
        for field in ("weight_decay", "noise", "deg_weight", "case_weight"):
            value = getattr(self, field)
            if not (is_number(value) and value >= 0):
                raise ValueError(f"{field} must be a finite number >= 0, got {value!r}")
        return self

    def as_dict(self) -> dict:
        """The recipe as JSON-ready nested dicts (``model`` as a dict of its fields)."""
        return {**self._asdict(), "model": self.model._asdict()}


class Batch(NamedTuple):
    """Stacked transitions of one mesh: z, z_next [B, N, 12]; f [B, N, 3] (the force during the step); w [B, 12]
    per-sample feature weights (`case_weights`) or None."""
    z: jax.Array
    f: jax.Array
    z_next: jax.Array
    w: jax.Array | None = None


def case_weights(data: D.Dataset, rows, power: float) -> np.ndarray:
    """Loss weights [len(rows), 12] per case and state feature: (mean scale / case scale)^(2 power), mean 1.

    A case's scales are the RMS over frames 1.. of the free nodes' displacement q − q0 (for the q features) and
    velocity, and of all nodes' stress (floored at 1e-3 of the largest case's).

    Raises:
      ValueError: ``power`` is negative or not finite.
    """
    rows = np.asarray(rows)
    if not (np.isfinite(power) and power >= 0):
        raise ValueError(f"case_weight must be a finite number >= 0, got {power}")
    if power == 0:
        return np.ones((len(rows), STATE_DIM), np.float32)
    z = data.z[rows, 1:].astype(np.float64)
    free = data.node_type == 0
    scales = np.stack([np.sqrt(np.mean((z[:, :, free, :3] - data.q0[free]) ** 2, axis=(1, 2, 3))),
                       np.sqrt(np.mean(z[:, :, free, 3:6] ** 2, axis=(1, 2, 3))),
                       np.sqrt(np.mean(z[..., 6:] ** 2, axis=(1, 2, 3)))], axis=1)   # [C, 3]
    scales = np.maximum(scales, 1e-3 * scales.max(axis=0, keepdims=True) + 1e-30)
    w = (scales.mean(axis=0) / scales) ** (2 * power)
    w = w / w.mean(axis=0)
    return np.repeat(w, [3, 3, 6], axis=1).astype(np.float32)


def make_optimizer(cfg: TrainConfig, total_steps: int) -> optax.GradientTransformation:
    """Global-norm clipping at 1, then AdamW on the warm-up + cosine schedule of ``cfg`` over ``total_steps``."""
    schedule = optax.warmup_cosine_decay_schedule(
        init_value=cfg.lr * 0.01, peak_value=cfg.lr, warmup_steps=min(cfg.warmup_steps, max(total_steps - 1, 1)),
        decay_steps=max(total_steps, 2), end_value=cfg.lr_end)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=cfg.weight_decay))


def loss_fn(weights, batch: Batch, key, arrays: dict, cfg: TrainConfig):
    """The training loss of a batch (module docstring) and its metrics.

    Args:
      weights: the flax parameters being trained.
      batch: the transitions (`Batch`).
      key: PRNG key of the input noise.
      arrays: the model's prepared arrays (`GenericGNN.prepare`); their ``weights`` entry is replaced.
      cfg: the recipe (``noise``, ``deg_weight`` and the architecture are read).

    Returns:
      (loss [], metrics): "loss", "mse" (the data term), "degeneracy" (the residual term before its weight),
      "mse_q", "mse_v", "mse_sigma" (the data term's feature groups), all dimensionless.
    """
    model = GenericGNN(cfg.model)
    arrays = {**arrays, "weights": weights}
    norm = arrays["norm"]
    c, s = norm["dz_std"], state_scale(norm)
    keep = (~prescribed(arrays["node_type"])).astype(batch.z.dtype)
    z_in = batch.z + jax.random.normal(key, batch.z.shape, batch.z.dtype) * (cfg.noise * c) * keep
    rt = jax.vmap(lambda z, f: model.rates(arrays, z, f))(z_in, batch.f)
    z_next = z_in + rt.dw * s
    sq = ((z_next - batch.z_next) / c) ** 2 * keep
    if batch.w is not None:
        sq = sq * batch.w[:, None, :]
    sq_sum = jnp.sum(sq, axis=(0, 1))                  # [12]
    denom = batch.z.shape[0] * jnp.sum(keep, axis=0)   # [12] entries per feature
    per_feature = sq_sum / denom
    data_loss = jnp.sum(sq_sum) / jnp.sum(denom)
    to_unit = s / c
    deg = jnp.mean((rt.deg_l * to_unit) ** 2 + (rt.deg_m * to_unit) ** 2)
    loss = data_loss + cfg.deg_weight * deg
    return loss, {"loss": loss, "mse": data_loss, "degeneracy": deg, "mse_q": per_feature[:3].mean(),
                  "mse_v": per_feature[3:6].mean(), "mse_sigma": per_feature[6:].mean()}


def make_train_step(cfg: TrainConfig, total_steps: int, arrays: dict):
    """``(state, batch) -> (state, metrics)``, compiled once per recipe, schedule length and shapes. ``state`` is
    {"step", "weights", "opt_state"}; the noise key is derived from (seed, step)."""
    context = {k: v for k, v in arrays.items() if k != "weights"}
    return lambda state, batch: _train_step(state, batch, context, cfg=cfg, total_steps=total_steps)


@partial(jax.jit, static_argnames=("cfg", "total_steps"))
def _train_step(state, batch, context, cfg, total_steps):
    optimizer = make_optimizer(cfg, total_steps)
    key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), state["step"])
    (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["weights"], batch, key, context, cfg)
    updates, opt_state = optimizer.update(grads, state["opt_state"], state["weights"])
    weights = optax.apply_updates(state["weights"], updates)
    finite = jnp.isfinite(metrics["loss"]) & jnp.all(jnp.array([jnp.all(jnp.isfinite(g))
                                                                for g in jax.tree.leaves(grads)]))
    keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, old)
    weights, opt_state = keep(weights, state["weights"]), keep(opt_state, state["opt_state"])
    metrics = {k: jnp.where(finite, v, 0.0) for k, v in metrics.items()}
    metrics["skipped"] = 1.0 - finite.astype(jnp.float32)
    return {"step": state["step"] + 1, "weights": weights, "opt_state": opt_state}, metrics


@partial(jax.jit, static_argnums=0)
def rollouts(model: GenericGNN, arrays: dict, z0, forces):
    """States [C, T+1, N, 12] of C bodies rolled out from z0 [C, N, 12] under forces [C, T, N, 3]."""
    def one(z_first, fs):
        def body(z, f):
            z = model.step_state(arrays, z, f)
            return z, z

        _, zs = jax.lax.scan(body, z_first, fs)
        return jnp.concatenate([z_first[None], zs])

    return jax.vmap(one)(z0, forces)


def relative_errors(pred, true, q0) -> np.ndarray:
    """[..., T, 4] relative L2 errors of snapshots 1..T of q, v, σ and u = q − q0 (``VARIABLES``), over all nodes,
    each over the true snapshot's norm (NaN where it is zero), of states pred, true [..., T+1, N, 12]."""
    pred, true = np.asarray(pred, np.float64)[..., 1:, :, :], np.asarray(true, np.float64)[..., 1:, :, :]
    q0 = np.asarray(q0, np.float64)
    out = []
    for name in VARIABLES:
        p, t = _variable(pred, q0, name), _variable(true, q0, name)
        num = np.sum((p - t) ** 2, axis=(-2, -1))
        den = np.sum(t ** 2, axis=(-2, -1))
        out.append(np.where(den > 0, np.sqrt(num / np.where(den > 0, den, 1.0)), np.nan))
    return np.stack(out, axis=-1)


def _variable(z, q0, name: str):
    """One of ``VARIABLES`` of states z [..., N, 12]: q, v, σ, or the displacement u = q − q0."""
    return z[..., :3] - q0 if name == "u" else z[..., {"q": D.Q, "v": D.V, "sigma": D.SIGMA}[name]]


def to_params(model: GenericGNN, stored: dict, mesh: dict, envelope: dict, info: dict) -> dict:
    """The model dict of `tignn_jax.simulators` (what `tignn_jax.api.save_model` writes).

    Args:
      model: the model class instance.
      stored: ``{"weights", "norm"}`` (`GenericGNN.stored`).
      mesh: ``{"q0" [N, 3], "senders" [E], "receivers" [E], "node_type" [N]}``.
      envelope: the training data's ``{"z_mean", "z_std", "z_dev_max", "u_max", "f_max"}``.
      info: provenance (JSON-ready).

    Returns:
      ``{"model", "arrays": model.prepare(stored, mesh), "mesh", "edges", "envelope", "info"}``; ``edges`` is the
      pair (senders, receivers) as jax arrays, as `tignn_jax.api.make_params` adds it.

    Raises:
      ValueError: a mesh or envelope entry is missing (or `GenericGNN.prepare`'s errors).
    """
    return make_params(model, stored, mesh, envelope, info)


def train(data_path, config: TrainConfig, run_dir, split=("train", "val"), progress: bool = True, *,
          stop_after_epoch: int | None = None, time_limit_s: float | None = None, log=print) -> dict:
    """Train a `GenericGNN` (or resume the run in ``run_dir`` from its latest checkpoint).

    Writes ``run_dir``/config.json (the recipe, data and parent), metrics.jsonl (one line per epoch: the mean
    training metrics, and the validation errors val_q, val_v, val_sigma, val_u and val_score where validated),
    checkpoints/ (orbax), best.json and best/model.npz (the lowest validation score so far).

    Args:
      data_path: a data file or folder (`tignn_jax.data.load`), a list of them on one mesh (their cases
        concatenated), or a loaded `tignn_jax.data.Dataset`.
      config: the recipe.
      run_dir: the run's folder.
      split: (training split, validation split): split names of the data set or lists of sim ids; a validation
        split of None skips validation (and the best model).
      progress: show a progress bar per epoch (tqdm).
      stop_after_epoch, time_limit_s: end the run early at an epoch boundary, with a checkpoint, as an
        interruption would; the schedule still spans ``config.epochs``.
      log: called with one line of text per epoch.

    Returns:
      The model dict (`to_params`) of the last weights.

    Raises:
      ValueError: an invalid recipe, a batch larger than the training set, an unknown split, or an
        ``config.init_from`` that is missing or of another architecture.
    """
    import orbax.checkpoint as ocp
    from tqdm import tqdm

    cfg = config.check()
    model = GenericGNN(cfg.model)
    data = _load(data_path)
    train_split, val_split = split
    rows = D.split_rows(data, train_split)
    val_rows = D.split_rows(data, val_split) if val_split is not None else None
    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    parent = _parent(cfg.init_from, model) if cfg.init_from is not None else None
    record = {"recipe": cfg.as_dict(), "data": _describe(data_path), "split": [_jsonable(s) for s in split]}
    if parent is not None:
        record.update(init_from=parent["path"], init_elapsed_s=parent["elapsed_s"])
    (run_dir / "config.json").write_text(json.dumps(record, indent=1))

    norm_np = D.normalization(data, rows)
    if parent is not None:   # the parent's scales are part of the function its weights compute: keep them
        norm_np.update(parent["stored"]["norm"])
    mesh = {"q0": np.asarray(data.q0, np.float32), "senders": data.edges[0], "receivers": data.edges[1],
            "node_type": data.node_type}
    in_memory = isinstance(data_path, D.Dataset)      # as `_load` reads it: a Dataset has no file for the cells
    cells = None if in_memory else D.cells(data_path if isinstance(data_path, (str, Path)) else data_path[0])
    stored = model.init(jax.random.PRNGKey(cfg.seed), norm_np, mesh)
    if parent is not None:
        stored["weights"] = parent["stored"]["weights"]
    arrays = model.prepare(stored, mesh)
    if cells is not None:      # kept with the model, for drawing its surface
        mesh = {**mesh, "cells": cells}
    envelope = {k: norm_np[k] for k in ENVELOPE}
    info = {"train_config": cfg.as_dict(), "data": _describe(data_path)}
    if parent is not None:
        info["init_from"] = parent["path"]

    frames = data.f.shape[1]
    n_samples = len(rows) * frames
    bs = cfg.batch_size
    steps_per_epoch = n_samples // bs
    if steps_per_epoch == 0:
        raise ValueError(f"batch_size {bs} exceeds the {n_samples} training transitions")
    total_steps = cfg.epochs * steps_per_epoch
    optimizer = make_optimizer(cfg, total_steps)
    devices = Mesh(np.array(jax.local_devices()), ("data",))
    if bs % devices.size:
        raise ValueError(f"batch_size {bs} is not divisible by the {devices.size} devices")
    batch_sharding, replicated = NamedSharding(devices, P("data")), NamedSharding(devices, P())

    weights = arrays["weights"]
    state = {"step": jnp.zeros((), jnp.int32), "weights": weights, "opt_state": optimizer.init(weights)}
    manager = ocp.CheckpointManager(run_dir / "checkpoints", options=ocp.CheckpointManagerOptions(
        max_to_keep=2, enable_async_checkpointing=False))
    start_epoch = 0
    best = {"score": float("inf"), "epoch": -1}
    if manager.latest_step() is not None:
        start_epoch = manager.latest_step()
        state = manager.restore(start_epoch, args=ocp.args.StandardRestore(state))
        if (run_dir / "best.json").exists():
            best = json.loads((run_dir / "best.json").read_text())
        log(f"resumed from epoch {start_epoch} (step {int(state['step'])})")
    _truncate_log(run_dir / "metrics.jsonl", start_epoch)
    state = jax.device_put(state, replicated)
    train_step = make_train_step(cfg._replace(init_from=None), total_steps, arrays)   # one program per recipe

    z_train, f_train = data.z[rows], data.f[rows]
    w_train = case_weights(data, rows, cfg.case_weight) if cfg.case_weight > 0 else None
    last_epoch = cfg.epochs if stop_after_epoch is None else min(cfg.epochs, stop_after_epoch)
    t_start = time.time()
    elapsed_before = _elapsed(run_dir)
    for epoch in range(start_epoch, last_epoch):
        perm = np.random.default_rng([cfg.seed, epoch]).permutation(n_samples)
        sums = {}
        t0 = time.time()
        bar = tqdm(range(steps_per_epoch), desc=f"epoch {epoch + 1}/{cfg.epochs}", disable=not progress,
                   leave=False)
        for b in bar:
            idx = perm[b * bs:(b + 1) * bs]
            r, k = idx // frames, idx % frames
            batch = Batch(z_train[r, k], f_train[r, k], z_train[r, k + 1], None if w_train is None else w_train[r])
            state, metrics = train_step(state, jax.device_put(batch, batch_sharding))
            for name, val in metrics.items():
                sums[name] = sums.get(name, 0.0) + val
        skipped = int(round(float(sums.pop("skipped"))))
        used = max(steps_per_epoch - skipped, 1)
        line = {"epoch": epoch + 1, "step": int(state["step"]), **{k: float(v) / used for k, v in sums.items()},
                "skipped": skipped, "epoch_s": time.time() - t0,
                "elapsed_s": elapsed_before + time.time() - t_start}
        done = epoch + 1 == last_epoch or (time_limit_s is not None and time.time() - t_start > time_limit_s)
        if val_rows is not None and ((epoch + 1) % cfg.eval_every == 0 or done):
            current = {**arrays, "weights": state["weights"]}
            pred = rollouts(model, current, jnp.asarray(data.z[val_rows, 0]), jnp.asarray(data.f[val_rows]))
            errs = np.nanmean(relative_errors(pred, data.z[val_rows], data.q0), axis=(0, 1))
            line.update({f"val_{v}": float(e) for v, e in zip(VARIABLES, errs)})
            score = float(errs[1] + errs[2] + errs[3])   # v + σ + u
            line["val_score"] = score
            if np.isfinite(score) and score < best["score"]:
                from tignn_jax import api

                best = {"score": score, "epoch": epoch + 1, **{f"val_{v}": float(e) for v, e in zip(VARIABLES, errs)}}
                params = to_params(model, model.stored(current), mesh, envelope, {**info, "best": best})
                api.save_model(params, run_dir / "best" / "model.npz")
                (run_dir / "best.json").write_text(json.dumps(best))
        with open(run_dir / "metrics.jsonl", "a") as fh:
            fh.write(json.dumps(line) + "\n")
        log(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in line.items()))
        if (epoch + 1) % cfg.ckpt_every == 0 or done:
            manager.save(epoch + 1, args=ocp.args.StandardSave(state), force=True)
        if done:
            break
    manager.wait_until_finished()
    manager.close()
    final = model.stored({**arrays, "weights": jax.device_get(state["weights"])})
    return to_params(model, final, mesh, envelope, {**info, "best": best})


def run(data_paths, config: TrainConfig, run_dir, progress: bool = True, split=("train", "val")) -> dict:
    """Train from a recipe (resumable) and write the selected model to ``run_dir``/model/model.npz: what
    ``tignn train --config`` calls.

    Args:
      data_paths: a data file or a list of data files on one mesh (their cases concatenated).
      config: the recipe.
      run_dir: the run's folder (see `train`).
      progress: show progress bars.
      split: (training split, validation split) as in `train`; without a validation split the last weights are
        written.

    Returns:
      The written model (`tignn_jax.api.load_model`).
    """
    from tignn_jax import api

    last = train(data_paths, config, run_dir, split=split, progress=progress)
    best, path = Path(run_dir) / "best" / "model.npz", Path(run_dir) / "model" / "model.npz"
    api.save_model(api.load_model(best) if best.exists() else last, path)
    return api.load_model(path)


def _parent(init_from, model: GenericGNN) -> dict:
    """The stored arrays, path and training time of the model a warm-started run begins from, checked against
    ``model``'s class and architecture."""
    from tignn_jax import api

    path = Path(init_from)
    if path.is_dir():
        path = path / "best" / "model.npz"
    if not path.exists():
        raise ValueError(f"init_from {str(init_from)!r}: no model file at {path}")
    params = api.load_model(path)
    if params["model"] != model:
        raise ValueError(f"init_from {str(init_from)!r}: architecture differs from the recipe's (parent, recipe): "
                         f"{params['model']!r}, {model!r}")
    run = path.parent.parent
    elapsed = _elapsed(run) if (run / "metrics.jsonl").exists() else float("nan")
    return {"path": str(path.resolve()), "stored": params["model"].stored(params["arrays"]), "elapsed_s": elapsed}


def _load(data_path) -> D.Dataset:
    if isinstance(data_path, D.Dataset):
        return data_path
    if isinstance(data_path, (list, tuple)):
        return D.concatenate(*(D.load(p) for p in data_path))
    return D.load(data_path)


def _describe(data_path):
    if isinstance(data_path, D.Dataset):
        return "a Dataset in memory"
    if isinstance(data_path, (list, tuple)):
        return [str(Path(p).resolve()) for p in data_path]
    return str(Path(data_path).resolve())


def _jsonable(split):
    return None if split is None else split if isinstance(split, str) else [int(s) for s in np.ravel(split)]


def _truncate_log(path: Path, epoch: int) -> None:
    """Drop the metric lines written after the checkpoint a run resumes from."""
    if not path.exists():
        return
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and json.loads(ln)["epoch"] <= epoch]
    path.write_text("".join(ln + "\n" for ln in lines))


def _elapsed(run_dir: Path) -> float:
    path = run_dir / "metrics.jsonl"
    if not path.exists() or not path.read_text().strip():
        return 0.0
    return json.loads(path.read_text().strip().splitlines()[-1])["elapsed_s"]
