"""FEM against the Abaqus reference beam data: relative L2 errors of u = q − q0, v and σ (free nodes).

    python benchmarks/abaqus_agreement.py --ours PATH_FROM_tignn_generate_beam-reference [--identification JSON]

Metric (as in ../shared/data/README.md): per frame, sqrt(Σ (ours − ref)² / Σ ref²) over nodes, then the mean over
frames 1..20 (frame 0 is the common initial state). Writes benchmarks/results/abaqus_agreement.{md,png,json}.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT.parent / "shared" / "data" / "abaqus_beam.npz"
RESULTS = Path(__file__).resolve().parent / "results"


def rel_l2(a, b, mask=None):
    """[cases, frames] relative L2 error over nodes (and components)."""
    if mask is not None:
        a, b = a[:, :, mask], b[:, :, mask]
    return np.sqrt(np.sum((a - b) ** 2, axis=(-2, -1)) / np.maximum(np.sum(b ** 2, axis=(-2, -1)), 1e-30))


def errors(ours, ref):
    q0 = ref["q0"]
    zo, zr = ours["z"], ref["z"]
    free = ref["node_type"] == 0
    e = {"u": rel_l2(zo[..., :3] - q0, zr[..., :3] - q0), "q": rel_l2(zo[..., :3], zr[..., :3]),
         "v": rel_l2(zo[..., 3:6], zr[..., 3:6]), "sigma_free": rel_l2(zo[..., 6:], zr[..., 6:], free),
         "sigma_all": rel_l2(zo[..., 6:], zr[..., 6:])}
    return {k: v[:, 1:] for k, v in e.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ours", required=True, help="our beam-reference data set (.npz)")
    ap.add_argument("--reference", default=str(REFERENCE), help="the Abaqus beam data (default %(default)s)")
    ap.add_argument("--identification", default=None, help="JSON history of fem.identify (optional)")
    ap.add_argument("--out", default=str(RESULTS), help="output folder (default %(default)s)")
    ap.add_argument("--name", default="abaqus_agreement", help="file name stem of the results")
    args = ap.parse_args(argv)
    ref = dict(np.load(args.reference))
    ours, meta, done = _load_ours(Path(args.ours))
    if not np.allclose(ours["q0"], ref["q0"], atol=1e-6):
        raise SystemExit("node order differs from the reference (q0 mismatch)")
    ref_sub = dict(ref, z=ref["z"][done])
    e = errors(ours, ref_sub)
    pos = {c: i for i, c in enumerate(done)}
    test_idx = [pos[c] for c in np.asarray(ref["split_test"]) - 1 if c in pos]
    train_idx = [pos[c] for c in np.asarray(ref["split_train"]) - 1 if c in pos]
    table = {}
    for split, idx in ((f"all ({len(done)} of 52)", np.arange(len(done))), (f"test ({len(test_idx)} of 6)", test_idx),
                       (f"train ({len(train_idx)} of 41)", train_idx)):
        if len(idx):
            table[split] = {k: float(np.mean(v[idx])) for k, v in e.items()}
    out = Path(args.out)
    ident = json.loads(Path(args.identification).read_text()) if args.identification else None
    payload = {"machine": describe(), "fem": {k: meta.get(k) for k in ("material", "damping", "n_sub", "load_interp",
                                                                       "wall_time_s")},
               "mean_relative_l2": table, "cases": (np.asarray(done) + 1).tolist(),
               "per_case_u": e["u"].mean(1).tolist(), "identification": ident}
    targets = {"u": 0.05, "v": 0.05, "sigma_free": 0.10}
    lines = ["# FEM against the Abaqus beam data", "",
             "Mean over frames 1–20 of the relative L2 error over nodes (σ: free nodes; 'all' includes the clamped "
             "face).",
             "", "| split | u = q − q0 | v | σ (free nodes) | σ (all nodes) | q |", "|---|---|---|---|---|---|"]
    for split, row in table.items():
        lines.append(f"| {split} | {row['u']:.4f} | {row['v']:.4f} | {row['sigma_free']:.4f} | "
                     f"{row['sigma_all']:.4f} | {row['q']:.5f} |")
    lines += ["", "Targets: u ≤ %.2f, v ≤ %.2f, σ (free) ≤ %.2f — %s: %s" % (
        targets["u"], targets["v"], targets["sigma_free"], next(iter(table)),
        ", ".join(f"{k} {'met' if next(iter(table.values()))[k] <= t else 'NOT met'}" for k, t in targets.items())), "",
        f"FEM settings: {json.dumps(payload['fem'])}", ""]
    if ident:
        lines += ["Identification history (train cases only; loss = mean relative L2 error of u):", "",
                  "| iter | loss | density | damping α | Prony time scale s |", "|---|---|---|---|---|"]
        lines += [f"| {h['iter']} | {h['loss']:.4f} | {h['density']:.4g} | {h['damping']:.4g} | "
                  f"{h['tau_scale']:.4g} |" for h in ident]
    write_results(args.name, payload, "\n".join(lines) + "\n", out, echo=False)
    _plot(out / f"{args.name}.png", ours, ref_sub, e, done)
    print("\n".join(lines))


def _load_ours(path: Path):
    """Our data set, or — while `tignn generate` is still running — the cases finished so far in PATH.parts/."""
    if path.exists():
        d = dict(np.load(path))
        done = d["sim_id"] - 1 if "sim_id" in d else np.arange(d["z"].shape[0])
        return d, json.loads(str(d["metadata"])), np.asarray(done)
    parts = path.with_name(path.name + ".parts")
    files = sorted(parts.glob("case_*.npz"))
    if not files:
        raise SystemExit(f"neither {path} nor finished cases in {parts}")
    done = np.array([int(f.stem.split("_")[1]) for f in files])
    from fem.meshes import beam_mesh

    d = {"z": np.stack([np.load(f)["z"] for f in files]), "q0": beam_mesh()[0]}
    meta = {"partial": f"{len(done)} of 52 cases, read from {parts.name} (settings: see the generating command)"}
    return d, meta, done


def _plot(path, ours, ref, e, done):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    q0 = ref["q0"]
    t = np.arange(21) * float(ref["dt"])
    tip = q0[:, 0] == q0[:, 0].max()
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    picks = [k for k, c in enumerate(done) if c in (0, 4, 8, 12)] or list(range(min(4, len(done))))  # 4 positions
    for k, col in zip(picks, ("C0", "C1", "C2", "C3")):
        i, sim = k, done[k] + 1
        zr, zo = ref["z"][i], ours["z"][i]                      # [21, N, 12]
        comp = int(np.argmax(np.abs(zr[-1][tip, :3] - q0[tip]).mean(0)))
        ax[0].plot(t, (zr[:, tip, comp] - q0[tip, comp]).mean(1), col + "-", label=f"Abaqus sim {sim}")
        ax[0].plot(t, (zo[:, tip, comp] - q0[tip, comp]).mean(1), col + "--", label=f"ours sim {sim}")
        node = int(np.argmax(np.abs(zr[-1][:, 6]) * (ref["node_type"] == 0)))
        ax[1].plot(t, zr[:, node, 6], col + "-")
        ax[1].plot(t, zo[:, node, 6], col + "--")
    ax[0].set(xlabel="t", ylabel="mean tip displacement (load axis)", title="tip displacement: — Abaqus, -- FEM")
    ax[0].legend(fontsize=7)
    ax[1].set(xlabel="t", ylabel="S11", title="S11 at the most stressed free node")
    ax[2].boxplot([e["u"].ravel(), e["v"].ravel(), e["sigma_free"].ravel()], tick_labels=["u", "v", "σ free"])
    ax[2].set(yscale="log", title="relative L2 error per case and frame")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
