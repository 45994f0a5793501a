"""The fast subset of benchmarks/stability.py: short rollouts of the shipped beam under the five stress loadings
against the FEM's backward-Euler step (`tignn_jax.fem_stepper`), its guards and energy balance, and the explicit FEM
past its stability limit."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import stability  # noqa: E402


@pytest.fixture(scope="module")
def beam_runs():
    """Every loading of the beam, plain and guarded, against the rest-linearised reference (cheap to compile: the
    guard and energy checks below do not need the FEM's Newton step)."""
    return stability.scene_runs("beam", steps=24, reference_steps=24, reference="linear", log=lambda *a: None)


@pytest.mark.long
def test_short_rollouts_stay_finite_and_near_the_fem():
    beam_runs = stability.scene_runs("beam", steps=24, reference_steps=24, log=lambda *a: None)
    runs = beam_runs["runs"]
    assert beam_runs["reference"] == "fem_stepper(beam-linear)"
    assert set(runs) == set(stability.SCENARIOS)
    for name, run in runs.items():
        assert run["nan_or_inf"] == 0, name
        assert len(run["series"]["u_max"]) == 25
        assert run["first_step_non_finite"] is None, name
    for name, ref in beam_runs["reference_runs"].items():
        assert ref["nan_or_inf"] == 0 and ref["frames"] == 24, name
    # within the training horizon, on a training-like load, the model follows the FEM
    assert runs["constant"]["u_error_at_reference_horizon"] < 0.15
    assert runs["release"]["u_error_at_reference_horizon"] < 0.3


def test_force_guard_flags_the_3x_load_only(beam_runs):
    runs = beam_runs["runs"]
    assert runs["3x load"]["force_guard"]["out_of_distribution"]
    assert runs["3x load"]["force_guard"]["max_force_ratio"] > 2.5
    assert not runs["constant"]["force_guard"]["out_of_distribution"]


def test_the_linear_model_never_creates_energy(beam_runs):
    # backward Euler of a PSD stiffness with mass damping: every frame dissipates (D = W − ΔE ≥ 0, up to the
    # rounding of the float32 states), noise runs included (D is measured from each frame's noisy input)
    for name, run in beam_runs["runs"].items():
        energy = run["energy"]
        assert energy["dissipative_fraction"] == 1.0, (name, energy)
        assert energy["E_max"] >= energy["E_last"] >= 0.0
        assert np.all(np.isfinite(run["series"]["E"])) and len(run["series"]["E"]) == 25


@pytest.mark.optimized
def test_fem_beyond_its_stable_step_reports_rather_than_hides():
    # 1.5x the stable sub-step: the explicit FEM goes unstable within the first frame (an element turns inside out,
    # then NaN), and the run says so, naming the element and the time, instead of handing back silent NaN
    (row,) = stability.fem_limit(factors=(1.5,), frames=4)
    assert row["inverted_element"] >= 0 and row["nan_or_inf"] > 0, row
    assert any(f"element {row['inverted_element']} inverted" in r for r in row["reported"]), row


def test_a_flagged_run_says_which_state_component_left_the_envelope_and_where(beam_runs):
    # A flagged run names the component (a velocity or stress column, or the displacement: what the state guard
    # measures) beyond the guard's tolerance times the training envelope, and the node's distance from the load.
    flagged = [run for run in beam_runs["runs"].values() if run["first_step_state_flagged"] is not None]
    assert flagged
    for run in flagged:
        how = run["leaves_envelope_by"]
        assert how["component"] in stability.COLUMNS[3:] + ("|u|",)
        assert how["envelope_ratio"] > stability.TOLERANCE
        assert how["hops_from_load"] is not None and how["hops_from_load"] >= 0
    quiet = [run for run in beam_runs["runs"].values() if run["first_step_state_flagged"] is None]
    assert all(run["leaves_envelope_by"] is None for run in quiet)


def test_guarded_rollouts_stay_finite_and_match_unflagged_plain_runs(beam_runs):
    # Through guarded_stepper (clip, reset) and fallback_stepper the rollouts are finite; where the plain rollout
    # never left the envelope, no step is flagged and the guarded rollout's error against the FEM is the plain
    # one's (the noise runs draw the same noise).
    for name, run in beam_runs["runs"].items():
        assert set(run["guarded"]) == set(stability.POLICIES)
        for policy, g in run["guarded"].items():
            assert g["nan_or_inf"] == 0, (name, policy)
            assert len(g["u_error"]) == len(run["series"]["u_error"])
            if run["first_step_state_flagged"] is None:
                assert g["flagged_steps"] == 0, (name, policy)
                np.testing.assert_allclose(g["u_error"], run["series"]["u_error"], rtol=1e-5, atol=1e-7)
            elif g["flagged_steps"]:
                assert g["first_flagged_step"] >= 1
