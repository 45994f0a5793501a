"""The colour legend on rendered frames: the bar shows the colour map from vmax (top) to vmin (bottom)."""
import numpy as np
import pytest

from tignn_jax import mr


def test_the_bar_runs_from_the_top_value_to_the_bottom_value():
    frame = np.full((200, 320, 3), 255, np.uint8)
    out = mr.with_legend(frame, 0.0, 6e4, "von Mises stress (data units)")
    assert out.shape == frame.shape and out.dtype == np.uint8 and np.array_equal(frame, np.full_like(frame, 255))
    column = out[22:22 + 80, 320 - 58 + 7]                       # the bar's middle column, top to bottom
    top, bottom = (np.asarray(mr.colour_map(np.array([v]), 0.0, 6e4))[0] * 255 for v in (6e4, 0.0))
    assert np.abs(column[0].astype(float) - top).max() < 3 and np.abs(column[-1].astype(float) - bottom).max() < 3
    assert (out[:20] != 255).any()                                 # the label is drawn above the bar


def test_bad_frames_and_ranges_are_named():
    with pytest.raises(ValueError, match=r"rgb must be \[H, W, 3\]"):
        mr.with_legend(np.zeros((10, 10)), 0.0, 1.0, "x")
    with pytest.raises(ValueError, match="vmax must exceed vmin, got 1.0 and 1.0"):
        mr.with_legend(np.zeros((10, 10, 3), np.uint8), 1.0, 1.0, "x")
