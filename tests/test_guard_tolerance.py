"""benchmarks/guard_tolerance.py on a few steps: the sweep's bookkeeping, its report and its argument checks."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import guard_tolerance as GT  # noqa: E402


@pytest.fixture(scope="module")
def short_sweep():
    # a tolerance so loose that nothing is handed over, against the shipped one, over the ramp's first 24 steps, the FEM over 6
    return GT.sweep("beam-abaqus-64x2", [1.5, 1e6], steps=24, fem_steps=6)


def test_sweep_reports_every_loading_and_a_loose_guard_hands_over_no_more(short_sweep):
    runs = short_sweep["runs"]
    assert set(runs) == {1.5, 1e6}
    for tol, rows in runs.items():
        assert set(rows) == set(GT.stability.SCENARIOS)
        for r in rows.values():
            assert r["nan_or_inf"] == 0
            assert 0 <= r["u_error_at_fem_horizon"] <= r["u_error_max"] < 0.5   # the start of the ramp: near the FEM
            assert r["u_error_mean"] <= r["u_error_max"]
    # the loose guard still hands over a non-finite state (the fingertip loading's network diverges by step 24);
    # the 3x load leaves 1.5x the envelope within 24 steps
    assert all(runs[1e6][s]["hand_overs"] <= runs[1.5][s]["hand_overs"] for s in runs[1.5])
    assert runs[1.5]["3x load"]["hand_overs"] > runs[1e6]["3x load"]["hand_overs"] == 0
    mean = short_sweep["mean"][1.5]
    assert mean["u_error_mean"] == pytest.approx(np.mean([r["u_error_mean"] for r in runs[1.5].values()]))


def test_report_has_a_row_per_tolerance_and_loading(short_sweep, tmp_path, monkeypatch):
    monkeypatch.setattr(GT, "RESULTS", tmp_path)
    result = {**short_sweep, "machine": {"cpu": "test", "cores": 2, "jax": "x"},
              "args": {"model": "beam-abaqus-64x2", "hold": 30, "steps": 24, "fem_steps": 6}, "wall_s": 1.0}
    GT.write(result, "t")
    md = (tmp_path / "t.md").read_text()
    assert md.count("| 1.5 |") == len(GT.stability.SCENARIOS) + 1 and "mean of the five" in md
    assert (tmp_path / "t.json").exists()


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="fem_steps"):
        GT.sweep("beam-abaqus-64x2", [1.5], steps=24, fem_steps=30)
    with pytest.raises(ValueError, match="at least 20"):
        GT.sweep("beam-abaqus-64x2", [1.5], steps=6, fem_steps=4)
    with pytest.raises(SystemExit, match="tolerances"):
        GT.main(["--tolerances", "1.5,x"])
    with pytest.raises(SystemExit, match="positive"):
        GT.main(["--tolerances", "0"])
