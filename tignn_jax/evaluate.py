"""Rollout errors, degeneracy residuals and entropy production of a model on a data set.

Error measure (as in ``shared/data/README.md``): per snapshot, the relative L2 error
``sqrt(Σ (pred − true)² / Σ true²)`` over the nodes (all nodes, or only free ones) and the variable's
components, for q (position), v, σ (stress) and u = q − q0 (displacement); the rollout starts from the true
first state and runs on the true forces; statistics are over snapshots 1..T (t = 0 is the given state).
"""
from __future__ import annotations

import json
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax import api
from tignn_jax import data as D
from tignn_jax import model as M

VARIABLES = ("q", "v", "sigma", "u")
PUBLISHED_TEST = {"q": 4.14e-3, "v": 1.72e-2, "sigma": 9.51e-2, "u": 7.07e-2}


def variable(states, q0, name: str):
    """One of ``VARIABLES`` from states [..., N, 12]: q, v, sigma, or the displacement u = q − q0."""
    if name == "u":
        return states[..., :3] - q0
    return states[..., {"q": D.Q, "v": D.V, "sigma": D.SIGMA}[name]]


def relative_errors(pred, true, q0, mask=None, reference: str = "snapshot") -> np.ndarray:
    """Per-snapshot relative L2 errors [..., T+1, 4] (q, v, sigma, u) of states pred, true [..., T+1, N, 12].

    mask [N] bool selects nodes (None: all). reference "snapshot" (the published measure): each snapshot's
    error over that snapshot's true norm, so the t = 0 entry of u is NaN (its true value is zero); "peak":
    over the largest true norm of the case's snapshots, for cases whose state passes through zero (a fingertip
    that presses, holds and lets go: while it holds, v ≈ 0 and the per-snapshot v error is a ratio of
    round-off)."""
    if reference not in ("snapshot", "peak"):
        raise ValueError(f"reference must be 'snapshot' or 'peak', got {reference!r}")
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    if mask is not None:
        pred, true, q0 = pred[..., mask, :], true[..., mask, :], np.asarray(q0)[mask]
    out = []
    for name in VARIABLES:
        p, t = variable(pred, q0, name), variable(true, q0, name)
        num = np.sum((p - t) ** 2, axis=(-2, -1))
        den = np.sum(t ** 2, axis=(-2, -1))
        if reference == "peak":
            den = np.broadcast_to(den.max(axis=-1, keepdims=True), den.shape)
        with np.errstate(invalid="ignore", divide="ignore"):
            out.append(np.where(den > 0, np.sqrt(num / np.where(den > 0, den, 1.0)), np.nan))
    return np.stack(out, axis=-1)


def rollout_cases(params: dict, data: D.Dataset, rows) -> np.ndarray:
    """Predicted states [len(rows), T+1, N, 12] from each case's first state and forces."""
    config = M.ModelConfig(**params["config"])
    nt = jnp.asarray(data.node_type, jnp.int32)
    topo = _topology(params, config, data)
    return np.asarray(_rollout_many(params["weights"], config, params["norm"], jnp.asarray(data.z[rows, 0]),
                                    jnp.asarray(data.f[rows]), nt, topo))


def _topology(params: dict, config: M.ModelConfig, data: D.Dataset):
    """The model's own Topology when the data are on the model's mesh (same rest positions and edges), else one
    built from the data's mesh: a coarse model's clustering (~0.4 s on the bunny) is not redone per call."""
    mesh = params.get("mesh", {})
    same = ("topo" in params and {"q0", "senders", "receivers", "node_type"} <= set(mesh)
            and np.array_equal(mesh["q0"], np.asarray(data.q0, np.float32))   # the model stores float32
            and np.array_equal(mesh["senders"], data.edges[0]) and np.array_equal(mesh["receivers"], data.edges[1])
            and np.array_equal(mesh["node_type"], data.node_type))
    if same:
        return params["topo"]
    return M.model_topology(config, data.edges[0], data.edges[1], len(data.node_type), data.q0)


@partial(jax.jit, static_argnames="config")
def _rollout_many(weights, config, norm, z0, forces, node_type, topo):
    return jax.vmap(lambda a, b: api.rollout_states(weights, config, norm, a, b, node_type, topo))(z0, forces)


def split_errors(params: dict, data: D.Dataset, rows, pred=None) -> dict:
    """Errors of the rollouts of ``rows`` over snapshots 1..T: {"all": [C,T,4], "free": [C,T,4]} relative to
    each snapshot, and "peak" [C,T,4] (all nodes) relative to the case's largest true norm."""
    pred = rollout_cases(params, data, rows) if pred is None else pred
    true = data.z[rows]
    free = data.node_type == 0
    return {"all": relative_errors(pred, true, data.q0)[:, 1:],
            "free": relative_errors(pred, true, data.q0, free)[:, 1:],
            "peak": relative_errors(pred, true, data.q0, reference="peak")[:, 1:]}


def summarize(errors: dict) -> dict:
    """Mean and median over cases and snapshots, and the mean per rollout step, per variable and node set."""
    out = {}
    for nodes, e in errors.items():
        out[nodes] = {
            name: {"mean": float(np.nanmean(e[..., i])), "median": float(np.nanmedian(e[..., i])),
                   "per_step_mean": np.nanmean(e[..., i], axis=0).tolist()}
            for i, name in enumerate(VARIABLES)}
    return out


def structure_along_rollouts(params: dict, data: D.Dataset, rows, pred) -> dict:
    """Degeneracy residuals and entropy production at every predicted state (frames 0..T-1).

    Residuals are reported relative to the size of the step: ‖L∇S‖/‖dw‖ and ‖M∇E‖/‖dw‖ (whole graph); the
    dissipated part ∇Sᵀ M ∇S is ≥ 0 by construction, and dS/dt·Δt = ∇Sᵀ dw is ≥ 0 when L∇S = 0."""
    config = M.ModelConfig(**params["config"])
    nt = jnp.asarray(data.node_type, jnp.int32)
    topo = _topology(params, config, data)
    res = np.asarray(_structure_many(params["weights"], config, params["norm"], jnp.asarray(pred[:, :-1]),
                                     jnp.asarray(data.f[rows]), nt, topo))
    names = ("deg_l_rel", "deg_m_rel", "entropy_rate", "dissipation")
    out = {n: {"mean": float(res[..., i].mean()), "max": float(res[..., i].max()),
               "min": float(res[..., i].min())} for i, n in enumerate(names)}
    out["entropy_rate_negative_fraction"] = float(np.mean(res[..., 2] < 0))
    return out


@partial(jax.jit, static_argnames="config")
def _structure_many(weights, config, norm, states, forces, node_type, topo):
    def one(z, f):
        rt = M.rates(weights, config, norm, z, f, node_type, topo)
        size = jnp.linalg.norm(rt.dw) + 1e-12
        return jnp.stack([jnp.linalg.norm(rt.deg_l) / size, jnp.linalg.norm(rt.deg_m) / size,
                          rt.entropy_rate, rt.dissipation])

    # cases one after another (lax.map), frames vectorised: the per-node 12x12 operators and the second-order
    # passes of every state at once need ~0.5 GB per bunny case (71 cases: 35 GB, out of memory)
    return jax.lax.map(lambda sf: jax.vmap(one)(*sf), (states, forces))


def evaluate(params: dict, data: D.Dataset, splits=("train", "val", "test"), structure: bool = True) -> dict:
    """Errors (and structure diagnostics) per split; returns a JSON-ready dict and the raw error arrays."""
    report, raw = {}, {}
    for split in splits:
        rows = D.split_rows(data, split)
        pred = rollout_cases(params, data, rows)
        errs = split_errors(params, data, rows, pred)
        raw[split] = errs
        report[split] = summarize(errs)
        if structure:
            report[split]["structure"] = structure_along_rollouts(params, data, rows, pred)
    return report, raw


def box_plot(raw: dict, path: str | Path, splits=("train", "test"), nodes: str = "all") -> Path:
    """The paper's box plot: per variable, the per-snapshot relative errors of each split side by side."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    width = 0.8 / len(splits)
    for j, split in enumerate(splits):
        e = raw[split][nodes]
        data = [e[..., i].ravel()[np.isfinite(e[..., i].ravel())] for i in range(len(VARIABLES))]
        pos = np.arange(len(VARIABLES)) + (j - (len(splits) - 1) / 2) * width
        bp = ax.boxplot(data, positions=pos, widths=width * 0.9, patch_artist=True, showfliers=False)
        for b in bp["boxes"]:
            b.set_facecolor(f"C{j}")
        ax.plot([], [], color=f"C{j}", lw=6, label=split)
    ax.set_xticks(np.arange(len(VARIABLES)), ["q", "v", "σ", "u = q − q0"])
    ax.set_yscale("log")
    ax.set_ylabel("relative L2 error per snapshot")
    ax.set_title(f"rollout errors ({nodes} nodes)")
    ax.legend()
    return _save(fig, path, dpi=120)


def format_table(report: dict) -> str:
    """Markdown table of mean (median) errors per split and node set."""
    lines = ["| split | nodes | q | v | σ | u |", "|---|---|---|---|---|---|"]
    for split, rep in report.items():
        for nodes in ("all", "free", "peak"):
            if nodes not in rep:
                continue
            cells = [f"{rep[nodes][v]['mean']:.3e} ({rep[nodes][v]['median']:.2e})" for v in VARIABLES]
            lines.append(f"| {split} | {nodes} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(report: dict, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=1))
    return path


def plot_learning_curve(metrics_path: str | Path, path: str | Path) -> Path:
    """Training loss and validation rollout errors against wall-clock training time (from metrics.jsonl)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rec = [json.loads(x) for x in Path(metrics_path).read_text().splitlines() if x.strip()]
    t = np.array([r["elapsed_s"] for r in rec]) / 60
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    a.semilogy(t, [r["mse"] for r in rec], label="one-step MSE (normalised)")
    a.semilogy(t, [r["degeneracy"] for r in rec], label="degeneracy residual²")
    a.set_xlabel("training time (min)")
    a.legend()
    ev = [r for r in rec if "val_u" in r]
    te = np.array([r["elapsed_s"] for r in ev]) / 60
    for v in VARIABLES:
        b.semilogy(te, [r[f"val_{v}"] for r in ev], marker="o", ms=3, label=v)
    b.set_xlabel("training time (min)")
    b.set_ylabel("val rollout rel. L2 error (mean)")
    b.legend()
    return _save(fig, path, dpi=110)


def _save(fig, path, dpi):
    """Write a figure (creating the folder) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
