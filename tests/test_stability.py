"""The fast subset of benchmarks/stability.py: short rollouts of the shipped beam model under the five stress
loadings (against the FEM on the same loads), its guards, and the FEM past its stability limit."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import stability  # noqa: E402

from tignn_jax import api  # noqa: E402


@pytest.fixture(scope="module")
def beam_runs():
    if not (Path(api.MODELS_DIR) / "beam-abaqus" / "model.npz").exists():
        pytest.skip("no shipped beam-abaqus model in this checkout")
    return stability.model_runs("beam", "beam-abaqus", steps=24, fem_steps=10)   # the FEM over half the ramp


def test_short_rollouts_stay_finite_and_near_the_fem(beam_runs):
    runs = beam_runs["runs"]
    assert set(runs) == set(stability.SCENARIOS)
    for name, run in runs.items():
        assert run["nan_or_inf"] == 0, name
        assert len(run["series"]["u_max"]) == 25
        assert run["first_step_non_finite"] is None, name
    # within the training horizon, on a training-like load, the model follows the FEM
    assert runs["constant"]["u_error_at_fem_horizon"] < 0.15
    assert runs["release"]["u_error_at_fem_horizon"] < 0.3


def test_force_guard_flags_the_3x_load_only(beam_runs):
    runs = beam_runs["runs"]
    assert runs["3x load"]["guard"]["out_of_distribution"]
    assert runs["3x load"]["guard"]["max_force_ratio"] > 2.5
    assert not runs["constant"]["guard"]["out_of_distribution"]


def test_entropy_diagnostics_are_reported_per_step(beam_runs):
    for run in beam_runs["runs"].values():
        assert 0.0 <= run["entropy_production_non_negative_fraction"] <= 1.0
        assert 0.0 <= run["entropy_non_decreasing_fraction"] <= 1.0
        assert np.all(np.isfinite(run["series"]["S"]))


def test_fem_beyond_its_stable_step_reports_rather_than_hides():
    # 1.5x the stable sub-step: the run must end in a reported inversion (or stay bounded), never silent NaN
    (row,) = stability.fem_limit(factors=(1.5,), frames=4)
    if row["nan_or_inf"] > 0 or row["inverted_element"] >= 0:
        assert row["reported"], row
    else:
        assert np.isfinite(row["max_u"])


def test_a_flagged_run_says_which_state_component_left_the_envelope_and_where(beam_runs):
    # A flagged run names the component (a velocity or stress column, or the displacement: what state_check
    # measures) beyond the state_check tolerance times the training envelope, and the node's distance from
    # the load.
    flagged = [run for run in beam_runs["runs"].values() if run["first_step_state_flagged"] is not None]
    assert flagged
    for run in flagged:
        how = run["leaves_envelope_by"]
        assert how["component"] in stability.COLUMNS[3:] + ("|u|",)
        assert how["envelope_ratio"] > 1.5
        assert how["hops_from_load"] is not None and how["hops_from_load"] >= 0
    quiet = [run for run in beam_runs["runs"].values() if run["first_step_state_flagged"] is None]
    assert all(run["leaves_envelope_by"] is None for run in quiet)


def test_guarded_rollouts_stay_finite_and_match_unflagged_plain_runs(beam_runs):
    # Through api.guarded_stepper (every policy) and api.fallback_stepper the rollouts are finite; where the
    # plain rollout never left the envelope, no step is flagged and the guarded rollout's error against the FEM
    # is the plain one's (the consistency trigger also flags a step that departs from the linear one while the
    # state is still inside the envelope, e.g. at the release: it is checked for finiteness only).
    for name, run in beam_runs["runs"].items():
        assert set(api.GUARD_POLICIES) | {"fallback"} <= set(run["guarded"]) <= \
            set(api.GUARD_POLICIES) | {"fallback", "fallback+consistency"}   # the latter with the reference data
        for policy, g in run["guarded"].items():
            assert g["nan_or_inf"] == 0, (name, policy)
            assert len(g["u_error"]) == len(run["series"]["u_error"])
            if policy == "fallback+consistency":
                continue
            if run["first_step_state_flagged"] is None and name != "noise":   # noise: another random draw
                assert g["flagged_steps"] == 0, (name, policy)
                np.testing.assert_allclose(g["u_error"], run["series"]["u_error"], rtol=1e-5, atol=1e-7)
            elif g["flagged_steps"]:
                assert g["first_flagged_step"] >= 1
