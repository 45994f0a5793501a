"""benchmarks/beam_reach.py: hop distances, shares, and the causal test on one fingertip patch of the FEM beam."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import beam_reach as br  # noqa: E402


def test_hop_distance_and_share_on_a_chain():
    # a path 0-1-2-3-4 (both directions): distances from node 0, and the energy beyond P edges
    edges = np.array([[0, 1, 1, 2, 2, 3, 3, 4], [1, 0, 2, 1, 3, 2, 4, 3]])
    dist = br.hop_distance(edges, 5, [0])
    assert dist.tolist() == [0, 1, 2, 3, 4]
    assert br.share_beyond(np.array([1.0, 1, 1, 1, 4]), dist, [0, 2, 4]) == {0: 0.875, 2: 0.625, 4: 0.0}


def test_one_frame_of_the_beam_reaches_beyond_three_edges():
    # The FEM's response to a fingertip patch: shares in [0, 1], falling with P, zero beyond the mesh's diameter
    # (the two runs share frame 1, checked inside measure); most of it lies beyond 3 edges.
    from fem import scenes

    scene = scenes.beam_scene(damping=60.0)
    (row,) = br.measure(scene, br.patch_loads(scene, 1)[:1], [0, 3, 6, 40])
    for key in ("from_rest_share_beyond", "rate_change_share_beyond"):
        s = [row[key][p] for p in (0, 3, 6, 40)]
        assert all(0.0 <= a <= 1.0 for a in s) and s == sorted(s, reverse=True) and s[-1] == 0.0, s
    assert row["rate_change_share_beyond"][3] > 0.5
    assert 0.0 < row["error_bound"][3] <= row["error_bound"][0]
