"""Smoke tests of the mixed-reality benchmarks (benchmarks/realtime.py, pinning.py, render.py, ar_contact.py): each
runs in its quick mode, in a fresh process (the real-time ones pin it before JAX starts), into a temporary
results folder, and writes its .json and .md with the expected rows."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
SCRIPTS = ("realtime", "pinning", "render", "ar_contact")


def _bench(script: str, out: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(BENCHMARKS / f"{script}.py"), "--quick", "--out", str(out), *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)


def _results(out: Path, stem: str):
    assert (out / f"{stem}.json").is_file() and (out / f"{stem}.md").is_file()
    return json.loads((out / f"{stem}.json").read_text()), (out / f"{stem}.md").read_text()


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_option_has_help(script):
    done = subprocess.run([sys.executable, str(BENCHMARKS / f"{script}.py"), "--help"], capture_output=True,
                          text=True, cwd=ROOT, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    options = [line.split()[0] for line in done.stdout.splitlines() if line.strip().startswith("--")]
    assert "--quick" in options and "--out" in options
    for line in done.stdout.split("options:")[1].split("\n  -")[1:]:   # each option's entry has a text
        assert len(line.split()) > 2, line


# long: its loop is the demo's, played by tests/test_render.py, and its step comparison is model_step's
# (tests/test_benchmarks.py); the smoke run compiles every variant again on one core (about 100 s)
@pytest.mark.long
def test_realtime_quick_writes_the_loop_and_the_public_step_against_the_stepper(tmp_path):
    done = _bench("realtime", tmp_path, "--scenes", "beam")   # one body: tests/test_render.py plays the two beams
    assert done.returncode == 0, done.stderr[-3000:]
    result, md = _results(tmp_path, "realtime")
    assert list(result["scenes"]) == ["beam"] and result["quick"]
    s = result["scenes"]["beam"]
    assert s["dynamics"].startswith("model beam") and s["bodies"] == 1 and s["frames"] == 10
    programs = s["step_programs"][s["judged_round"]]
    for variant in ("loop's step program", "tignn_jax.stepper", "tignn_jax.step, device forces",
                    "tignn_jax.step, host forces"):
        assert programs[variant]["p50_ms"] > 0
    assert programs["max_abs_difference_step_vs_stepper"] < 1e-4   # step runs the stepper's program
    assert s["public_step"]["simulation_p50_ms_estimated"] >= s["simulation_learned"]["p50_ms"]
    if hasattr(os, "sched_setaffinity"):
        assert result["machine"]["pinned_cpus"] == sorted(os.sched_getaffinity(0))[:1]   # as `tignn demo`
    assert "load_average_1m" in result["machine"] and "load_average_1m_at_end" in result["machine"]
    assert md.count("| beam |") == 2 and "QUICK RUN" in md   # the loop's table and the step's


@pytest.mark.long
@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="pinning needs os.sched_setaffinity")
def test_pinning_quick_writes_the_pinned_configuration(tmp_path):
    done = _bench("pinning", tmp_path, "--rows", "beam", "--configs", "1")
    assert done.returncode == 0, done.stderr[-3000:]
    result, md = _results(tmp_path, "pinning")
    config = "1 core, pinned" if len(os.sched_getaffinity(0)) > 1 else "1 core"
    row = result["summary"]["beam"][config]
    assert row["dynamics"] == "model beam" and len(row["rounds"]) == 1 and row["budget_ms"] == 9.0
    assert result["runs"][config][0]["pinned_cpus"] == sorted(os.sched_getaffinity(0))[:1]
    assert "| beam | 9 ms |" in md


def test_render_quick_writes_the_beam_row(tmp_path):
    done = _bench("render", tmp_path, "--meshes", "beam_hex8")
    assert done.returncode == 0, done.stderr[-3000:]
    result, md = _results(tmp_path, "render")
    r = result["beam_hex8"]
    assert r["surface_triangles"] == 900 and r["drawn_pixels"] > 0 and not r["overflow"]
    assert r["max_abs_diff_jax_vs_numpy"] < 1e-3          # the NumPy rasteriser is the same algorithm
    assert r["draw_jax"]["p50_ms"] > 0 and "| beam_hex8 | 756 | 900 |" in md


@pytest.mark.long
def test_ar_contact_quick_writes_the_beam_row(tmp_path):
    done = _bench("ar_contact", tmp_path, "--cases", "beams")
    assert done.returncode == 0, done.stderr[-3000:]
    result, md = _results(tmp_path, "ar_contact")
    r = result["beams"]
    assert r["nodes"] == [756, 756] and r["pairs_in_contact"] > 0
    assert r["pruned_max_abs_diff_vs_dense"] < 0.1   # forces of order 1e4: the same to float32 rounding
    for variant in ("dense", "dense_cond", "pruned", "pruned_apart") + (("jaxmd_cell",) if result["jax_md"] else ()):
        assert r[variant]["p50_ms"] > 0
    assert "| beams | 756+756 |" in md
