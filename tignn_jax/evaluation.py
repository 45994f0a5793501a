"""Rollout errors and structure diagnostics of a model on a data set.

Error measure (as in ``shared/data/README.md``): per snapshot, the relative L2 error
``sqrt(Σ (pred − true)² / Σ true²)`` over the nodes (all nodes, or only free ones) and the variable's
components, for q (position), v, σ (stress) and u = q − q0 (displacement); the rollout starts from the true
first state and runs on the true forces; statistics are over snapshots 1..T (t = 0 is the given state).
"""
from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax import api
from tignn_jax import data as D

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
    """Predicted states [len(rows), T+1, N, 12] of the cases ``rows`` from each case's first state and forces.

    Raises:
      ValueError: the data are on another mesh than the model.
    """
    check_mesh(params, data)
    model, arrays, n = params["model"], params["arrays"], len(data.node_type)
    return np.stack([np.asarray(api._rollout(model, n, arrays, jnp.asarray(data.z[r, 0]), jnp.asarray(data.f[r])))
                     for r in np.atleast_1d(rows)])


def check_mesh(params: dict, data: D.Dataset) -> None:
    """ValueError unless the data set's mesh (rest positions, edges, clamps) is the model's."""
    mesh = params["mesh"]
    same = (np.shape(mesh["q0"]) == np.shape(data.q0)
            and np.allclose(mesh["q0"], data.q0, atol=1e-5 * max(np.abs(data.q0).max(), 1e-30))
            and np.array_equal(mesh["senders"], data.edges[0]) and np.array_equal(mesh["receivers"], data.edges[1])
            and np.array_equal(mesh["node_type"], data.node_type))
    if not same:
        raise ValueError(f"the data ({len(data.q0)} nodes) are on another mesh than the model "
                         f"({len(mesh['q0'])} nodes): nodes, edges or clamps differ")


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
    """The model class's structure diagnostics (its ``diagnostics(arrays, z, f, z_next)``: e.g. the
    degeneracy residuals and entropy production of a GENERIC network, the dissipation of a linear model) at every
    predicted transition, as mean / max / min per quantity; {} for a class without diagnostics."""
    model = params["model"]
    if not hasattr(model, "diagnostics"):
        return {}
    one = jax.jit(jax.vmap(lambda z, f, zn: model.diagnostics(params["arrays"], z, f, zn)))
    parts = [one(jnp.asarray(p[:-1]), jnp.asarray(data.f[r]), jnp.asarray(p[1:])) for p, r in zip(pred, rows)]
    out = {}
    for name in parts[0]:
        x = np.stack([np.asarray(q[name]) for q in parts])
        out[name] = {"mean": float(x.mean()), "max": float(x.max()), "min": float(x.min())}
    return out


def evaluate(params: dict, data: D.Dataset, splits=("train", "val", "test"), structure: bool = True) -> dict:
    """Rollout errors (and the model's structure diagnostics) per split of a data set.

    Args:
      params: a model.
      data: a `tignn_jax.data.Dataset` on the model's mesh.
      splits: split names of the data set.
      structure: also the model class's diagnostics along the predicted rollouts.

    Returns:
      (report, raw): a JSON-ready dict per split (`summarize`: mean, median and per-step mean of the relative L2
      errors of q, v, σ and u over all nodes, free nodes and relative to the case's peak), and the raw error
      arrays [cases, T, 4] per split and node set.

    Raises:
      ValueError: the data are on another mesh, or a split is unknown.
    """
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
