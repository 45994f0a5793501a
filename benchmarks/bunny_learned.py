"""The learned bunny (`bunny`: linear GENERIC operators learned from the FEM's trajectories,
`tignn_jax.linear_generic`) against its untrained start and the FEM's own rest linearisation (`bunny-linear`),
on the training, validation and held-out test load positions of the bunny data.

Errors: 20-step rollouts from each case's first state with its forces through the public `tignn_jax.rollout`
(float32, as a user runs it), relative L2 per snapshot (`tignn_jax.evaluate.relative_errors`, all nodes, clamped
stress predicted), mean and median over snapshots 1..20 and cases: the measure of the model cards. The untrained
start is the same architecture with its networks' heads at zero and its scales where training began (the run's
config: the material's nominal moduli, half the shear in the nodes and half in the cells, half the deviatoric
stress smoothed), packed the same way. Time: median of one step (`tignn_jax.stepper`) from a mid-rollout state,
after compilation. Writes benchmarks/results/bunny_learned.{json,md}.

    python benchmarks/bunny_learned.py --data data/bunny.npz --run runs/lg-d [--repeats 200]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _machine import describe  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
SPLITS = {"train positions": "train", "val": list(range(81, 91)), "test": list(range(91, 101))}


def untrained(run: Path, data_path: str):
    """The packed untrained start of the run ``run`` (params, graph)."""
    import jax
    jax.config.update("jax_enable_x64", True)
    from tignn_jax import api
    from tignn_jax import framesolve as FS
    from tignn_jax import linear_generic as LG

    saved = json.loads((run / "config.json").read_text())
    config = LG.LinearConfig(**saved["config"])
    data, geo = LG.geometry_from_file(data_path)
    lin = LG.to_rest_linearization(LG.init(config, geo, saved["seed"]), geo, config)
    like, graph = api.load_pretrained("bunny-linear")
    jax.config.update("jax_enable_x64", False)
    return FS.model_from_operators(like, lin, float(data.dt)), graph


def errors(params, graph, data, rows) -> dict:
    import tignn_jax
    from tignn_jax.evaluate import relative_errors

    e = np.stack([relative_errors(np.asarray(tignn_jax.rollout(params, graph, data.f[r])), data.z[r], data.q0)[1:]
                  for r in rows])
    names = ("q", "v", "sigma", "u")
    return {"mean": dict(zip(names, e.mean(axis=(0, 1)).round(5).tolist())),
            "median": dict(zip(names, np.median(e, axis=(0, 1)).round(5).tolist())),
            "worst case u": float(e[..., 3].mean(axis=1).max().round(5)), "cases": len(rows),
            "finite": bool(np.isfinite(e).all())}


def structure(params, graph, data, rows) -> dict:
    """The linear GENERIC structure of a packed model, measured: K's extreme eigenvalues on the free degrees of
    freedom (PSD: the energy ½vᵀMv + ½uᵀKu is bounded below), α and the masses (> 0), and along the rollouts of
    ``rows`` each step's dissipation D = f·Δu − ΔE (≥ 0: backward Euler of this system never creates energy;
    reported relative to the largest |ΔE|)."""
    import tignn_jax

    norm = {k: np.asarray(v, np.float64) for k, v in params["norm"].items()}
    n = data.q0.shape[0]
    K = np.zeros((n, n, 3, 3))
    K[norm["fs_k_rows"].astype(int), norm["fs_k_cols"].astype(int)] = norm["fs_k"]
    K = K.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)
    free = np.repeat(np.asarray(data.node_type) == 0, 3)
    eig = np.linalg.eigvalsh(K[free][:, free])
    m3 = np.repeat(norm["fs_mass"], 3)
    worst, scale = np.inf, 0.0
    for r in rows:
        z = np.asarray(tignn_jax.rollout(params, graph, data.f[r]), np.float64)
        u, v = (z[..., :3] - data.q0).reshape(len(z), -1), z[..., 3:6].reshape(len(z), -1)
        energy = 0.5 * np.einsum("ti,i,ti->t", v, m3, v) + 0.5 * np.einsum("ti,ij,tj->t", u, K, u)
        work = np.einsum("ti,ti->t", data.f[r].reshape(len(z) - 1, -1), np.diff(u, axis=0))
        dissipation = work - np.diff(energy)
        worst, scale = min(worst, dissipation.min()), max(scale, np.abs(np.diff(energy)).max())
    return {"K eigenvalue min": float(eig[0]), "K eigenvalue max": float(eig[-1]),
            "alpha": float(norm["fs_alpha"].reshape(-1)[0]), "mass min": float(norm["fs_mass"].min()),
            "dissipation min / max |dE|": float(worst / scale)}


def step_ms(params, graph, data, repeats: int) -> float:
    import jax
    import jax.numpy as jnp
    import tignn_jax

    fn = tignn_jax.stepper(params)
    z, f = jnp.asarray(data.z[0, 10]), jnp.asarray(data.f[0, 10])
    jax.block_until_ready(fn(z, f))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(z, f))
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def curve(records: list, path: Path) -> Path:
    """The training curve: train (minibatch) and val relative errors of u, v, σ against the step."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r["step"] for r in records]
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    for k, (name, colour) in enumerate((("u", "C0"), ("v", "C1"), ("σ", "C2"))):
        ax.plot(steps, [r["train"][k] for r in records], ":", color=colour, label=f"train {name} (minibatch)")
        ax.plot(steps, [r["val"][k] for r in records], "-", color=colour, label=f"val {name}")
    ax.axhline(0.05, color="grey", lw=0.8, ls="--")
    ax.axhline(0.10, color="grey", lw=0.8, ls="-.")
    ax.set(yscale="log", xlabel="step (12 training positions each)", ylabel="relative L2 error (20-step rollouts)",
           title="learned bunny: training curve (targets u 0.05, σ 0.10 dashed)")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_md(out: dict) -> None:
    """benchmarks/results/bunny_learned.md from the JSON record ``out``."""
    m = out["machine"]
    lines = ["# The learned bunny against its start and the FEM's rest linearisation", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']} ({m['backend']}); load average "
             f"{m['load_average_1m']} at start. Data: `{out['data']}` (the bunny's 100 patch-load positions); training "
             f"run `{out['run']}`. Rollouts of 20 steps through `tignn_jax.rollout`, relative L2 per snapshot, mean (median) "
             "over snapshots and cases; targets u ≤ 0.05, σ ≤ 0.10. 'train positions' are sims 1–80 (71 trained on, "
             "9 never seen). Step: median of `tignn_jax.stepper` after compilation.", "",
             "| model | split | u | v | σ | worst case u | finite | step ms |", "|---|---|---|---|---|---|---|---|"]
    for name, row in out["rows"].items():
        for split in SPLITS:
            r = row[split]
            cell = lambda k: f"{r['mean'][k]:.4f} ({r['median'][k]:.4f})"
            lines.append(f"| {name} | {split} | {cell('u')} | {cell('v')} | {cell('sigma')} | {r['worst case u']:.4f} "
                         f"| {r['finite']} | {row['step ms']:.2f} |")
    lines += ["", "Structure (the test rollouts; K on the free degrees of freedom; dissipation D = f·Δu − ΔE per step, "
              "relative to the largest |ΔE|, ≥ 0 up to float32 round-off):", "",
              "| model | K eigenvalues min / max | α | mass min | D min |", "|---|---|---|---|---|"]
    for name, row in out["rows"].items():
        st = row["structure"]
        lines.append(f"| {name} | {st['K eigenvalue min']:.3g} / {st['K eigenvalue max']:.3g} | {st['alpha']:.4g} | "
                     f"{st['mass min']:.3g} | {st['dissipation min / max |dE|']:.2g} |")
    if out.get("training curve"):
        curve(out["training curve"], RESULTS / "bunny_learned_curve.png")
        best = min(out["training curve"], key=lambda r: r["val_loss"])
        lines += ["", f"Training curve: `bunny_learned_curve.png` ({len(out['training curve'])} validations; best at step "
                  f"{best['step']}: val u {best['val'][0]:.4f}, v {best['val'][1]:.4f}, σ {best['val'][2]:.4f}; learned "
                  f"density {best['density']:.6g}, mass damping α {best['alpha']:.4g}, against the data's 1e-3 and 2)."]
    (RESULTS / "bunny_learned.md").write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="data/bunny.npz", help="the bunny data set (all 100 positions)")
    ap.add_argument("--run", default="runs/lg-d", help="the training run of the shipped model (its config)")
    ap.add_argument("--model", default="bunny")
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--render", action="store_true", help="only rewrite the .md from the existing .json")
    args = ap.parse_args(argv)
    if args.render:
        out = json.loads((RESULTS / "bunny_learned.json").read_text())
        if "training curve" not in out and (Path(args.run) / "metrics.jsonl").exists():
            out["training curve"] = [json.loads(x) for x in (Path(args.run) / "metrics.jsonl").read_text().splitlines()]
            (RESULTS / "bunny_learned.json").write_text(json.dumps(out, indent=1))
        write_md(out)
        return 0
    import tignn_jax
    from tignn_jax import data as D

    data = D.load(args.data)
    models = {"untrained start": untrained(Path(args.run), args.data),
              f"{args.model} (learned)": tignn_jax.load_pretrained(args.model),
              "bunny-linear (FEM rest linearisation, not learned)": tignn_jax.load_pretrained("bunny-linear")}
    machine = describe()
    out = {"machine": machine, "data": args.data, "run": args.run, "rows": {}}
    for name, (params, graph) in models.items():
        row = {split: errors(params, graph, data, D.split_rows(data, sel)) for split, sel in SPLITS.items()}
        row["step ms"] = round(step_ms(params, graph, data, args.repeats), 3)
        row["structure"] = structure(params, graph, data, D.split_rows(data, SPLITS["test"]))
        out["rows"][name] = row
        print(name, json.dumps(row))
    metrics = Path(args.run) / "metrics.jsonl"
    out["training curve"] = [json.loads(x) for x in metrics.read_text().splitlines()] if metrics.exists() else []
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bunny_learned.json").write_text(json.dumps(out, indent=1))
    write_md(out)
    print(f"wrote {RESULTS / 'bunny_learned.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
