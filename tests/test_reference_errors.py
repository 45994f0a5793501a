"""The shipped beams' errors on the Abaqus reference data's published split, as recorded before the library's
restructuring (rollout from each case's first state; mean relative L2 over snapshots and cases, all nodes)."""
import numpy as np
import pytest

import tignn_jax as T
from tignn_jax import data as D
from tignn_jax import evaluation as EV
from tignn_jax.simulators import RestStartGNN

# (model, split): q, v, σ, u at 680d0e9; v differs by float32 rounding of the step's two algebraic forms
RECORDED = {("beam", "test"): (0.00465, 0.08574, 0.0597, 0.04161),
            ("beam", "val"): (0.01957, 0.19157, 0.13007, 0.09389),
            ("beam-linear", "test"): (0.00505, 0.09153, 0.06294, 0.05071)}
PUBLISHED_TEST = (0.0041, 0.017, 0.095, 0.071)   # the published TIGNN's test errors: q, v, σ, u


@pytest.fixture(scope="module")
def reference():
    path = D.reference_path()
    if not path.exists():
        pytest.skip(f"the Abaqus reference data are not at {path}")
    return D.load(path)


@pytest.mark.parametrize("model,split", sorted(RECORDED))
def test_errors_on_the_reference_split_are_as_recorded(reference, model, split):
    params, _ = T.load_pretrained(model)
    report, _ = EV.evaluate(params, reference, (split,), structure=False)
    got = [report[split]["all"][v]["mean"] for v in EV.VARIABLES]
    want = RECORDED[(model, split)]
    assert np.allclose(got[0], want[0], rtol=2e-3) and np.allclose(got[2:], want[2:], rtol=2e-3)
    assert np.allclose(got[1], want[1], rtol=1e-2)


def test_the_beam_beats_the_rest_linearisation_on_the_test_split(reference):
    errs = {}
    for model in ("beam", "beam-linear"):
        report, _ = EV.evaluate(T.load_pretrained(model)[0], reference, ("test",), structure=False)
        errs[model] = report["test"]["all"]["u"]["mean"]
    assert errs["beam"] < errs["beam-linear"]


def test_the_corotational_beam_beats_the_published_network_on_the_test_split(reference):
    params, _ = T.load_pretrained("beam-corot")
    rows = D.split_rows(reference, "test")
    pred = EV.rollout_cases(params, reference, rows)
    got = EV.relative_errors(pred, reference.z[rows], reference.q0)[:, 1:].mean((0, 1))   # q, v, σ, u
    assert all(g < p for g, p in zip(got, PUBLISHED_TEST)), got
    # as measured with the FEM's Mooney–Rivlin energy and the Schur-complement preconditioner (a solve to 1 % carries
    # its own error into σ, whose pressure is κ times the step's linearised volume change; σ was 0.0238 with the
    # energy linear in each element's turned frame)
    np.testing.assert_allclose(got, (0.000634, 0.01064, 0.01898, 0.01426), rtol=0.02)
    # v in the data's convention: the data's v is numpy.gradient of their q (a central difference); the model's own
    # v is backward Euler's (q_k+1 − q_k)/Δt, half a frame behind it. The same difference of the model's own q
    # halves the v error: the rest is the trajectory's
    assert np.abs(np.gradient(reference.z[rows, :, :, :3].astype(np.float64), float(reference.dt), axis=1,
                              edge_order=2) - reference.z[rows, :, :, 3:6]).max() < 1e-3 * np.abs(
        reference.z[rows, :, :, 3:6]).max()
    fd = pred.copy()
    fd[..., 3:6] = np.gradient(pred[..., :3].astype(np.float64), float(reference.dt), axis=1, edge_order=2)
    v_fd = EV.relative_errors(fd, reference.z[rows], reference.q0)[:, 1:, 1].mean()
    np.testing.assert_allclose(v_fd, 0.00566, rtol=0.03)
    assert v_fd < 0.6 * got[1]


def _test_errors_from_rest(reference, model: str) -> np.ndarray:
    """A shipped model's mean q, v, σ, u errors on the test split, each case rolled out from its first state with
    v = 0 (the body's true state at rest) instead of the data's finite-difference velocity."""
    params, _ = T.load_pretrained(model)
    rows = D.split_rows(reference, "test")
    rest = reference.z.copy()
    rest[:, 0, :, 3:6] = 0.0
    pred = EV.rollout_cases(params, reference._replace(z=rest), rows)
    return EV.relative_errors(pred, reference.z[rows], reference.q0)[:, 1:].mean((0, 1))


def test_the_corotational_beam_beats_the_published_network_from_rest(reference):
    # from rest (v = 0 at t = 0, the body's true first state) instead of the data's finite-difference velocity,
    # which holds the next two frames' positions: the published network started from that velocity
    got = _test_errors_from_rest(reference, "beam-corot")
    assert all(g < p for g, p in zip(got, PUBLISHED_TEST)), got
    np.testing.assert_allclose(got, (0.00066, 0.0152, 0.0222, 0.0179), rtol=0.03)


def test_the_reproduction_beats_the_published_network_from_the_data_first_state(reference):
    # the paper's network, reproduced (`beam-tignn`): from each case's first state, as the published errors were
    # measured; the data's first velocity there is a finite difference of the next two frames' positions
    params, _ = T.load_pretrained("beam-tignn")
    assert isinstance(params["model"], RestStartGNN) and params["model"].config.passes == 2
    report, _ = EV.evaluate(params, reference, ("test",), structure=False)
    got = [report["test"]["all"][v]["mean"] for v in EV.VARIABLES]
    assert all(g < p for g, p in zip(got, PUBLISHED_TEST)), got
    np.testing.assert_allclose(got, (0.00209, 0.00744, 0.0879, 0.0398), rtol=5e-3)


def test_the_reproduction_beats_the_published_network_from_rest(reference):
    # from rest (v = 0 at t = 0): `RestStartGNN` gives the network the quasi-static rate of the first frame's load,
    # K₀⁻¹f/Δt, for the data's finite-difference velocity; the bare network does not move from there (u 0.994)
    got = _test_errors_from_rest(reference, "beam-tignn")
    assert all(g < p for g, p in zip(got, PUBLISHED_TEST)), got
    np.testing.assert_allclose(got, (0.00249, 0.0150, 0.0872, 0.0452), rtol=1e-2)


def test_the_reproduction_follows_a_test_case_from_its_rest_graph_through_the_public_step(reference):
    # as a user runs it: the rest graph load_pretrained returns, stepped by tignn_jax.step under a test case's loads
    params, graph = T.load_pretrained("beam-tignn")
    case = D.split_rows(reference, "test")[0]
    np.testing.assert_array_equal(np.asarray(graph.nodes["z"])[:, :3], reference.z[case, 0, :, :3])
    for f in reference.f[case]:
        graph = T.step(params, graph, f)
    u = np.asarray(graph.nodes["z"])[:, :3] - reference.q0
    u_ref = reference.z[case, -1, :, :3] - reference.q0
    assert np.linalg.norm(u - u_ref) < 0.07 * np.linalg.norm(u_ref)   # measured 0.049
