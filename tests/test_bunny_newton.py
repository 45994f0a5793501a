"""benchmarks/bunny_newton.py's error measure and scripts/bunny_heldout_subset.py's split-and-merge round trip."""
import sys
from pathlib import Path

import numpy as np

from tignn_jax import data as D

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts"))
import bunny_heldout_subset  # noqa: E402
import bunny_newton  # noqa: E402


def _moving_cases(n_cases=3, frames=4, nodes=5, seed=0):
    # each case moves every node by a fixed increment d per frame: q_k = q0 + k d, v = d / dt, σ = k s
    rng = np.random.default_rng(seed)
    q0 = rng.normal(size=(nodes, 3))
    d, s = rng.normal(size=(n_cases, nodes, 3)), rng.normal(size=(n_cases, nodes, 6))
    k = np.arange(frames + 1)[None, :, None, None]
    z = np.concatenate([q0 + k * d[:, None], np.broadcast_to(d[:, None], (n_cases, frames + 1, nodes, 3)),
                        k * s[:, None]], -1).astype(np.float32)
    return D.Dataset(q0=q0.astype(np.float32), edges=np.zeros((2, 0), np.int32), node_type=np.zeros(nodes, np.int8),
                     z=z, f=np.zeros((n_cases, frames, nodes, 3), np.float32), dt=0.05,
                     sim_id=np.arange(1, n_cases + 1, dtype=np.int32), splits={}), z[:, 1] - z[:, 0]


def test_a_step_that_replays_the_data_has_zero_error_and_one_that_overshoots_by_a_tenth_errs_by_a_tenth():
    # the increment is the same in every frame, so a step adding (1 + e) times it errs in u by exactly e
    data, inc = _moving_cases()
    for c in range(2):
        exact = bunny_newton.errors(lambda z, f, c=c: z + inc[c], data, [c])
        assert exact["finite"] and exact["u"] < 1e-6 and exact["sigma"] < 1e-6
    over = bunny_newton.errors(lambda z, f: z + 1.1 * inc[1], data, [1])
    assert abs(over["u"] - 0.1) < 1e-5 and abs(over["sigma"] - 0.1) < 1e-5 and abs(over["v"]) < 1e-6


def test_a_split_subset_merges_back_to_the_same_rows_of_the_data_set(tmp_path):
    # per-case arrays keep the split's rows; mesh arrays (q0, node_type, edges) are kept whole
    data, _ = _moving_cases(n_cases=4)
    full = tmp_path / "full.npz"
    np.savez(full, z=data.z, f=data.f, q0=data.q0, sim_id=data.sim_id, node_type=np.zeros(5, np.int8),
             edges=np.zeros((2, 6), np.int32), dt=np.float64(0.05), v_solver=data.z[..., 3:6],
             split_train=np.array([1, 3]), split_test=np.array([4, 2]))
    bunny_heldout_subset.main([str(full), "--split", "test", "--out", str(tmp_path / "parts")])
    bunny_heldout_subset.main(["--merge", str(tmp_path / "parts"), "--split", "test", "--out", str(tmp_path / "t.npz")])
    sub = np.load(tmp_path / "t.npz")
    np.testing.assert_array_equal(sub["sim_id"], [4, 2])
    np.testing.assert_array_equal(sub["z"], data.z[[3, 1]])
    np.testing.assert_array_equal(sub["v_solver"], data.z[[3, 1]][..., 3:6])
    np.testing.assert_array_equal(sub["q0"], data.q0)
    assert sub["node_type"].shape == (5,) and "split_train" not in sub.files
