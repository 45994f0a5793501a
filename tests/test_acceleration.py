"""benchmarks/acceleration.py: the velocity's change per frame and its share in steps whose load does not grow,
against constructed trajectories with known answers."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import acceleration as acc  # noqa: E402


def _states(v_of_frame, cases=2, nodes=3):
    t = len(v_of_frame)
    z = np.zeros((cases, t, nodes, 12))
    z[..., 3] = np.asarray(v_of_frame)[None, :, None]
    return z


def test_steady_motion_has_no_change_and_a_doubling_velocity_changes_by_one():
    ramp = np.linspace(0.0, 1.0, 5)[None, :, None, None] * np.ones((2, 5, 3, 3))   # a load that always grows
    steady = acc.acceleration_stats(_states([2.0] * 6), ramp)
    assert steady["median"] == 0.0 and steady["flat_load_frames"] == 0.0
    doubling = acc.acceleration_stats(_states([1.0, 2.0, 4.0, 8.0, 16.0, 32.0]), ramp)
    np.testing.assert_allclose(doubling["per_frame_median"], 1.0)
    assert doubling["cases"] == 2 and doubling["frames"] == 5


def test_the_change_in_steps_whose_load_stops_growing_is_counted_there():
    # load rises over steps 0-2, then is held (steps 3, 4); the velocity changes only in steps 3 and 4
    load = np.array([0.0, 1.0, 2.0, 2.0, 2.0])[None, :, None, None] * np.ones((1, 5, 3, 3))
    z = _states([1.0, 1.0, 1.0, 1.0, 0.5, 0.25], cases=1)
    stats = acc.acceleration_stats(z, load)
    assert stats["flat_load_frames"] == 0.4
    np.testing.assert_allclose(stats["dv_energy_in_flat_load_frames"], 1.0)
    np.testing.assert_allclose(stats["per_frame_median"], [0.0, 0.0, 0.0, 0.5, 0.5])
