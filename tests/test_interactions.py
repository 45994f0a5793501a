"""benchmarks/interactions.py: fingertip cases grouped by profile, and peak-relative errors with known answers."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import interactions as itx  # noqa: E402
from tignn_jax import data as D  # noqa: E402
from tignn_jax import evaluate as EV  # noqa: E402


def test_profiles_come_from_the_generated_files_metadata(tmp_path):
    good = tmp_path / "good.npz"
    np.savez(good, metadata=np.array(json.dumps({"cases": [{"profile": "hold"}, {"profile": "move"}]})))
    assert itx.profiles_of(good) == ["hold", "move"]
    bare = tmp_path / "bare.npz"
    np.savez(bare, metadata=np.array("{}"))
    with pytest.raises(ValueError, match="bare.npz"):
        itx.profiles_of(bare)


def test_groups_split_the_fingertip_cases_by_profile():
    ref = D.synthetic_beam(cases=3)
    tips = D.synthetic_beam(cases=4)._replace(splits={"test": np.array([1, 2, 4], np.int32)})
    found = itx.groups(ref, tips, ["hold", "move", "hold", "hold"], "test")
    assert [(g, r.tolist()) for g, _, r in found] == [("reference", [2]), ("hold", [0, 3]), ("move", [1])]
    with pytest.raises(ValueError, match="3 profiles for 4"):
        itx.groups(ref, tips, ["hold"] * 3, "test")


def test_errors_are_relative_to_each_cases_peak(monkeypatch):
    data = D.synthetic_beam(cases=2, frames=4)
    pred = data.z.astype(np.float64).copy()
    pred[..., :3] = data.q0 + 1.5 * (data.z[..., :3] - data.q0)   # u 50 % too large everywhere, v and σ exact
    pred[1, 3:, 0, 0] = np.nan                                      # the second rollout fails at snapshot 3
    monkeypatch.setattr(EV, "rollout_cases", lambda params, d, rows: pred[rows])
    one = itx.errors(None, data, np.array([0]))
    u = np.linalg.norm((data.z[0, 1:, :, :3] - data.q0).reshape(4, -1), axis=1)
    np.testing.assert_allclose(one["u"], np.mean(0.5 * u / u.max()), rtol=1e-5)   # float32 data
    np.testing.assert_allclose(one["u_max"], 0.5, rtol=1e-5)
    assert one["v"] == 0.0 and one["sigma"] == 0.0 and (one["cases"], one["finite"]) == (1, 1)
    both = itx.errors(None, data, np.array([0, 1]))
    assert (both["cases"], both["finite"]) == (2, 1)
