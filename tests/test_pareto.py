"""The pieces of benchmarks/pareto.py that decide its results: the Pareto front, the coarse-mesh transfer and
the mixed-precision step."""
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import pareto  # noqa: E402

from fem import box_hex_mesh, beam_mesh  # noqa: E402
from tignn_jax import data as D  # noqa: E402
from tignn_jax import model as M  # noqa: E402


def test_pareto_front_keeps_exactly_the_non_dominated_points():
    # (time, error): b is dominated by a (slower and worse); d ties a in time but is worse; e diverged (NaN)
    cost = [1.0, 2.0, 3.0, 1.0, 0.5, 10.0]
    error = [0.5, 0.6, 0.1, 0.7, np.nan, 0.05]
    assert pareto.pareto_front(cost, error).tolist() == [0, 2, 5]


def test_pareto_front_keeps_duplicates_of_a_front_point():
    # two identical points dominate nothing of each other: both stay
    assert pareto.pareto_front([1.0, 1.0, 2.0], [0.3, 0.3, 0.4]).tolist() == [0, 1]


def test_pareto_front_rejects_mismatched_inputs():
    with pytest.raises(ValueError, match="one length"):
        pareto.pareto_front([1.0, 2.0], [0.1])


def test_pareto_front_over_several_errors_needs_domination_in_all():
    # (time; u, v): b is cheaper and better in u than c but worse in v, so both stay; d is dominated by a
    cost = [1.0, 2.0, 3.0, 1.5]
    error = [[0.5, 0.5], [0.2, 0.9], [0.3, 0.1], [0.6, 0.6]]
    assert pareto.pareto_front(cost, error).tolist() == [0, 1, 2]
    assert pareto.pareto_front(cost, [e[0] for e in error]).tolist() == [0, 1]


def test_linear_frame_settles_on_the_static_solution_of_the_rest_stiffness():
    """The rest-linearised backward-Euler frame (the cheap FEM baseline) under a held load settles on
    K₀ u = f (dense K₀ from the same linearisation, clamped rows removed), with 1 and 2 solves per frame."""
    from fem import implicit

    divisions = (5, 2, 2)
    frame1, scene, _ = pareto.linear_frame(divisions, 1)
    frame2, _, _ = pareto.linear_frame(divisions, 2)
    lin = pareto._LINEAR[divisions]
    n = len(scene.points)
    k = np.zeros((n, n, 3, 3))
    k[lin.k_rows, lin.k_cols] = lin.k_blocks
    k = k.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)
    free = np.repeat(np.asarray(scene.node_type) == 0, 3)
    f = np.zeros((n, 3))
    f[np.asarray(scene.points)[:, 0] > 40.0 - 1e-6, 2] = -100.0   # u ~ 0.1: far above float32 rounding of q
    u_static = np.zeros(3 * n)
    u_static[free] = np.linalg.solve(k[np.ix_(free, free)], f.reshape(-1)[free])
    fj = jnp.asarray(f, jnp.float32)
    for frame in (frame1, frame2):
        z = jnp.concatenate([jnp.asarray(scene.points, jnp.float32), jnp.zeros((n, 9))], 1)
        for _ in range(400):
            z = frame(z, fj, fj)
        u = np.asarray(z[:, :3]) - scene.points
        assert np.linalg.norm(u.reshape(-1) - u_static) < 1e-3 * np.linalg.norm(u_static)
        # at rest: the motion per frame is at float32 rounding of the positions (~40 × 6e-8 per step)
        assert float(jnp.abs(z[:, 3:6]).max()) * 0.05 < 2e-3 * np.abs(u_static).max()
    assert isinstance(lin, implicit.RestLinearization)


@pytest.mark.parametrize("divisions", [(10, 3, 3), (14, 4, 4)])
def test_trilinear_interpolation_reproduces_a_linear_field_exactly(divisions):
    # trilinear shape functions contain the linear polynomials: a homogeneous deformation is transferred exactly
    fine, _, _ = beam_mesh()
    coarse, _ = box_hex_mesh(pareto.BEAM_SIZE, divisions)
    w = pareto.trilinear_weights(fine, divisions)
    a = np.array([[1.1, 0.2, -0.3], [0.05, 0.9, 0.1], [-0.2, 0.3, 1.2]])
    b = np.array([0.5, -1.0, 2.0])
    np.testing.assert_allclose(w @ (coarse @ a.T + b), fine @ a.T + b, atol=1e-10)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)


def test_interpolation_at_coarse_nodes_is_the_identity():
    # a reference node that is also a coarse node takes that node's value alone
    divisions = (10, 5, 5)
    coarse, _ = box_hex_mesh(pareto.BEAM_SIZE, divisions)
    w = pareto.trilinear_weights(coarse, divisions)
    np.testing.assert_allclose(w, np.eye(len(coarse)), atol=1e-12)


def test_load_transfer_conserves_total_force_and_moment():
    # W.T f is the consistent nodal load of point forces: same resultant and same moment about the origin
    fine, _, _ = beam_mesh()
    divisions = (10, 3, 3)
    coarse, _ = box_hex_mesh(pareto.BEAM_SIZE, divisions)
    w = pareto.trilinear_weights(fine, divisions)
    f = np.random.default_rng(0).normal(size=fine.shape)
    fc = w.T @ f
    np.testing.assert_allclose(fc.sum(0), f.sum(0), atol=1e-10)
    np.testing.assert_allclose(np.cross(coarse, fc).sum(0), np.cross(fine, f).sum(0), atol=1e-8)


def test_trilinear_weights_reject_points_outside_the_box():
    with pytest.raises(ValueError, match="inside the box"):
        pareto.trilinear_weights(np.array([[41.0, 1.0, 1.0]]), (10, 3, 3))


def _tiny_model():
    data = D.synthetic_beam(cases=2, frames=3)
    rows = D.split_rows(data, "train")
    norm = {k: jnp.asarray(v) for k, v in D.normalization(data, rows).items()}
    nt = jnp.asarray(data.node_type, jnp.int32)
    topo = M.topology(data.edges[0], data.edges[1], len(data.node_type), data.q0)
    cfg = M.ModelConfig(hidden=8, passes=2)
    z, f = jnp.asarray(data.z[0, 2]), jnp.asarray(data.f[0, 2])
    w = M.init_weights(jax.random.PRNGKey(1), cfg, norm, z, f, nt, topo)
    return w, cfg, norm, z, f, nt, topo


def test_mixed_step_in_float32_is_the_model_step():
    # the mixed-precision step only changes the network's dtype; in float32 it must be model.step_state
    w, cfg, norm, z, f, nt, topo = _tiny_model()
    ref = jax.jit(lambda z: M.step_state(w, cfg, norm, z, f, nt, topo))(z)
    out = jax.jit(lambda z: pareto.step_mixed(w, cfg, norm, z, f, nt, topo, jnp.float32))(z)
    np.testing.assert_allclose(np.asarray(out), np.asarray(ref), rtol=1e-5, atol=1e-6)


def test_mixed_step_in_bfloat16_keeps_a_float32_state_near_the_float32_step():
    # bfloat16 network, float32 state: the increment is perturbed at the ~1 % level, the state stays float32
    w, cfg, norm, z, f, nt, topo = _tiny_model()
    ref = np.asarray(jax.jit(lambda z: M.step_state(w, cfg, norm, z, f, nt, topo))(z))
    w16 = pareto.cast_weights(w, jnp.bfloat16)
    out = jax.jit(lambda z: pareto.step_mixed(w16, cfg, norm, z, f, nt, topo, jnp.bfloat16))(z)
    assert out.dtype == jnp.float32
    dz_ref, dz = ref - np.asarray(z), np.asarray(out) - np.asarray(z)
    assert np.linalg.norm(dz - dz_ref) <= 0.1 * np.linalg.norm(dz_ref)


def test_each_step_is_timed_under_both_xla_configurations_and_keeps_the_faster():
    # best_config picks each name's faster configuration and keeps every median; the compiled configurations
    # compute the same step (the option changes how XLA:CPU runs it, not what)
    times = {"a|default": {"p50_ms": 3.0, "p90_ms": 4.0}, "a|ynn-off": {"p50_ms": 2.0, "p90_ms": 2.5},
             "b x|default": {"p50_ms": 1.0, "p90_ms": 1.1}, "b x|ynn-off": {"p50_ms": 5.0, "p90_ms": 6.0}}
    best = pareto.best_config(times)
    assert best["a"]["p50_ms"] == 2.0 and best["a"]["p90_ms"] == 2.5 and best["a"]["xla"] == "ynn-off"
    assert best["b x"]["xla"] == "default" and best["b x"]["p50_by_xla"] == {"default": 1.0, "ynn-off": 5.0}
    fn = jax.jit(lambda x, w: jnp.tanh(x @ w).sum(0))
    args = (jnp.ones((64, 32)), jnp.full((32, 16), 0.01))
    compiled = pareto.compiled_configs(fn, args)
    assert set(compiled) == set(pareto.XLA_CONFIGS)
    for c in compiled.values():
        np.testing.assert_allclose(np.asarray(c(*args)), np.asarray(fn(*args)), rtol=1e-5)
    timed = pareto.time_configs({"f": fn}, args, repeats=5)
    assert set(timed) == {"f"} and set(timed["f"]["p50_by_xla"]) == set(pareto.XLA_CONFIGS)


def test_the_shipped_verdict_names_each_front_it_is_on_or_off():
    # a point off the u-only front can still be on the all-error front: the text must not join them with "and"
    assert pareto.shipped_verdict({"on_front": False, "on_front_uvs": True}) == (
        "does NOT lie on the (time, u) front but lies on the (time, u, v, σ) front")
    assert pareto.shipped_verdict({"on_front": True, "on_front_uvs": True}).endswith("and on the (time, u, v, σ) front")
    assert pareto.shipped_verdict({"on_front": False, "on_front_uvs": False}).endswith("nor on the (time, u, v, σ) front")


def test_cached_errors_of_a_model_are_stale_once_its_weights_change():
    # errors cached for one set of weights must not be reported for another (the shipped model is retrained)
    w = {"weights": {"a": np.ones((2, 3), np.float32), "b": [np.zeros(4, np.float32)]}}
    fp = pareto.weights_fingerprint(w)
    assert fp == pareto.weights_fingerprint({"weights": {"a": np.ones((2, 3), np.float32),
                                                         "b": [np.zeros(4, np.float32)]}})
    changed = {"weights": {"a": np.ones((2, 3), np.float32), "b": [np.array([0, 0, 1e-7, 0], np.float32)]}}
    reshaped = {"weights": {"a": np.ones((3, 2), np.float32), "b": [np.zeros(4, np.float32)]}}
    assert pareto.weights_fingerprint(changed) != fp and pareto.weights_fingerprint(reshaped) != fp
    cache = {"m": {"u": 0.05, "weights_sha256": fp}, "old": {"u": 0.05}}
    assert not pareto.stale(cache, "m", fp)
    assert pareto.stale(cache, "m", pareto.weights_fingerprint(changed))
    assert pareto.stale(cache, "old", fp) and pareto.stale(cache, "missing", fp)


def test_labels_of_crowded_points_are_moved_apart_and_lone_ones_stay_beside_their_marker():
    # three markers at one spot get three labels a line apart; a far marker keeps the default offset
    xy = np.array([[100.0, 100.0], [101.0, 100.0], [100.5, 101.0], [600.0, 300.0]])
    offsets = pareto.spread_labels(xy)
    assert offsets[3] == (4, 3.0)
    ys = sorted(xy[i, 1] + offsets[i][1] for i in range(3))
    assert all(b - a >= 9.0 - 1e-9 for a, b in zip(ys, ys[1:]))


def test_report_only_quick_reads_and_writes_the_quick_result(tmp_path, monkeypatch, capsys):
    """--report-only --quick regenerates the quick result where the quick run writes it, and says which file
    is missing when there is none (it used to read the full result whatever --quick said)."""
    monkeypatch.setattr(pareto, "RUNS", tmp_path)
    with pytest.raises(SystemExit):
        pareto.main(["--quick", "--report-only"])
    assert "pareto_quick.json" in capsys.readouterr().err
    full = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "pareto.json"
    if not full.exists():
        pytest.skip("no committed pareto.json")
    (tmp_path / "quick").mkdir()
    (tmp_path / "quick" / "pareto_quick.json").write_text(full.read_text())
    assert pareto.main(["--quick", "--report-only"]) == 0
    assert (tmp_path / "quick" / "pareto_quick.md").read_text().startswith("#")
    assert (tmp_path / "quick" / "pareto_quick.png").stat().st_size > 0
