"""How long does our FEM take to generate a data set, against the paper's Abaqus figures?

Reads the wall time that `tignn generate` stores in each data set's metadata (the FEM runs of all cases,
batched, compilation included, on the machine that generated it) and writes datasets.{json,md} to ``--out``
(default benchmarks/results).

    python benchmarks/datasets.py data/beam_ref.npz data/bunny.npz ... [--out DIR]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import RESULTS_DIR, describe, write_results  # noqa: E402

PAPER_SECONDS = {"beam": 795.0, "bunny": 2700.0}   # Abaqus, as reported by the paper for 52 beam / 100 bunny cases


def read(path) -> dict:
    """One data set's row: file, scene, cases, frames, sub-steps per frame, wall time, the paper's time."""
    with np.load(path, allow_pickle=False) as d:
        if "metadata" not in d.files:
            raise SystemExit(f"{path}: no metadata (not written by `tignn generate`)")
        meta = json.loads(str(d["metadata"]))
        n_cases, n_frames = d["z"].shape[0], d["z"].shape[1] - 1
    scene = meta.get("scene", "?")
    return {"file": Path(path).name, "scene": scene, "cases": int(n_cases), "frames": int(n_frames),
            "n_sub": meta.get("n_sub"), "wall_time_s": float(meta.get("wall_time_s", float("nan"))),
            "paper_s": PAPER_SECONDS.get(scene), "machine_load": meta.get("machine_load", "")}


def report(result: dict) -> str:
    m = result["machine"]
    lines = ["# Data generation wall time", "",
             f"Machine of this report: {m['cpu']}, {m['cores']} cores (the times were measured where each data set "
             "was generated).", "",
             "| file | scene | cases | frames | sub-steps / frame | our wall time [s] | paper (Abaqus) [s] |",
             "|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['file']} | {r['scene']} | {r['cases']} | {r['frames']} | {r['n_sub']} | "
                     f"{r['wall_time_s']:.0f} | {r['paper_s'] if r['paper_s'] else '—'} |")
    lines += ["", "Wall time covers the FEM runs of all cases (batched with vmap, compilation included). The machine "
              "may have been shared with other jobs while generating (see each data set's metadata)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="+", help="data sets written by `tignn generate` (.npz with metadata)")
    ap.add_argument("--out", default=str(RESULTS_DIR), help="folder of datasets.{json,md} (default %(default)s)")
    args = ap.parse_args(argv)
    result = {"machine": describe(), "rows": [read(p) for p in args.paths]}
    write_results("datasets", result, report(result), Path(args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
