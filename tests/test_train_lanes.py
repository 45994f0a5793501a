"""scripts/train_lanes.py: plans are checked, epoch counts fit the budget, and a two-phase lane runs end to end
(the second phase warm-started from the first's selected model, the pack holding the models but no checkpoints)."""
import importlib.util
import json
import sys
import tarfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tignn_jax import api
from tignn_jax import data as D
from tignn_jax import model as M
from tignn_jax import train as T

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("train_lanes", ROOT / "scripts" / "train_lanes.py")
lanes = importlib.util.module_from_spec(spec)
spec.loader.exec_module(lanes)


def _plan(**lane):
    base = {"name": "a", "init": "m.npz", "phases": [{"set": ["lr=0.001"]}]}
    return {"lanes": [{**base, **lane}]}


@pytest.mark.parametrize("plan, message", [
    ({}, "non-empty list 'lanes'"),
    (_plan(name="a b"), "lane name"),
    ({"lanes": _plan()["lanes"] * 2}, "appears twice"),
    (_plan(init=""), "needs an 'init'"),
    (_plan(phases=[]), "non-empty list 'phases'"),
    (_plan(phases=[{"share": 0}]), "share must be > 0, got 0"),
    (_plan(phases=[{"epochs": 0}]), "epochs must be an integer >= 1, got 0"),
    (_plan(phases=[{"epochs": 2.5}]), "got 2.5"),
])
def test_bad_plans_are_named(plan, message):
    with pytest.raises(ValueError, match=message):
        lanes.check_plan(plan)


def test_plan_defaults_and_epoch_arithmetic(tmp_path):
    plan = lanes.check_plan(_plan(phases=[{"set": []}, {"set": ["eval_every=4"]}]))
    assert plan["config"] == "beam" and plan["common"] == []
    assert [p["share"] for p in plan["lanes"][0]["phases"]] == [0.5, 0.5]
    assert lanes.epochs_for(100.0, 2.0, 1.25) == 40
    assert lanes.epochs_for(1.0, 2.0, 1.0) == 1          # at least one epoch
    with pytest.raises(ValueError, match="positive number, got nan"):
        lanes.epochs_for(10.0, float("nan"), 1.0)
    # eval_every: the phase's own over the plan's common setting over the trainer's default 2
    assert lanes._eval_every({"common": []}, plan["lanes"][0]["phases"][0]) == 2
    assert lanes._eval_every({"common": ["eval_every=3"]}, plan["lanes"][0]["phases"][1]) == 4
    assert lanes._eval_every({"common": ["eval_every=3"]}, {"set": []}) == 3
    # the calibration's costs: epoch 2's training time, and the rest of the time between the two records
    run = tmp_path / "cal"
    run.mkdir()
    rows = [{"epoch": 1, "epoch_s": 9.0, "elapsed_s": 10.0}, {"epoch": 2, "epoch_s": 2.0, "elapsed_s": 15.0}]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert lanes.epoch_costs(run) == (2.0, 3.0)
    assert all(np.isnan(lanes.epoch_costs(tmp_path / "missing")))


def test_two_phase_lane_runs_end_to_end(tmp_path):
    data = D.synthetic_beam(nx=4, ny=2, nz=2, cases=5, frames=4)
    path = tmp_path / "toy.npz"
    D.save(data, path)
    cfg = T.CONFIGS["tiny"]
    norm = D.normalization(data, D.split_rows(data, "train"))
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), data.q0)
    weights = M.init_weights(jax.random.PRNGKey(0), cfg.model, {k: jnp.asarray(v) for k, v in norm.items()},
                             jnp.asarray(data.z[0, 0]), jnp.asarray(data.f[0, 0]),
                             jnp.asarray(data.node_type, jnp.int32), topo)
    init = api.save_model(api.make_params(cfg.model, norm, weights, data.q0, data.edges, data.node_type),
                          tmp_path / "init.npz")
    plan = {"config": "tiny", "common": ["batch_size=4", "eval_every=1"],
            "lanes": [{"name": "t1", "init": str(init),
                       "phases": [{"share": 0.5, "set": ["lr=0.01"]}, {"epochs": 1, "set": ["lr=0.001"]}]}]}
    (tmp_path / "plan.json").write_text(json.dumps(plan))
    out = tmp_path / "out"
    assert lanes.main(["--plan", str(tmp_path / "plan.json"), "--data", str(path), "--budget", "600",
                       "--out", str(out), "--startup", "0", "--max-epochs", "2", "--python", sys.executable]) == 0
    record = json.loads((out / "lanes.json").read_text())
    cal = record["calibration"]["t1-p0"]
    assert cal["rc"] == 0 and cal["epoch_s"] > 0 and cal["eval_s"] >= 0
    assert "t1-p1" not in record["calibration"]              # a fixed epoch count is not measured
    p0, p1 = record["phases"]["t1-p0"], record["phases"]["t1-p1"]
    assert (p0["epochs"], p0["rc"], p1["epochs"], p1["rc"]) == (2, 0, 1, 0)
    config1 = json.loads((out / "runs" / "t1-p1" / "config.json").read_text())
    assert Path(config1["init_from"]) == (out / "runs" / "t1-p0" / "best" / "model.npz").resolve()
    assert config1["lr"] == 0.001 and config1["epochs"] == 1
    with tarfile.open(out / "lanes.tar.gz") as tar:
        names = tar.getnames()
    assert "runs/t1-p0/best/model.npz" in names and "runs/t1-p1/best/model.npz" in names
    assert "lanes.json" in names and not any("checkpoints" in n for n in names)


def test_bad_budget_and_plan_exit_with_a_message(tmp_path, capsys):
    (tmp_path / "plan.json").write_text(json.dumps({"lanes": []}))
    args = ["--plan", str(tmp_path / "plan.json"), "--data", "x.npz", "--out", str(tmp_path / "o")]
    assert lanes.main(args + ["--budget", "0"]) == 2
    assert "budget must be > 0 s, got 0.0" in capsys.readouterr().err
    assert lanes.main(args + ["--budget", "10"]) == 2
    assert "non-empty list 'lanes'" in capsys.readouterr().err
