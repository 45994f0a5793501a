"""Data-generation wall time against the paper's Abaqus figures.

    python benchmarks/datasets.py data/beam_ref.npz data/bunny.npz ...

Reads the wall time that `tignn generate` stores in each data set's metadata (time of the FEM runs, compilation
included, on this machine) and writes benchmarks/results/datasets.md.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe  # noqa: E402

PAPER_SECONDS = {"beam": 795.0, "bunny": 2700.0}   # Abaqus, as reported by the paper for 52 beam / 100 bunny cases


def main(paths):
    rows = []
    for p in paths:
        d = np.load(p)
        meta = json.loads(str(d["metadata"]))
        n_cases, n_frames = d["z"].shape[0], d["z"].shape[1] - 1
        wall = float(meta.get("wall_time_s", float("nan")))
        rows.append((Path(p).name, meta["scene"], n_cases, n_frames, meta.get("n_sub"), wall,
                     PAPER_SECONDS.get(meta["scene"]), meta.get("machine_load", "")))
    lines = ["# Data generation wall time", "", "Machine: " + json.dumps(describe()), "",
             "| file | scene | cases | frames | sub-steps / frame | our wall time [s] | paper (Abaqus) [s] |",
             "|---|---|---|---|---|---|---|"]
    for name, scene, c, t, ns, wall, paper, _ in rows:
        lines.append(f"| {name} | {scene} | {c} | {t} | {ns} | {wall:.0f} | {paper if paper else '—'} |")
    lines += ["", "Wall time covers the FEM runs of all cases (batched with vmap, compilation included). The machine "
              "was shared with other jobs while generating (see the load average in each run's note)."]
    out = Path(__file__).resolve().parent / "results" / "datasets.md"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main(sys.argv[1:])
