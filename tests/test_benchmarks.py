"""Smoke tests of the product benchmarks (benchmarks/model_step.py, stability.py, pareto.py, scaling.py, embedded.py,
fem_implicit.py, large_deformation.py, contact_beams.py, fem_throughput.py, abaqus_agreement.py, datasets.py,
diffrax_integrators.py): each runs in its quick or small-argument mode, in a fresh process, into a temporary
results folder, and writes its .json and .md (and .png where it draws one) with the expected rows. Every option
has a help text."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
REFERENCE = ROOT.parent / "shared" / "data" / "abaqus_beam.npz"
QUICK = ("model_step", "stability", "pareto", "scaling", "fem_implicit", "large_deformation", "large_deformation_bunny",
         "contact_beams", "embedded")
SCRIPTS = QUICK + ("fem_throughput", "abaqus_agreement", "datasets")
needs_reference = pytest.mark.skipif(not REFERENCE.exists(), reason="reference data ../shared/data/abaqus_beam.npz "
                                                                    "not present")


def _bench(script: str, *args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    done = subprocess.run([sys.executable, str(BENCHMARKS / f"{script}.py"), *args], capture_output=True, text=True,
                          cwd=ROOT, timeout=timeout)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def _results(out: Path, stem: str, png: bool = False):
    assert (out / f"{stem}.json").is_file() and (out / f"{stem}.md").is_file()
    if png:
        assert (out / f"{stem}.png").stat().st_size > 0
    return json.loads((out / f"{stem}.json").read_text()), (out / f"{stem}.md").read_text()


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_option_has_help(script):
    done = _bench(script, "--help", timeout=120)
    options = [line.split()[0] for line in done.stdout.splitlines() if line.strip().startswith("--")]
    assert "--out" in options and ("--quick" in options) == (script in QUICK)
    for line in done.stdout.split("options:")[1].split("\n  -")[1:]:   # each option's entry has a text
        assert len(line.split()) > 2, line


def test_diffrax_quick_integrates_the_same_trajectory(tmp_path):
    _bench("diffrax_integrators", "--quick", "--out", str(tmp_path))
    result, md = _results(tmp_path, "diffrax")
    assert result["quick"] and result["frames"] == 5 and result["max_difference_relative"] < 1e-5
    assert all(v > 0 for v in result["ms_per_frame_p50"].values()) and "QUICK RUN" in md


def test_model_step_quick_reports_step_against_stepper(tmp_path):
    _bench("model_step", "--quick", "--rows", "beam:1,beam:2", "--out", str(tmp_path))
    result, md = _results(tmp_path, "model_step")
    assert [(r["model"], r["copies"]) for r in result["rows"]] == [("beam", 1), ("beam", 2)] and result["quick"]
    for r in result["rows"]:
        t = r["timing"]
        assert r["same_frame"] and r["nodes"] == 756 * r["copies"]
        assert all(t[k]["p50_ms"] > 0 for k in ("step", "stepper", "rollout"))
        assert t["checks_overhead"] == pytest.approx(t["step"]["p50_ms"] / t["stepper"]["p50_ms"] - 1)
    assert "| beam | 1 | 756 |" in md and "| beam | 2 | 1512 |" in md and "checks overhead" in md


@pytest.mark.long
def test_stability_quick_runs_every_loading_with_and_without_guards(tmp_path):
    _bench("stability", "--quick", "--out", str(tmp_path))
    result, md = _results(tmp_path, "stability", png=True)
    beam = result["scenes"]["beam"]
    assert result["steps"] == 40 and beam["model"] == "beam" and beam["reference"] == "beam-linear"
    assert list(beam["runs"]) == ["release", "constant", "fingertip", "3x load", "noise"]
    for name, run in beam["runs"].items():
        assert run["nan_or_inf"] == 0 and set(run["guarded"]) == {"clip", "reset", "fallback"}, name
        assert len(run["series"]["u_max"]) == 41 and run["energy"]["dissipative_fraction"] == 1.0
        assert f"| beam | {name} | beam |" in md
    assert "| beam | noise | fallback |" in md


@pytest.mark.long
def test_contact_beams_quick_compares_the_couplings_with_the_fem(tmp_path):
    _bench("contact_beams", "--quick", "--out", str(tmp_path), timeout=600)
    result, md = _results(tmp_path, "contact_beams")
    assert result["quick"] and result["frames"] == 4 and {r["load"] for r in result["rows"]} == {"1x hold"}
    implicit = [r for r in result["rows"] if "implicit step" in r["model"]]
    assert len(result["rows"]) == 3 and len(implicit) == 1
    assert implicit[0]["finite"] and implicit[0]["energy_creating_frames"] == 0 and implicit[0]["u_error"] < 0.05
    for t in result["frame_ms"].values():   # 4 frames, the first call left out
        assert t["frames"] == 3 and 0 < t["p50"] <= t["p99"] <= t["max"]
    assert "closest approach" in md


@pytest.mark.long
def test_large_deformation_quick_compares_the_models_with_the_fem_and_times_every_frame(tmp_path):
    _bench("large_deformation", "--quick", "--out", str(tmp_path), timeout=600)
    result, md = _results(tmp_path, "large_deformation")
    assert result["quick"] and result["frames"] == 21
    models = {r["model"] for r in result["rows"]}
    assert {r["load"] for r in result["rows"]} == {"3x hold"} and len(models) == 3
    corot = [r for r in result["rows"] if r["model"].startswith("beam-corot")]
    assert len(corot) == 1 and all(r["finite"] and r["energy_creating_frames"] == 0 and r["u_error"] < 0.05
                                   for r in corot), corot
    assert set(result["frame_ms"]) == models == set(result["step_ms"])
    for t in result["frame_ms"].values():   # one case of 21 frames, its first call left out
        assert t["frames"] == 20 and 0 < t["p50"] <= t["p99"] <= t["max"]
    assert "p99 / p50" in md


@pytest.mark.long
@needs_reference
def test_pareto_quick_places_the_shipped_models_against_the_fem(tmp_path):
    _bench("pareto", "--quick", "--out", str(tmp_path))
    result, md = _results(tmp_path, "pareto", png=True)
    names = [p["name"] for p in result["points"]]
    assert names == ["beam", "beam-linear", "FEM 5×2×2, mass ×64"] and len(result["test_sims"]) == 1
    for p in result["points"]:
        assert p["ms"] > 0 and np.isfinite([p["u"], p["v"], p["sigma"]]).all()
    assert result["front"] and set(result["front"]) <= set(names)
    assert "| published TIGNN (reference line) | — |" in md and "| beam |" in md


@pytest.mark.long
def test_scaling_quick_fits_the_growth_of_every_model_class(tmp_path):
    _bench("scaling", "--quick", "--linear", "5x2x2", "--corot", "5x2x2", "--gnn", "5x2x2,10x3x3", "--out",
           str(tmp_path))
    stem = json.loads(next(tmp_path.glob("scaling*.json")).read_text())["machine"]["backend"]
    result, md = _results(tmp_path, "scaling" if stem == "cpu" else f"scaling_{stem}", png=True)
    assert [r["nodes"] for r in result["linear"]] == [54] and [r["nodes"] for r in result["gnn"]] == [54, 176]
    assert [r["nodes"] for r in result["corot"]] == [54]
    assert result["corot"][0]["ainv"] == "32 modes + Schur complement (20²)"
    assert result["linear"][0]["ainv"] == "dense" and all(r["ms"] > 0 for r in result["linear"] + result["gnn"])
    assert "Corotational step time over the linear one's on the same mesh" in md
    assert result["fits"]["gnn_ms"]["meshes"] == 2 and result["fits"]["linear_ms"] is None
    assert "| 5×2×2 | 54 |" in md and "| 10×3×3 | 176 |" in md and "Fitted exponent" in md


@pytest.mark.long   # CI time (~30 s); the class itself is tested in tests/test_embedded.py
def test_embedded_quick_compares_the_cage_with_the_fine_model_and_times_both(tmp_path):
    _bench("embedded", "--quick", "--out", str(tmp_path))
    result, md = _results(tmp_path, "embedded")
    assert result["quick"] and "QUICK" in md and [r["case"] for r in result["accuracy"]] == ["patch 1x hold"]
    row = result["accuracy"][0]    # the 756-node mesh is its own cage: the two models are one
    assert row["u_error"] < 0.01 and row["energy_creating_frames"] == 0 and row["dent"] > 0
    (timed,) = result["timing"]
    assert timed["nodes"] == 756 and timed["cage_nodes"] == 756 and timed["embedded_p50"] > 0
    assert timed["corotational_p50"] > 0


@pytest.mark.long
@needs_reference
def test_fem_implicit_quick_compares_both_solvers_on_a_test_case(tmp_path):
    _bench("fem_implicit", "--quick", "--out", str(tmp_path))
    result, md = _results(tmp_path, "fem_implicit")
    assert [r["name"] for r in result["beam"]] == ["explicit (stable sub-step)", "implicit, 1 step(s) per frame"]
    assert "bunny" not in result and all(np.isfinite(r["u"]) for r in result["beam"])
    assert "| explicit (stable sub-step) |" in md and "QUICK" in md


@pytest.mark.long
def test_fem_throughput_small_run_times_each_variant(tmp_path):
    _bench("fem_throughput", "--scenes", "beam", "--substeps", "3", "--repeats", "1", "--batches", "2",
           "--naive-batches", "1", "--two-process-batches", "", "--out", str(tmp_path))
    result, md = _results(tmp_path, "fem_throughput")
    assert [(r["variant"], r["batch"]) for r in result["rows"]] == [
        ("trailing batch (solver)", 2), ("vmap (cases first)", 2), ("naive jax.grad + scatter", 1)]
    assert all(r["element_substeps_per_second"] > 0 for r in result["rows"]) and md.count("| beam |") == 3


@needs_reference
def test_abaqus_agreement_of_a_perturbed_copy_of_two_cases(tmp_path):
    ref = np.load(REFERENCE)
    rows = [8, 9]                                   # sims 9 (test) and 10 (test)
    z = ref["z"][rows].astype(np.float64)
    z[:, 1:] *= 1.001                               # 0.1 % off everywhere but the first frame
    ours = tmp_path / "ours.npz"
    np.savez(ours, z=z.astype(np.float32), q0=ref["q0"], sim_id=ref["sim_id"][rows],
             metadata=json.dumps({"material": "test", "damping": 1.0, "n_sub": 1, "load_interp": "linear"}))
    _bench("abaqus_agreement", "--ours", str(ours), "--out", str(tmp_path), timeout=120)
    result, md = _results(tmp_path, "abaqus_agreement", png=True)
    assert result["cases"] == [9, 10] and list(result["mean_relative_l2"]) == ["all (2 of 52)", "test (2 of 6)"]
    assert result["mean_relative_l2"]["test (2 of 6)"]["v"] == pytest.approx(1e-3, rel=0.05)
    assert "| test (2 of 6) |" in md


def test_datasets_reads_the_generation_time_of_each_data_set(tmp_path):
    path = tmp_path / "beam_small.npz"
    np.savez(path, z=np.zeros((3, 5, 4, 12), np.float32),
             metadata=json.dumps({"scene": "beam", "n_sub": 100, "wall_time_s": 12.5}))
    _bench("datasets", str(path), "--out", str(tmp_path), timeout=120)
    result, md = _results(tmp_path, "datasets")
    assert result["rows"] == [{"file": "beam_small.npz", "scene": "beam", "cases": 3, "frames": 4, "n_sub": 100,
                               "wall_time_s": 12.5, "paper_s": 795.0, "machine_load": ""}]
    assert "| beam_small.npz | beam | 3 | 4 | 100 | 12 | 795.0 |" in md


def test_large_deformation_bunny_presses_are_the_held_out_patch_loads_scaled_held_and_released():
    # its quick run needs the FEM's Newton preconditioner of the bunny (minutes): the loads are checked here
    sys.path.insert(0, str(BENCHMARKS))
    import large_deformation_bunny as B

    sc = B.scene()
    hold, nodes, inward = B.forces(sc, 30, 30.0, "hold", B.POSITIONS)
    release, nodes_r, _ = B.forces(sc, 30, 30.0, "release", B.POSITIONS)
    assert hold.shape == (2, 30, len(sc.points), 3) and np.array_equal(nodes, nodes_r)
    np.testing.assert_allclose(np.linalg.norm(hold[:, -1].sum(axis=1), axis=-1), 30.0, rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(inward, axis=1), 1.0, rtol=1e-5)
    for c in range(2):       # the total force points along the loaded node's inward normal
        np.testing.assert_allclose(hold[c, -1].sum(axis=0) / 30.0, inward[c], atol=1e-5)
    assert np.abs(release[:, B.RELEASE_AT:]).max() == 0.0
    np.testing.assert_array_equal(release[:, :B.RELEASE_AT], hold[:, :B.RELEASE_AT])
    assert hold[:, 0].sum() != 0 and np.abs(hold[:, 0]).max() < np.abs(hold[:, 10]).max()   # the 10-frame rise
