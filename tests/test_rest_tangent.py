"""benchmarks/rest_tangent.py: implicit steps on the rest tangent, against known answers on a small hex bar of
the beam's nearly incompressible material."""
import sys
from pathlib import Path

import numpy as np
import pytest

import fem
from fem import implicit
from fem.meshes import mesh_edges

pytestmark = pytest.mark.slow   # a research branch's checks: `pytest -m slow` (not in the default run)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import rest_tangent as rt  # noqa: E402

H, C10, C01, D1 = 0.05, 1.5e5, 5e3, 1e-7


def _bar(clamped: bool):
    pts, cells = fem.box_hex_mesh((8.0, 2.0, 2.0), (4, 1, 1))
    node_type = (pts[:, 0] < 1e-9).astype(np.int8) if clamped else np.zeros(len(pts), np.int8)
    material = fem.mooney_rivlin(c10=C10, c01=C01, d1=D1, density=7.135e-3)
    problem = fem.setup(pts, cells, material=material, frame_dt=H, n_frames=1, clamped=np.where(node_type)[0],
                        damping=60.0, n_sub=1)
    return pts, node_type, problem, material, implicit.rest_linearization(problem, material), mesh_edges(cells)


# One kind per code path of the step (the kinds of one family differ only in their iteration counts): each kind
# is a separate XLA compilation of an unrolled solve, 15-40 s apiece, and all twelve made this file the suite's
# slowest (409 s).
NEWTON_KINDS = ("backward Euler, 1 Newton step, 5 CG",                     # the velocity predictor
                "backward Euler, 2 Newton steps from v' = 0, 3 CG each")   # v' = 0: tignn_jax.newton's default
PATHS = ("linear", "exact force", "exact force, rotated solve", next(iter(rt.ITERATIONS)), *NEWTON_KINDS)


def _steps(clamped, kinds=PATHS):
    pts, node_type, problem, material, lin, edges = _bar(clamped)
    ops = rt.scene_operators(problem, material, lin, node_type, pts, H)
    return pts, {k: rt.make_step(k, ops, edges) for k in kinds}


def test_the_tested_kinds_cover_every_code_path_of_the_benchmark():
    assert set(PATHS) <= set(rt.KINDS) and set(NEWTON_KINDS) <= set(rt.NEWTON_CG)
    assert {rt.NEWTON_CG[k][2] for k in NEWTON_KINDS} == {"velocity", "zero"}   # both predictors


def _rotation(th):
    return np.array([[np.cos(th), -np.sin(th), 0.0], [np.sin(th), np.cos(th), 0.0], [0.0, 0.0, 1.0]])


def _state(q):
    z = np.zeros((len(q), 12), np.float32)
    z[:, :3] = q
    return z


def test_the_two_steps_agree_to_second_order_in_the_displacement():
    # From a bent state at rest, the exact force differs from K₀u at higher order in u: the two steps' velocity
    # changes differ by a share of the change that at least halves with the amplitude (difference O(ε²) or
    # smaller, each change ∝ ε; measured: 0.044, 0.011, 0.0021 at tip amplitudes 0.4, 0.2, 0.1 of the 8-long
    # bar, so O(ε³) for this symmetric bend; below 0.1 float32 rounding takes over).
    pts, steps = _steps(clamped=True, kinds=rt.KINDS[:2])
    bend = np.zeros_like(pts)
    bend[:, 2] = (pts[:, 0] / 8.0) ** 2
    f = np.zeros_like(pts, dtype=np.float32)
    share = []
    for eps in (0.4, 0.2):
        z = _state(pts + eps * bend)
        lin, exact = (np.asarray(steps[k](z, f), np.float64) for k in rt.KINDS[:2])
        share.append(np.linalg.norm(exact[:, 3:6] - lin[:, 3:6]) / np.linalg.norm(lin[:, 3:6]))
    assert share[0] < 0.1 and share[0] / share[1] > 2.0, share


def test_a_rigid_rotation_stays_at_rest_only_with_the_exact_force():
    # An unclamped bar turned rigidly by 0.1 rad: no internal force and no stress, so every step with the exact
    # force leaves it at rest, while the rest linearisation sees a strain div u = 2(cos θ − 1) and responds with
    # its pressure, K₀u ≠ 0, and a velocity (the stress pressure itself: tests/test_prior_jump.py).
    pts, steps = _steps(clamped=False)
    c = pts.mean(0)
    z = _state((pts - c) @ _rotation(0.1).T + c)
    f = np.zeros_like(pts, dtype=np.float32)
    out = {k: np.asarray(st(z, f), np.float64) for k, st in steps.items()}
    lin = out["linear"]
    scale = np.abs(pts).max()
    for kind in PATHS[1:]:
        assert np.abs(out[kind][:, 3:6]).max() * H < 1e-4 * scale, kind      # stays where it is
        assert np.abs(out[kind][:, 6:]).max() < 1e-3 * C10, kind              # and unstressed
    assert np.abs(lin[:, 3:6]).max() * H > 1e-3 * scale          # the linear step moves it (2.4e-2 per step)


def test_errors_count_non_finite_rollouts_and_their_first_bad_step():
    true = np.zeros((3, 4, 2, 12))
    true[..., 0] = np.arange(4)[None, :, None]
    pred = true.copy()
    pred[1, 2:, 0, 0] = np.nan
    out = rt.errors(pred, true, np.zeros((2, 3)))
    assert out["cases"] == 3 and out["finite"] == 2 and out["first_non_finite_step"] == [2]
    assert out["u"] == 0.0 and out["u_max"] == 0.0
    with pytest.raises(ValueError, match="kind"):
        rt.make_step("nonlinear", None)


def test_newton_cg_step_keeps_rest_exactly_and_follows_the_linear_step_at_small_loads():
    # From rest with no force the residual is zero: the conjugate gradients must not divide 0 by 0. Under a
    # small tip load the body stays in the linear range, so one Newton step with the exact tangent lands where the
    # rest-linearised backward-Euler step does (to 1 % of its velocity change).
    pts, steps = _steps(clamped=True, kinds=("linear", *NEWTON_KINDS))
    z, f = _state(pts), np.zeros_like(pts, dtype=np.float32)
    for kind in NEWTON_KINDS:
        np.testing.assert_array_equal(np.asarray(steps[kind](z, f)), z)
    f[np.argmax(pts[:, 0]), 2] = -10.0
    lin = np.asarray(steps["linear"](z, f), np.float64)
    for kind in NEWTON_KINDS:
        out = np.asarray(steps[kind](z, f), np.float64)
        assert np.all(np.isfinite(out))
        assert np.linalg.norm(out[:, 3:6] - lin[:, 3:6]) < 0.01 * np.linalg.norm(lin[:, 3:6]), kind
