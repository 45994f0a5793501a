"""Pinning the real-time process to cores (`tignn_jax.mr.pin_cores`, `tignn demo --cores`) and its benchmark's
tables."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tignn_jax import mr

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import pinning  # noqa: E402

linux = pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="pinning needs os.sched_setaffinity")


def _python(code: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=ROOT, timeout=600)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "1", None])
def test_pin_cores_names_a_bad_count(bad):
    with pytest.raises(ValueError, match=repr(bad).replace("(", r"\(").replace(".", r"\.")):
        mr.pin_cores(bad)


@linux
def test_pin_cores_refuses_more_cores_than_the_process_may_use():
    allowed = len(os.sched_getaffinity(0))
    with pytest.raises(ValueError, match=f"{allowed + 1} is more than the {allowed} CPUs"):
        mr.pin_cores(allowed + 1)


PIN_FIRST = """
import json, os, sys
from tignn_jax import mr
cpus = mr.pin_cores(1)
import jax, jax.numpy as jnp
x = jax.jit(lambda a: (a @ a).sum())(jnp.ones((256, 256)))   # the backend starts, and with it XLA's threads
x.block_until_ready()
masks = {tid: sorted(os.sched_getaffinity(int(tid))) for tid in os.listdir("/proc/self/task")}
print(json.dumps({"cpus": list(cpus), "masks": list(masks.values()), "threads": len(masks),
                  "allowed_before": int(sys.argv[1])}))
"""


@linux
def test_pin_cores_before_jax_pins_every_thread_jax_starts_afterwards():
    allowed = sorted(os.sched_getaffinity(0))
    done = _python(PIN_FIRST, str(len(allowed)))
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["cpus"] == [allowed[0]]                      # the lowest-numbered CPU the process could use
    assert out["threads"] > 1                               # XLA's threads exist by now ...
    assert all(mask == [allowed[0]] for mask in out["masks"])   # ... and every one runs on that CPU only


JAX_FIRST = """
import warnings
import jax.numpy as jnp
from tignn_jax import mr
jnp.ones(3).block_until_ready()      # the backend has started
try:
    mr.pin_cores(1)
except RuntimeError as e:
    print("refused:", e)
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    pinned, devices = mr.real_time_cores(1)   # the demo's set-up: goes on unpinned, and says so
print("real_time_cores:", pinned, len(devices), [str(w.message) for w in caught])
"""


@linux
def test_pin_cores_after_jax_started_refuses_instead_of_squeezing_its_thread_pool():
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("one CPU: pinning to it changes nothing, so nothing is refused")
    done = _python(JAX_FIRST)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "refused: pin_cores(1) must run before JAX's first operation" in done.stdout
    assert "real_time_cores: () 1 [\"not pinned: pin_cores(1) must run before JAX's first operation" in done.stdout


def _demo(tmp_path, *extra: str) -> subprocess.CompletedProcess:
    """`tignn demo` on the beam's stand-in for 3 small frames, in a fresh process (pinning acts on the whole
    process)."""
    return subprocess.run([sys.executable, "-m", "tignn_jax.cli", "demo", "--scene", "beam", "--frames", "3",
                           "--size", "96x72", "--stand-in", "--out", str(tmp_path), *extra], capture_output=True,
                          text=True, cwd=ROOT, timeout=600)


@linux
def test_demo_runs_pinned_to_one_core_by_default(tmp_path):
    allowed = sorted(os.sched_getaffinity(0))
    done = _demo(tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads((tmp_path / "beam_STAND-IN_timings.json").read_text())
    assert summary["cores"] == 1 and summary["pinned_cpus"] == [allowed[0]]
    assert f"pinned to CPU {allowed[0]}" in done.stdout
    # the placeholder dynamics are labelled as such in the files' names, the summary and the output
    assert summary["dynamics"].startswith("STAND-IN") and summary["frames"] == 2
    assert (tmp_path / "beam_STAND-IN.gif").stat().st_size > 0 and "NOTE" in done.stdout


@linux
def test_demo_names_a_core_count_the_machine_does_not_have(tmp_path):
    allowed = len(os.sched_getaffinity(0))
    done = _demo(tmp_path, "--cores", str(allowed + 1))
    assert done.returncode != 0
    assert f"--cores {allowed + 1}: n = {allowed + 1} is more than the {allowed} CPUs" in done.stderr


def _played(p50, p99, frame=10.0, meets=True):
    return {"simulation_p50_ms": p50, "simulation_p99_ms": p99, "frame_p50_ms": frame, "frame_p99_ms": frame,
            "step_alone": {"p50_ms": p50 - 1, "p99_over_p50": 1.1}, "guard_trips": 0, "budget_ms": 18.0,
            "meets": meets, "dynamics": "model beam", "learned_frames": 500}


def test_pinning_summary_takes_medians_and_counts_the_rounds_that_meet_the_budget():
    runs = {"1 core, pinned": [{"rows": {"two-beams": _played(13.0, 14.0)}},
                               {"rows": {"two-beams": _played(14.0, 15.0)}},
                               {"rows": {"two-beams": _played(12.0, 13.0)}}],
            "2 cores": [{"rows": {"two-beams": _played(9.0, 16.2, meets=False)}},
                        {"rows": {"two-beams": _played(10.0, 12.0)}},
                        {"rows": {"two-beams": _played(8.0, 14.4, meets=False)}}]}
    s = pinning.summarise(runs, ["two-beams"])["two-beams"]
    assert s["1 core, pinned"]["p50_ms"] == 13.0 and s["1 core, pinned"]["p99_ms"] == 14.0
    assert s["1 core, pinned"]["rounds_meeting"] == 3 and s["2 cores"]["rounds_meeting"] == 1
    assert s["2 cores"]["p99_over_p50_max"] == pytest.approx(1.8)
    assert s["2 cores"]["p99_over_p50_median"] == pytest.approx(1.8)   # 1.8, 1.2, 1.8
    result = {"machine": {"cpu": "x", "cores": 2, "jax": "j", "load_average_1m": 0.0, "note": "n"}, "rounds": 3,
              "frames": 500, "warmup": 20, "configs": {"1 core, pinned": 1, "2 cores": 2}, "runs": runs,
              "summary": {"two-beams": s}}
    md = pinning.format_md(result)
    assert "| two-beams | 18 ms | 13.00 / 14.00 (1.08×; 1.08×) | 10.00 | 3 of 3 |" in md
    assert "14.40 (1.80×)" in md and md.count("| two-beams |") == 1


@pytest.mark.parametrize("argv, message", [(["--rows", "beam,cube"], "unknown row(s) ['cube']"),
                                           (["--configs", "1,x"], "comma-separated integers, got '1,x'"),
                                           (["--configs", "0"], "core counts from 1 to"),
                                           (["--rounds", "0"], "--rounds must be ≥ 1")])
def test_pinning_benchmark_names_bad_arguments(argv, message):
    with pytest.raises(SystemExit, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")
                       .replace("]", r"\]")):
        pinning.main(argv)
