"""Training the GENERIC graph network on one-step transitions with noise injection.

A sample is a transition (z_k, f_k) → z_{k+1} of a training case. The loss is the mean squared error of the
predicted increment, per feature in units of the training increments' standard deviation (clamped nodes' q,v
excluded), plus ``deg_weight`` times the squared degeneracy residuals L∇S and M∇E (same units). Gaussian
noise of ``noise`` × increment std is added to the input state and the target increment is corrected for it,
so the model learns to pull a perturbed state back (as in the paper and MeshGraphNets).

The evaluation metric is a *relative* error per case, but the loss above is in global units, so cases with a
small response (a load near the clamp) weigh little in it. ``case_weight`` = p > 0 multiplies each case's loss
terms by (s̄ / s_c)^(2p) per variable, where s_c is the case's RMS displacement, velocity or stress and s̄ their
mean over the training cases (weights renormalised to mean 1): p = 1 makes the loss an average of relative
squared errors. A run can start from a trained model's weights (``init_from``, a warm restart with a fresh
schedule); its config.json records the parent and the parent's training time.

Batches of same-mesh graphs are vmapped, sharded along the batch axis over all local devices with
``jax.sharding`` (parameters replicated; XLA inserts the gradient all-reduce). Orbax checkpoints at epoch
boundaries hold the step, weights and optimiser state; batch order and noise are functions of (seed, epoch,
step), so a resumed run reproduces the uninterrupted one.
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

from tignn_jax import api
from tignn_jax import data as D
from tignn_jax import evaluate as EV
from tignn_jax import framesolve as FS
from tignn_jax import graph as G
from tignn_jax import model as M


class TrainConfig(NamedTuple):
    """Architecture (see ModelConfig) and optimisation settings. lr peaks after ``warmup_steps`` and decays
    by cosine to ``lr_end`` at the end of ``epochs``; ``noise`` is the input-noise std as a fraction of the
    per-feature increment std; ``eval_every``/``ckpt_every`` are in epochs. ``unroll`` = K > 1 trains on K
    consecutive steps from each sampled state: step j+1 starts from the model's own prediction of step j (held
    constant in the gradient, the "pushforward" trick), so the loss sees the states a rollout visits.
    ``bptt``: the gradient flows through the K unrolled steps instead (backpropagation through time; each step
    is rematerialised in the backward pass, so memory grows with K only by one state per step).
    ``snapshot_loss``: each unrolled step's loss is the squared relative error of u, v and σ over the true
    snapshot's norm, as ``evaluate.relative_errors`` measures a rollout ("snapshot" reference; a snapshot whose
    true squared norm is below 1e-3 of the training split's mean is divided by that floor instead).
    ``v_weight``: the squared errors of the velocity features count v_weight times in the loss's mean; the
    reported MSEs stay unweighted. ``val_reference``: how the validation rollout errors (and the score that
    selects the best model) are made relative, "snapshot" (the published measure) or "peak" (over each case's
    largest true norm: for data whose velocities pass through zero, see ``evaluate.relative_errors``).
    ``residual_scale`` (with ``linear_prior``): the network's output scale in the velocity and stress rows is
    the spread of the prior's residual (`framesolve.residual`, the increment with which the prior's step
    reproduces the data) instead of the state's increments. On a stiff mesh that residual is a stiff force
    (the bunny: 2000× the velocity increments, growing with the deformation), so pair it with a small
    ``correction_scale``.
    ``stability_weight`` > 0 adds the rest-state stability term (``stability_term``): the unloaded body at rest
    must stay at rest (squared drift of one step, in increment stds) and the step's linearisation there must
    not amplify: the growth ‖J x‖ of a probe x that follows J's dominant mode by one power iteration per
    training step is penalised above ``stability_bound`` (per step); ``stability_eps`` is the probe's
    finite-difference size (rms per state entry, in state stds). ``stability_data``: a second probe does the
    same at each batch's first input state under its force (the true, damped step contracts there too; one
    iteration per changing state does not converge to its dominant mode, so prefer ``stability_anchors``).
    ``stability_anchors`` = A > 0: A fixed training states (frames T/2 and T−1 of A/2 training cases spread over
    the split, under their forces), each with its own persistent probe; every training step iterates the
    rest probe and one anchor's in turn, so each anchor's power iteration advances once per A steps.
    ``sigma_noise``: the stress features' input-noise level (same units as ``noise``, which then applies to q
    and v only). The target stays the true next state, so a larger level teaches the step to pull a stored
    stress that has drifted from the one the positions imply back to it, instead of carrying the drift on."""
    hidden: int = 24
    mlp_layers: int = 2
    passes: int = 3
    activation: str = "silu"
    edge_velocity: bool = True
    edge_strain: bool = False
    node_position: bool = False
    exact_degeneracy: bool = False
    global_pool: bool = False
    kinematic_prior: bool = False
    edge_traction: bool = False
    force_port: bool = False
    load_context: bool = False
    coarse_nodes: int = 0
    coarse_passes: int = 2
    coarse_mixing: bool = False
    rest_equilibrium: bool = False
    node_embedding: int = 0
    elastic_port: bool = False
    port_hops: int = 0
    frame_solve: bool = False
    linear_prior: bool = False
    correction_scale: float = 0.01
    integrator: str = "euler"
    static_l: bool = False
    convex: bool = False
    free_energy: bool = False
    dynamic_l: bool = False
    relaxation: bool = False
    substeps: int = 1
    residual_scale: bool = False
    lr: float = 3e-3
    lr_end: float = 2e-5
    weight_decay: float = 1e-6
    batch_size: int = 2
    epochs: int = 30
    warmup_steps: int = 100
    noise: float = 0.2
    deg_weight: float = 1.0
    case_weight: float = 0.0
    unroll: int = 1
    bptt: bool = False
    snapshot_loss: bool = False
    v_weight: float = 1.0
    seed: int = 0
    eval_every: int = 2
    ckpt_every: int = 2
    val_reference: str = "snapshot"
    stability_weight: float = 0.0
    stability_bound: float = 0.9
    stability_eps: float = 1e-3
    stability_data: bool = False
    stability_anchors: int = 0
    sigma_noise: float | None = None

    @property
    def model(self) -> M.ModelConfig:
        return M.ModelConfig(**{k: getattr(self, k) for k in M.ModelConfig._fields})


CONFIGS = {
    "tiny": TrainConfig(hidden=8, passes=1, batch_size=4, epochs=2, warmup_steps=2, eval_every=1, ckpt_every=1),
    "beam": TrainConfig(),
    # 1330 nodes / 14 054 edges: 3.5x the beam's edges, so a narrower network to fit the 11 ms step budget
    "bunny": TrainConfig(hidden=16, batch_size=4, epochs=10, lr=2e-3, warmup_steps=50, ckpt_every=1,
                         node_position=True),
}


class Batch(NamedTuple):
    """Stacked transitions: z, z_next [B,N,12]; f [B,N,3]; optional per-sample feature weights w [B,12].
    For unrolled training f [B,K,N,3] and z_next [B,K,N,12] hold the K steps after z; ``rel`` [B,K,3] are the
    inverse true squared norms of u, v and σ at those snapshots (``snapshot_loss``)."""
    z: jax.Array
    f: jax.Array
    z_next: jax.Array
    w: jax.Array | None = None
    rel: jax.Array | None = None


GROUPS = np.repeat(np.eye(3, dtype=np.float32), [3, 3, 6], axis=0)   # [12, 3]: state feature -> u, v, σ


def snapshot_weights(data: D.Dataset, rows, floor: float = 1e-3) -> np.ndarray:
    """[len(rows), T+1, 3]: 1 / (squared L2 norm over all nodes of u = q − q0, v, σ) per case and snapshot, each
    norm floored at ``floor`` × its mean over the cases' snapshots 1..T."""
    z, q0 = np.asarray(data.z[np.asarray(rows)], np.float64), np.asarray(data.q0, np.float64)
    e = np.stack([np.sum(EV.variable(z, q0, name) ** 2, axis=(-2, -1)) for name in ("u", "v", "sigma")], axis=-1)
    e = np.maximum(e, floor * e[:, 1:].mean(axis=(0, 1)) + 1e-30)
    return (1.0 / e).astype(np.float32)


def case_weights(data: D.Dataset, rows, power: float) -> np.ndarray:
    """Loss weights [len(rows), 12] per case and state feature: (mean scale / case scale)^(2 power), mean 1.

    Scales per case: RMS over frames 1.. of the free nodes' displacement q - q0 (for the q features) and
    velocity, and of all nodes' stress."""
    rows = np.asarray(rows)
    if power < 0 or not np.isfinite(power):
        raise ValueError(f"case_weight must be a finite number >= 0, got {power}")
    if power == 0:
        return np.ones((len(rows), M.STATE_DIM), np.float32)
    z = data.z[rows, 1:].astype(np.float64)
    free = data.node_type == 0
    scales = np.stack([np.sqrt(np.mean((z[:, :, free, :3] - data.q0[free]) ** 2, axis=(1, 2, 3))),
                       np.sqrt(np.mean(z[:, :, free, 3:6] ** 2, axis=(1, 2, 3))),
                       np.sqrt(np.mean(z[..., 6:] ** 2, axis=(1, 2, 3)))], axis=1)  # [C, 3]
    scales = np.maximum(scales, 1e-3 * scales.max(axis=0, keepdims=True) + 1e-30)
    w = (scales.mean(axis=0) / scales) ** (2 * power)
    w = w / w.mean(axis=0)
    return np.repeat(w, [3, 3, 6], axis=1).astype(np.float32)


def make_optimizer(cfg: TrainConfig, total_steps: int) -> optax.GradientTransformation:
    schedule = optax.warmup_cosine_decay_schedule(
        init_value=cfg.lr * 0.01, peak_value=cfg.lr, warmup_steps=min(cfg.warmup_steps, max(total_steps - 1, 1)),
        decay_steps=max(total_steps, 2), end_value=cfg.lr_end)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=cfg.weight_decay))


def loss_fn(weights, batch: Batch, key, norm, cfg: TrainConfig, node_type, topo):
    """Scalar loss and a dict of metrics for a batch of transitions on one mesh (K unrolled steps when
    ``batch.f`` has a step axis: each step's error is measured against the true next state from the model's
    own current state, and the losses are averaged over the steps)."""
    c, s = norm["dz_std"], M.state_scale(norm)
    norm = M.with_rest(weights, cfg.model, norm, node_type, topo)   # once per batch, not per sample
    keep = (~M.prescribed(node_type)).astype(batch.z.dtype)
    f_seq, z_seq = (batch.f, batch.z_next) if batch.f.ndim == 4 else (batch.f[:, None], batch.z_next[:, None])
    level = jnp.full(M.STATE_DIM, cfg.noise, batch.z.dtype)
    if cfg.sigma_noise is not None:   # the stress features' own level (see TrainConfig)
        level = level.at[6:].set(cfg.sigma_noise)
    z_in = batch.z + jax.random.normal(key, batch.z.shape, batch.z.dtype) * (level * c) * keep
    to_unit = s / c
    denom = batch.z.shape[0] * jnp.sum(keep, axis=0)
    n_steps = f_seq.shape[1]
    if cfg.snapshot_loss and batch.rel is None:
        raise ValueError("snapshot_loss needs the batch's inverse snapshot norms (Batch.rel, see snapshot_weights)")
    rel_seq = batch.rel if batch.rel is not None else jnp.zeros(f_seq.shape[:2] + (3,), batch.z.dtype)

    # bptt: a step's increment is bounded at 100 increment stds per feature before it feeds the next step, so
    # a rollout that blows up gives a large, finite loss (bounded entries pass no gradient)
    lim = 100.0 / to_unit
    dw_bounded = (lambda dw: jnp.clip(dw, -lim, lim)) if cfg.bptt else (lambda dw: dw)

    # frame_solve: the step is z + W⁻¹(dw s); its error is measured on the state, over the state increments'
    # scale (the network's output scale s is that of W Δz, whose stiff components the solve all but removes)
    step_of = jax.vmap(lambda dw, z, f: M.increment(cfg.model, norm, dw, z, f, node_type, topo))
    state_unit = norm["fs_dz_std"] if cfg.frame_solve else c

    def limit_of(f):   # relaxation: each sample's γ under its own force
        if not cfg.model.relaxation:
            return None
        one = lambda z, dw, stages, f_: M.relaxation_limit(weights, cfg.model, norm, f_, node_type, topo)(
            z, dw, stages)
        return lambda z, dw, stages: jax.vmap(one)(z, dw, stages, f)[:, None, None]

    def one_step(z_in, xs):
        f_j, z_true, rel_j = xs
        rates_of = jax.vmap(lambda z, f: M.rates(weights, cfg.model, norm, z, f, node_type, topo))
        # the step the model will be used with: every Runge-Kutta stage's rates, each stage's shift bounded
        # like the step (bptt); the degeneracy residuals of all stages enter the loss
        dw, stages = M.runge_kutta(cfg.model.integrator, lambda x: rates_of(x, f_j), z_in, s, dw_bounded,
                                   cfg.model.substeps, limit_of(f_j))
        rt = stages[0]._replace(dw=dw, deg_l=jnp.concatenate([o.deg_l for o in stages], axis=1),
                                deg_m=jnp.concatenate([o.deg_m for o in stages], axis=1))
        dw = dw_bounded(rt.dw)
        z_next = z_in + (step_of(dw, z_in, f_j) if cfg.frame_solve else dw * s)
        sq = ((z_next - z_true) / state_unit) ** 2 * keep
        if batch.w is not None:
            sq = sq * batch.w[:, None, :]
        err2 = jnp.sum((z_next - z_true) ** 2 * keep, axis=1) @ GROUPS      # [B, 3] squared state errors
        rel = jnp.mean(err2 * rel_j, axis=0)                                   # [3] mean squared relative error
        deg = jnp.mean((rt.deg_l * to_unit) ** 2 + (rt.deg_m * to_unit) ** 2)
        if not cfg.bptt:
            z_next = jax.lax.stop_gradient(z_next)
        return z_next, (jnp.sum(sq, axis=(0, 1)), deg, rel)

    body = jax.checkpoint(one_step) if cfg.bptt else one_step
    _, (sq_steps, deg_steps, rel_steps) = jax.lax.scan(
        body, z_in, (jnp.swapaxes(f_seq, 0, 1), jnp.swapaxes(z_seq, 0, 1), jnp.swapaxes(rel_seq, 0, 1)))
    sq_sum, deg_sum, rel_mean = jnp.sum(sq_steps, axis=0), jnp.sum(deg_steps), jnp.mean(rel_steps, axis=0)
    per_feature = sq_sum / (denom * n_steps)
    data_loss = jnp.sum(sq_sum) / (jnp.sum(denom) * n_steps)
    deg = deg_sum / n_steps
    fw = jnp.ones(M.STATE_DIM, sq_sum.dtype).at[3:6].set(cfg.v_weight)   # v counts v_weight times (1: data_loss)
    if cfg.snapshot_loss:
        loss = jnp.mean(rel_mean) + cfg.deg_weight * deg
    else:
        loss = jnp.sum(sq_sum * fw) / (jnp.sum(denom * fw) * n_steps) + cfg.deg_weight * deg
    metrics = {"loss": loss, "mse": data_loss, "degeneracy": deg, "mse_q": per_feature[:3].mean(),
               "mse_v": per_feature[3:6].mean(), "mse_sigma": per_feature[6:].mean()}
    if batch.rel is not None:
        metrics.update(rel2_u=rel_mean[0], rel2_v=rel_mean[1], rel2_sigma=rel_mean[2])
    return loss, metrics


def stability_term(weights, probes, norm, cfg: TrainConfig, node_type, topo, z_anchor, f_anchor):
    """(drift, growth [A], next probes [A,N,12]) of the model's step at A anchor states; anchor 0 is the rest
    state under zero force.

    drift: the mean squared one-step change of anchor 0 in increment stds (the truth is 0: an unloaded body at
    rest stays there; clamped nodes' q, v excluded). growth: ‖J_a x_a‖ for each unit probe x_a [N,12] in state
    stds, J_a the step's Jacobian at anchor a restricted to the evolved entries (clamped q, v are prescribed),
    by a finite difference of size ``stability_eps`` per entry (the step has custom VJPs, so no forward-mode
    JVP). A probe renormalised to J x each training step is a power
    iteration: its growth tends to J's largest eigenvalue modulus, the factor by which a small disturbance of
    the anchor state grows per step (> 1: the learned step is unstable there; the true, damped one is not)."""
    norm = M.with_rest(weights, cfg.model, norm, node_type, topo)
    std = norm["z_std"]
    # clamped nodes' q, v are prescribed, not state: a disturbance there stays as it is (eigenvalue 1 whatever
    # the network), so the probes live on the other entries
    keep = (~M.prescribed(node_type)).astype(probes.dtype)
    probes = probes * keep
    h = cfg.stability_eps * np.sqrt(probes[0].size)
    step = jax.vmap(lambda z, f: M.step_state(weights, cfg.model, norm, z, f, node_type, topo))
    nxt = step(jnp.concatenate([z_anchor, z_anchor + h * probes * std]), jnp.concatenate([f_anchor, f_anchor]))
    base, moved = jnp.split(nxt, 2)
    drift = jnp.sum(((base[0] - z_anchor[0]) / norm["dz_std"]) ** 2 * keep) / jnp.sum(keep)
    jx = (moved - base) / (h * std) * keep
    growth = jnp.sqrt(jnp.sum(jx ** 2, axis=(1, 2)))
    return drift, growth, jax.lax.stop_gradient(jx / jnp.maximum(growth, 1e-12)[:, None, None])


def stability_anchor_states(data: D.Dataset, rows, count: int):
    """(z [A,N,12], f [A,N,3]): frames T/2 and T−1 of ``count``/2 training cases spread evenly over ``rows``."""
    if count < 2 or count % 2:
        raise ValueError(f"stability_anchors must be an even number >= 2, got {count}")
    rows = np.asarray(rows)
    if count // 2 > len(rows):
        raise ValueError(f"stability_anchors={count} needs {count // 2} training cases, the split has {len(rows)}")
    cases = rows[np.linspace(0, len(rows) - 1, count // 2).round().astype(int)]
    frames = data.f.shape[1]
    pick = [(r, k) for r in cases for k in (frames // 2, frames - 1)]
    return (jnp.asarray(np.stack([data.z[r, k] for r, k in pick]), jnp.float32),
            jnp.asarray(np.stack([data.f[r, k] for r, k in pick]), jnp.float32))


def initial_probes(seed: int, n_nodes: int, count: int = 1) -> jax.Array:
    """[count,N,12] unit random starts for ``stability_term``'s power iterations."""
    x = jax.random.normal(jax.random.fold_in(jax.random.PRNGKey(seed), 1), (count, n_nodes, M.STATE_DIM))
    return x / jnp.linalg.norm(x, axis=(1, 2), keepdims=True)


def make_train_step(cfg: TrainConfig, total_steps: int, norm, node_type, topo, anchors=None):
    """``(state, batch) -> (state, metrics)``, jit-compiled once per (cfg, total_steps, shapes); the noise
    key is derived from the step count. ``anchors``: the stability term's fixed states (``stability_anchors``
    of ``stability_states``; with ``stability_weight`` > 0 at least the rest state)."""
    return lambda state, batch: _train_step(state, batch, norm, node_type, topo, anchors, cfg=cfg,
                                            total_steps=total_steps)


def stability_states(data: D.Dataset, rows, cfg: TrainConfig) -> dict | None:
    """The stability term's fixed states (None without it): ``rest`` [N,12] and, with ``stability_anchors``,
    ``z`` [A,N,12] and ``f`` [A,N,3] (``stability_anchor_states``)."""
    if (cfg.stability_data or cfg.stability_anchors) and cfg.stability_weight <= 0:
        raise ValueError(f"stability_data / stability_anchors={cfg.stability_anchors} need stability_weight > 0, "
                         f"got {cfg.stability_weight}")
    if cfg.stability_weight <= 0:
        return None
    if cfg.stability_data and cfg.stability_anchors:
        raise ValueError("stability_data and stability_anchors are alternatives: set one")
    states = {"rest": jnp.asarray(G.rest_state(data.q0))}
    if cfg.stability_anchors:
        states.update(zip(("z", "f"), stability_anchor_states(data, rows, cfg.stability_anchors)))
    return states


@partial(jax.jit, static_argnames=("cfg", "total_steps"))
def _train_step(state, batch, norm, node_type, topo, anchors, cfg, total_steps):
    optimizer = make_optimizer(cfg, total_steps)
    key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), state["step"])

    def total(weights):
        loss, metrics = loss_fn(weights, batch, key, norm, cfg, node_type, topo)
        if cfg.stability_weight <= 0:
            return loss, (metrics, None)
        rest = anchors["rest"]
        z_a, f_a = rest[None], jnp.zeros((1, rest.shape[0], 3), rest.dtype)
        probes, slots = state["probe"], jnp.arange(state["probe"].shape[0])
        if cfg.stability_data:   # the batch's first (noise-free) input state under its force
            f_first = batch.f[0, 0] if batch.f.ndim == 4 else batch.f[0]
            z_a, f_a = jnp.concatenate([z_a, batch.z[:1]]), jnp.concatenate([f_a, f_first[None]])
        if cfg.stability_anchors:   # the rest probe and anchor (step mod A), in turn
            a = state["step"] % cfg.stability_anchors
            z_a = jnp.concatenate([z_a, anchors["z"][a][None]])
            f_a = jnp.concatenate([f_a, anchors["f"][a][None]])
            slots = jnp.stack([0, 1 + a])
            probes = probes[slots]
        drift, growth, probe = stability_term(weights, probes, norm, cfg, node_type, topo, z_a, f_a)
        probe = state["probe"].at[slots].set(probe)
        loss = loss + cfg.stability_weight * (drift + jnp.sum(jax.nn.relu(growth - cfg.stability_bound) ** 2))
        extra = {"rest_drift": drift, "rest_growth": growth[0]}
        if cfg.stability_data or cfg.stability_anchors:
            extra["data_growth"] = growth[1]
        return loss, ({**metrics, "loss": loss, **extra}, probe)

    (_, (metrics, probe)), grads = jax.value_and_grad(total, has_aux=True)(state["weights"])
    updates, opt_state = optimizer.update(grads, state["opt_state"], state["weights"])
    weights = optax.apply_updates(state["weights"], updates)
    # a batch whose loss or gradient is not finite (an unrolled rollout that blew up) leaves the weights and the
    # optimiser as they were; its metrics count as 0 and it is reported in "skipped"
    finite = jnp.isfinite(metrics["loss"]) & jnp.all(jnp.array([jnp.all(jnp.isfinite(g))
                                                                for g in jax.tree.leaves(grads)]))
    keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, old)
    weights, opt_state = keep(weights, state["weights"]), keep(opt_state, state["opt_state"])
    metrics = {k: jnp.where(finite, v, 0.0) for k, v in metrics.items()}
    metrics["skipped"] = 1.0 - finite.astype(jnp.float32)
    new = {"step": state["step"] + 1, "weights": weights, "opt_state": opt_state}
    if probe is not None:
        new["probe"] = jnp.where(jnp.all(jnp.isfinite(probe)), probe, state["probe"])
    return new, metrics


def data_mesh(devices=None) -> Mesh:
    """A 1-D device mesh with axis "data" over the given (default: all local) devices."""
    devices = jax.local_devices() if devices is None else devices
    return Mesh(np.array(devices), ("data",))


def train(data: D.Dataset, cfg: TrainConfig, run_dir: str | Path, train_split="train", val_split="val",
          stop_after_epoch: int | None = None, time_limit_s: float | None = None, devices=None,
          progress: bool = True, log=print, init_from: str | Path | None = None, frame_ops=None) -> dict:
    """Train (or resume from ``run_dir``'s latest checkpoint) and return the final model params.

    Writes ``run_dir``/metrics.jsonl (one line per epoch), checkpoints/ (orbax), best/model.npz (lowest
    validation score = mean rollout error of v + sigma + u over the val split) and config.json.
    ``stop_after_epoch``/``time_limit_s`` end the run early at an epoch boundary (with a checkpoint), as an
    interruption would; the schedule still spans ``cfg.epochs``. ``init_from`` (a model.npz or a run folder
    with best/model.npz) starts from that model's weights and normalisation instead of a random draw and the
    data's statistics; its architecture must match ``cfg`` (up to the ``WEIGHT_FREE`` options, e.g. a model
    fine-tuned into ``exact_degeneracy``). ``frame_ops``: the `fem.implicit.RestLinearization` of the data's
    scene, needed by ``frame_solve`` (`framesolve.operators_from_file`; a warm start reuses its parent's)."""
    import orbax.checkpoint as ocp
    from tqdm import tqdm

    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    parent = _parent(init_from, cfg) if init_from is not None else None
    record_cfg = cfg._asdict()
    if parent is not None:
        record_cfg.update(init_from=parent["path"], init_elapsed_s=parent["elapsed_s"])
    (run_dir / "config.json").write_text(json.dumps(record_cfg, indent=1))
    rows = D.split_rows(data, train_split)
    val_rows = D.split_rows(data, val_split) if val_split else None
    if cfg.residual_scale and not cfg.linear_prior:
        raise ValueError("residual_scale scales a linear_prior model's correction: set linear_prior=true too")
    M.check_integrator(cfg.model)
    if cfg.linear_prior and not cfg.frame_solve:
        raise ValueError("linear_prior needs frame_solve (forward Euler on the stiff rest dynamics is unstable)")
    if cfg.frame_solve:
        if frame_ops is None and (parent is None or "fs_k" not in parent["norm"]):
            raise ValueError("frame_solve needs the rest linearisation of the data's scene: pass "
                             "frame_ops=framesolve.operators_from_file(data_path)")
        ops = FS.norm_entries(frame_ops) if frame_ops is not None else {k: parent["norm"][k] for k in FS.KEYS}
        ops["dt"] = np.array([data.dt], np.float32)
        # the network's output scale: without the prior it must produce all of W Δz (whose stiff components are
        # orders of magnitude above the state's increments); with it, only a correction of the state's size
        # residual_scale: the velocity and stress rows at the spread of what the prior misses (the increment with
        # which its step reproduces the data, `framesolve.residual`: in the velocity rows a stiff force, orders
        # of magnitude above the state's increments), the position rows at the state's (the residual is ~0 there)
        if cfg.residual_scale:   # (checked above: with linear_prior)
            pseudo = FS.residuals(ops, data.z[rows], data.f[rows], data.node_type, data.q0)
        else:
            pseudo = None if cfg.linear_prior else FS.increments(ops, data.z[rows], data.node_type)
        norm_np = D.normalization(data, rows, increments=pseudo)
        norm_np.update({k: np.asarray(v, np.float32) for k, v in ops.items()})
        norm_np["fs_dz_std"] = D.normalization(data, rows)["dz_std"]   # the state increments' scale (the loss's)
        if cfg.residual_scale:
            norm_np["dz_std"][:3] = norm_np["fs_dz_std"][:3]
    else:
        norm_np = D.normalization(data, rows)
    if parent is not None:   # the parent's scales are part of the function its weights compute: keep them
        norm_np.update(parent["norm"])
    if cfg.frame_solve:
        norm_np = FS.with_inverse(norm_np, data.node_type)
    norm = {k: jnp.asarray(v) for k, v in norm_np.items()}
    node_type = jnp.asarray(data.node_type, jnp.int32)
    topo = M.model_topology(cfg.model, data.edges[0], data.edges[1], len(data.node_type), data.q0)
    frames = data.f.shape[1]
    if cfg.val_reference not in ("snapshot", "peak"):
        raise ValueError(f"val_reference must be 'snapshot' or 'peak', got {cfg.val_reference!r}")
    unroll = int(cfg.unroll)
    if not 1 <= unroll <= frames:
        raise ValueError(f"unroll must be between 1 and the {frames} frames of a case, got {cfg.unroll}")
    starts = frames - unroll + 1   # start frames per case
    n_samples = len(rows) * starts
    bs = cfg.batch_size
    steps_per_epoch = n_samples // bs
    if steps_per_epoch == 0:
        raise ValueError(f"batch_size {bs} exceeds the {n_samples} training transitions")
    total_steps = cfg.epochs * steps_per_epoch
    optimizer = make_optimizer(cfg, total_steps)
    anchors = stability_states(data, rows, cfg)

    mesh = data_mesh(devices)
    if bs % mesh.size:
        raise ValueError(f"batch_size {bs} is not divisible by the {mesh.size} devices")
    batch_sharding = NamedSharding(mesh, P("data"))
    replicated = NamedSharding(mesh, P())

    weights = M.init_weights(jax.random.PRNGKey(cfg.seed), cfg.model, norm, jnp.asarray(data.z[rows[0], 0]),
                             jnp.asarray(data.f[rows[0], 0]), node_type, topo)
    if parent is not None:
        weights = {**weights, **jax.tree.map(lambda a, b: jnp.asarray(b, a.dtype),
                                             {k: weights[k] for k in parent["weights"]}, parent["weights"])}
    state = {"step": jnp.zeros((), jnp.int32), "weights": weights, "opt_state": optimizer.init(weights)}
    if anchors is not None:   # the power iterations' probes are part of the state (a resume reproduces them)
        n_probes = 1 + int(cfg.stability_data) + int(cfg.stability_anchors)
        state["probe"] = initial_probes(cfg.seed, len(data.node_type), n_probes)
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
    train_step = make_train_step(cfg, total_steps, norm, node_type, topo, anchors)

    z_train, f_train = data.z[rows], data.f[rows]
    w_train = case_weights(data, rows, cfg.case_weight) if cfg.case_weight > 0 else None
    rel_train = snapshot_weights(data, rows) if cfg.snapshot_loss else None
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
            r, k = idx // starts, idx % starts
            ahead = k[:, None] + np.arange(unroll)[None, :]   # [B, K] frames of the unrolled steps
            batch = Batch(z_train[r, k], f_train[r[:, None], ahead], z_train[r[:, None], ahead + 1],
                          None if w_train is None else w_train[r],
                          None if rel_train is None else rel_train[r[:, None], ahead + 1])
            batch = jax.device_put(batch, batch_sharding)
            state, metrics = train_step(state, batch)
            for name, val in metrics.items():
                sums[name] = sums.get(name, 0.0) + val
        skipped = int(round(float(sums.pop("skipped"))))
        used = max(steps_per_epoch - skipped, 1)
        record = {"epoch": epoch + 1, "step": int(state["step"]),
                  **{k: float(v) / used for k, v in sums.items()}, "skipped": skipped,
                  "epoch_s": time.time() - t0, "elapsed_s": elapsed_before + time.time() - t_start}
        done = epoch + 1 == last_epoch or (time_limit_s is not None and time.time() - t_start > time_limit_s)
        if val_rows is not None and ((epoch + 1) % cfg.eval_every == 0 or done):
            params = api.make_params(cfg.model, norm_np, state["weights"], data.q0, data.edges, data.node_type)
            errs = EV.summarize(EV.split_errors(params, data, val_rows))[
                "peak" if cfg.val_reference == "peak" else "all"]
            record.update({f"val_{v}": errs[v]["mean"] for v in EV.VARIABLES})
            score = errs["v"]["mean"] + errs["sigma"]["mean"] + errs["u"]["mean"]
            record["val_score"] = score
            if np.isfinite(score) and score < best["score"]:
                best = {"score": score, "epoch": epoch + 1, **{f"val_{v}": errs[v]["mean"] for v in EV.VARIABLES}}
                api.save_model(params, run_dir / "best" / "model.npz",
                               info={"train_config": cfg._asdict(), "best": best})
                (run_dir / "best.json").write_text(json.dumps(best))
        with open(run_dir / "metrics.jsonl", "a") as fh:
            fh.write(json.dumps(record) + "\n")
        log(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in record.items()))
        if (epoch + 1) % cfg.ckpt_every == 0 or done:
            manager.save(epoch + 1, args=ocp.args.StandardSave(state), force=True)
        if done:
            break
    manager.wait_until_finished()
    manager.close()
    return api.make_params(cfg.model, norm_np, jax.device_get(state["weights"]), data.q0, data.edges,
                           data.node_type)


# model options that change how the weights are used but not their shapes: a warm start may switch them
WEIGHT_FREE = ("exact_degeneracy", "kinematic_prior", "rest_equilibrium", "correction_scale", "integrator",
               "static_l", "relaxation", "substeps")
# options a warm start may switch on: the parent's weights are kept and the ones the option adds start at their
# initialisation (dynamic_l's gates at zero: the parent's function)
ADDS_WEIGHTS = ("dynamic_l",)


def _parent(init_from, cfg: TrainConfig) -> dict:
    """Weights and normalisation of the model a warm-started run begins from, checked against ``cfg``'s
    architecture (every ModelConfig field but those in ``WEIGHT_FREE`` must agree, and those in
    ``ADDS_WEIGHTS`` may be on where the parent's are off)."""
    path = Path(init_from)
    if path.is_dir():
        path = path / "best" / "model.npz"
    if not path.exists():
        raise ValueError(f"init_from {str(init_from)!r}: no model file at {path}")
    params = api.load_model(path)
    mine = {k: v for k, v in cfg.model._asdict().items() if k not in WEIGHT_FREE}
    theirs = {k: params["config"].get(k, M.ModelConfig._field_defaults[k]) for k in mine}
    theirs.update({k: mine[k] for k in ADDS_WEIGHTS if mine[k] and not theirs[k]})
    if theirs != mine:
        diff = {k: (theirs[k], mine[k]) for k in mine if theirs[k] != mine[k]}
        raise ValueError(f"init_from {str(init_from)!r}: architecture differs from the config (parent, config): {diff}")
    run = path.parent.parent
    elapsed = _elapsed(run) if (run / "metrics.jsonl").exists() else float("nan")
    return {"path": str(path.resolve()), "weights": params["weights"], "elapsed_s": elapsed,
            "norm": {k: np.asarray(v) for k, v in params["norm"].items()}}


def _truncate_log(path: Path, epoch: int) -> None:
    """Drop metric lines written after the checkpoint a run resumes from."""
    if not path.exists():
        return
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and json.loads(ln)["epoch"] <= epoch]
    path.write_text("".join(ln + "\n" for ln in lines))


def _elapsed(run_dir: Path) -> float:
    path = run_dir / "metrics.jsonl"
    if not path.exists() or not path.read_text().strip():
        return 0.0
    return json.loads(path.read_text().strip().splitlines()[-1])["elapsed_s"]
