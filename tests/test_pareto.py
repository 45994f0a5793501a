"""The pieces of benchmarks/pareto.py that decide its results: the Pareto front, the coarse-mesh transfer, the
timing under both XLA configurations and the report."""
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import pareto  # noqa: E402

from fem import box_hex_mesh, beam_mesh  # noqa: E402


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
    timed = pareto.time_configs({"f": (fn, args)}, repeats=5)
    assert set(timed) == {"f"} and set(timed["f"]["p50_by_xla"]) == set(pareto.XLA_CONFIGS)
    plain = pareto.time_configs({"f": (fn, args)}, repeats=5, configs=False)
    assert set(plain["f"]["p50_by_xla"]) == {"default"} and plain["f"]["xla"] == "default"


def test_the_shipped_verdict_names_each_front_it_is_on_or_off():
    # a point off the u-only front can still be on the all-error front: the text must not join them with "and"
    assert pareto.shipped_verdict({"on_front": False, "on_front_uvs": True}) == (
        "does NOT lie on the (time, u) front but lies on the (time, u, v, σ) front")
    assert pareto.shipped_verdict({"on_front": True, "on_front_uvs": True}).endswith("and on the (time, u, v, σ) front")
    assert pareto.shipped_verdict({"on_front": False, "on_front_uvs": False}).endswith(
        "nor on the (time, u, v, σ) front")


def test_labels_of_crowded_points_are_moved_apart_and_lone_ones_stay_beside_their_marker():
    # three markers at one spot get three labels a line apart; a far marker keeps the default offset
    xy = np.array([[100.0, 100.0], [101.0, 100.0], [100.5, 101.0], [600.0, 300.0]])
    offsets = pareto.spread_labels(xy)
    assert offsets[3] == (4, 3.0)
    ys = sorted(xy[i, 1] + offsets[i][1] for i in range(3))
    assert all(b - a >= 9.0 - 1e-9 for a, b in zip(ys, ys[1:]))


def test_newton_settings_are_parsed_and_checked():
    assert pareto.parse_newton("1x3, 2x3") == [(1, 3), (2, 3)] and pareto.parse_newton("") == []
    for bad in ("2", "0x3", "2xa"):
        with pytest.raises(ValueError):
            pareto.parse_newton(bad)


def _point(name, kind, ms, u, **extra):
    return {"name": name, "kind": kind, "ms": ms, "u": u, "v": 2 * u, "sigma": 3 * u, "sigma_free": 3 * u,
            "u_worst_case": 1.5 * u, "on_front": False, "on_front_uvs": False, **extra}


def test_report_only_rewrites_the_report_and_plot_from_the_stored_result(tmp_path, capsys):
    """--report-only reads pareto.json from --out and writes pareto.md and pareto.png beside it, the published
    network as a reference row; it names the missing file when there is none."""
    with pytest.raises(SystemExit):
        pareto.main(["--report-only", "--out", str(tmp_path)])
    assert "pareto.json" in capsys.readouterr().err
    points = [_point("beam-corot", "shipped", 4.0, 0.014), _point("beam", "shipped-learned", 1.1, 0.03),
              _point("beam-linear", "shipped-linear", 0.8, 0.04),
              _point("FEM 5×2×2", "fem", 19.0, 0.2, elements=20, n_sub=743, inverted=[-1]),
              _point("FEM Newton-CG 2×3", "fem-newton", 8.0, 0.02, newton=[2, 3])]
    front = pareto.pareto_front([p["ms"] for p in points], [p["u"] for p in points])
    for i in front:
        points[i]["on_front"] = points[i]["on_front_uvs"] = True
    result = {"machine": {"cpu": "x", "cores": 2, "jax": jax.__version__, "backend": "cpu"},
              "load_average_start": [0, 0, 0], "load_average_after_steps": [0, 0, 0], "load_average_end": [0, 0, 0],
              "test_sims": [9], "budget_ms": pareto.BUDGET_MS, "points": points,
              "front": [points[i]["name"] for i in front], "front_uvs": [points[i]["name"] for i in front],
              "published_test": {"q": 4.14e-3, "v": 1.72e-2, "sigma": 9.51e-2, "u": 7.07e-2}, "repeats": 5,
              "quick": True, "xla_configs": ["default"], "xla_flags": ""}
    (tmp_path / "pareto.json").write_text(json.dumps(result))
    assert pareto.main(["--report-only", "--out", str(tmp_path)]) == 0
    md = (tmp_path / "pareto.md").read_text()
    assert md.startswith("# Run time against error") and "| published TIGNN (reference line) | — |" in md
    assert "beam-linear → beam → beam-corot" in md and "| beam-corot | 4.00 |" in md
    assert "Against `beam`, the learned linear GENERIC model: 4.00 against 1.10 ms per step (3.64×)" in md
    assert (tmp_path / "pareto.png").stat().st_size > 0
