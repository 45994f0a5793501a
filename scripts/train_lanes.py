"""Run several `tignn train` chains at once inside one wall-clock budget (a leased GPU, say).

    python scripts/train_lanes.py --plan plan.json --data ../shared/data/abaqus_beam.npz --budget 420 --out runs/lanes

A plan is JSON: ``{"config": "beam", "common": ["hidden=64", ...], "lanes": [{"name": "d1", "init": "a/model.npz",
"phases": [{"share": 0.5, "set": ["case_weight=1.0", "lr=0.001"]}, {"share": 0.5, "set": ["unroll=20", ...]}]}]}``.
Each lane's phases run one after another, each warm-started (``--init-from``) from the model its previous phase
selected on val (the first from the lane's ``init``); the lanes run side by side, each in its own process.

A phase may fix its ``epochs``; every other phase's epoch count is fitted to the budget. First each such phase's
configuration runs two epochs with a validation after each, all at once (so the measured times include the
lanes' contention for the device): the second epoch's training time, plus the first validation's time divided by
the phase's ``eval_every``, is its cost per epoch. (Session 46 learnt this the hard way: on an H200 the beam's
one-step epoch took 1.1-1.9 s but each validation about 4 s, and a calibration without it gave schedules the
time limit cut at a tenth.) Each phase then gets ``share`` of what is left of its lane's budget, less
``--startup`` (data loading and compilation), divided by that cost times ``--overhead``, at most
``--max-epochs``. It also gets that allotment as ``--time-limit``, so it ends at an epoch boundary with a checkpoint
even if the estimate was short. Every ``--pack-every`` s, and at the end, the run folders without their
checkpoints (config, metrics.jsonl, best/model.npz, logs) are packed into ``--pack-to`` (default
OUT/lanes.tar.gz), so a job that is killed still leaves its models; OUT/lanes.json records the plan, the measured
costs and each phase's epochs, return code and wall time. Session 46 ran it on a leased H200 (lab notes): the
fine-tune that became `beam-abaqus-64x2`.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tarfile
import threading
import time
from pathlib import Path


def check_plan(plan: dict) -> dict:
    """The plan with defaults filled in; a clear error for a malformed one."""
    if not isinstance(plan.get("lanes"), list) or not plan["lanes"]:
        raise ValueError("plan needs a non-empty list 'lanes'")
    names = set()
    for lane in plan["lanes"]:
        name = lane.get("name")
        if not name or not str(name).replace("-", "").replace("_", "").isalnum():
            raise ValueError(f"lane name must be letters, digits, '-' or '_', got {name!r}")
        if name in names:
            raise ValueError(f"lane name {name!r} appears twice")
        names.add(name)
        if not lane.get("init"):
            raise ValueError(f"lane {name!r} needs an 'init' model (a model.npz or run folder)")
        phases = lane.get("phases")
        if not isinstance(phases, list) or not phases:
            raise ValueError(f"lane {name!r} needs a non-empty list 'phases'")
        for i, ph in enumerate(phases):
            share = ph.get("share", 1.0 / len(phases))
            if not (isinstance(share, (int, float)) and share > 0):
                raise ValueError(f"lane {name!r} phase {i}: share must be > 0, got {share!r}")
            ph["share"] = float(share)
            if "epochs" in ph and not (isinstance(ph["epochs"], int) and ph["epochs"] >= 1):
                raise ValueError(f"lane {name!r} phase {i}: epochs must be an integer >= 1, got {ph['epochs']!r}")
            ph.setdefault("set", [])
    plan.setdefault("config", "beam")
    plan.setdefault("common", [])
    return plan


def epochs_for(seconds: float, epoch_s: float, overhead: float) -> int:
    """How many epochs fit in ``seconds`` at ``epoch_s`` each, times ``overhead`` (at least one)."""
    if not (epoch_s > 0 and math.isfinite(epoch_s)):
        raise ValueError(f"epoch time must be a positive number, got {epoch_s!r}")
    return max(1, int(seconds // (epoch_s * overhead)))


def _train_cmd(args, plan, sets, init, run_dir, extra=()):
    cmd = [args.python, "-m", "tignn_jax.cli", "train", "--data", args.data, "--config", plan["config"],
           "--run-dir", str(run_dir), "--no-progress", "--init-from", str(init)]
    for s in [*plan["common"], *sets, *extra]:
        cmd += ["--set", s]
    return cmd


def epoch_costs(run_dir: Path) -> tuple[float, float]:
    """(training s per epoch, s per validation) from a calibration run's metrics.jsonl: the last epoch's
    training time, and the rest of the elapsed time between the last two epochs (the validation between them)."""
    path = run_dir / "metrics.jsonl"
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.exists() else []
    if not rows:
        return float("nan"), float("nan")
    train_s = float(rows[-1]["epoch_s"])
    if len(rows) < 2:
        return train_s, float("nan")
    return train_s, max(float(rows[-1]["elapsed_s"]) - float(rows[-2]["elapsed_s"]) - train_s, 0.0)


def _eval_every(plan: dict, phase: dict) -> int:
    """The phase's eval_every (its own --set, else the plan's common one, else the trainer's default 2)."""
    every = 2
    for item in [*plan["common"], *phase["set"]]:
        key, _, value = item.partition("=")
        if key == "eval_every":
            every = int(value)
    return max(every, 1)


def pack(out: Path, dest: Path | None = None) -> None:
    """Pack the lanes' run folders (no checkpoints) and logs into ``dest`` (out/lanes.tar.gz), atomically."""
    dest = Path(dest) if dest is not None else out / "lanes.tar.gz"
    tmp = dest.with_name(dest.name + ".tmp")
    with tarfile.open(tmp, "w:gz") as tar:
        for path in sorted(p for sub in ("calibration", "runs") if (out / sub).exists() for p in (out / sub).rglob("*")):
            rel = path.relative_to(out)
            if path.is_file() and "checkpoints" not in rel.parts:
                tar.add(path, arcname=str(rel))
        if (out / "lanes.json").exists():
            tar.add(out / "lanes.json", arcname="lanes.json")
    os.replace(tmp, dest)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plan", required=True, help="plan JSON file")
    ap.add_argument("--data", required=True, help="data set .npz")
    ap.add_argument("--budget", type=float, required=True, help="wall-clock seconds for everything, calibration in")
    ap.add_argument("--out", required=True, help="folder for runs/, lanes.json and lanes.tar.gz")
    ap.add_argument("--python", default=sys.executable)
    ap.add_argument("--overhead", type=float, default=1.25,
                    help="safety factor on the measured cost of an epoch and its validation (checkpoints, jitter)")
    ap.add_argument("--startup", type=float, default=40.0, help="seconds allowed per phase for start and compile")
    ap.add_argument("--max-epochs", type=int, default=None, help="cap on a calibrated phase's epochs")
    ap.add_argument("--pack-every", type=float, default=60.0)
    ap.add_argument("--pack-to", default=None, help="where the pack goes (default OUT/lanes.tar.gz)")
    args = ap.parse_args(argv)
    t0 = time.time()
    if args.budget <= 0:
        print(f"error: budget must be > 0 s, got {args.budget}", file=sys.stderr)
        return 2
    try:
        plan = check_plan(json.loads(Path(args.plan).read_text()))
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    out = Path(args.out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    record = {"plan": plan, "budget_s": args.budget, "calibration": {}, "phases": {}}

    def save_record():
        (out / "lanes.json").write_text(json.dumps(record, indent=1))

    stop = threading.Event()

    def packer():
        while not stop.wait(args.pack_every):
            save_record()
            pack(out, args.pack_to)

    threading.Thread(target=packer, daemon=True).start()

    # calibration: two epochs of every phase configuration without a fixed epoch count, all at once
    cal = {}
    for lane in plan["lanes"]:
        for i, ph in enumerate(lane["phases"]):
            if "epochs" in ph:   # a fixed epoch count: nothing to measure
                continue
            run_dir = out / "calibration" / f"{lane['name']}-p{i}"
            # two epochs with a validation after each: the second epoch's time plus the first validation's
            # (elapsed_s is recorded before an epoch's validation) is what one epoch with validation costs
            cmd = _train_cmd(args, plan, ph["set"], lane["init"], run_dir,
                             extra=("epochs=2", "eval_every=1", "ckpt_every=1000"))
            run_dir.parent.mkdir(parents=True, exist_ok=True)
            log = open(out / "calibration" / f"{lane['name']}-p{i}.log", "w")
            cal[(lane["name"], i)] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), run_dir, log)
    for key, (proc, run_dir, log) in cal.items():
        proc.wait()
        log.close()
        train_s, eval_s = epoch_costs(run_dir)
        record["calibration"][f"{key[0]}-p{key[1]}"] = {"rc": proc.returncode, "epoch_s": train_s, "eval_s": eval_s}
    save_record()
    if cal:
        print(f"calibration done after {time.time() - t0:.0f} s: " + ", ".join(
            f"{k} {v['epoch_s']:.2f} s/epoch + {v['eval_s']:.2f} s/validation"
            for k, v in record["calibration"].items()), flush=True)
    deadline = t0 + args.budget

    def run_lane(lane):
        init = lane["init"]
        phases = lane["phases"]
        for i, ph in enumerate(phases):
            left = deadline - time.time()
            share = ph["share"] / sum(p["share"] for p in phases[i:])
            allot = left * share
            key = f"{lane['name']}-p{i}"
            if "epochs" in ph:
                epochs = int(ph["epochs"])
            else:
                c = record["calibration"][key]
                every = _eval_every(plan, ph)
                epoch_s = c["epoch_s"] + (c["eval_s"] / every if math.isfinite(c["eval_s"]) else 0.0)
                if not math.isfinite(epoch_s) or allot - args.startup <= 0:
                    record["phases"][key] = {"skipped": f"epoch_s {epoch_s}, allotment {allot:.0f} s"}
                    return
                epochs = epochs_for(allot - args.startup, epoch_s, args.overhead)
                if args.max_epochs is not None:
                    epochs = min(epochs, args.max_epochs)
            run_dir = out / "runs" / key
            cmd = _train_cmd(args, plan, ph["set"], init, run_dir, extra=(f"epochs={epochs}",))
            cmd += ["--time-limit", str(max(allot - args.startup, 1.0))]
            record["phases"][key] = {"epochs": epochs, "allot_s": allot, "cmd": cmd}
            start = time.time()
            with open(out / "runs" / f"{key}.log", "w") as log:
                rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT)
            record["phases"][key].update(rc=rc, wall_s=time.time() - start)
            best = run_dir / "best" / "model.npz"
            if rc != 0 or not best.exists():
                return
            init = str(best)

    threads = [threading.Thread(target=run_lane, args=(lane,)) for lane in plan["lanes"]]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    stop.set()
    save_record()
    pack(out, args.pack_to)
    for key, ph in record["phases"].items():
        print(key, {k: v for k, v in ph.items() if k != "cmd"}, flush=True)
    print(f"done after {time.time() - t0:.0f} s; packed {args.pack_to or out / 'lanes.tar.gz'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
