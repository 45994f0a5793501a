"""MediaPipe hand landmarks → fingertip tracks: a synthetic hand seen by a pinhole camera is placed back at its
depth."""
import json

import numpy as np
import pytest

from tignn_jax.cli import main
from tignn_jax.mr import hands, load_track

W, H, F = 640, 480, 540.0


def _hand(depth, turn=0.3, tip_forward=0.02):
    """A hand's 21 landmarks in camera space (m): palm in the image plane at ``depth``, turned by ``turn`` in it,
    the index tip ``tip_forward`` nearer the camera than the wrist. Returns (camera points, MediaPipe-style
    normalised landmarks, world landmarks)."""
    base = np.zeros((21, 3))
    base[[0, 5, 9, 13, 17], :2] = [[0, 0], [-0.035, -0.08], [-0.012, -0.085], [0.01, -0.082], [0.03, -0.072]]
    for k, (a, b) in enumerate(((1, 4), (5, 8), (9, 12), (13, 16), (17, 20))):
        root = base[[0, 5, 9, 13, 17][k]] if k else np.array([-0.04, -0.03, 0.0])
        for j, i in enumerate(range(a, b + 1)):
            base[i, :2] = root[:2] + (j + 1) * np.array([0.0, -0.022])
    base[8, 2] = -tip_forward
    c, s = np.cos(turn), np.sin(turn)
    cam = base @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [0.02, 0.01, depth]
    x = (F * cam[:, 0] / cam[:, 2] + W / 2) / W
    y = (F * cam[:, 1] / cam[:, 2] + H / 2) / H
    z = (cam[:, 2] - cam[0, 2]) * F / (depth * W)          # MediaPipe's relative z, in image widths
    return cam, np.stack([x, y, z], 1), base - base.mean(axis=0)


@pytest.mark.parametrize("depth", [0.3, 0.5, 0.8])
def test_depth_from_the_hands_size(depth):
    cam, lm, world = _hand(depth)
    u, v, d = hands.hand_to_tips(lm, W, H, F, world_landmarks=world)[0]
    assert abs(u - lm[8, 0] * W) < 1e-9 and abs(v - lm[8, 1] * H) < 1e-9
    assert abs(d - cam[8, 2]) < 0.01 * depth, (d, cam[8, 2])
    # without world landmarks, an adult palm's length: off by the ratio of the palm sizes
    d2 = hands.hand_to_tips(lm, W, H, F)[0, 2]
    ratio = hands.PALM_M / hands.palm_length(world)
    assert abs(d2 / cam[8, 2] - ratio) < 0.02 * ratio


def test_depth_image_is_read_where_given():
    _, lm, _ = _hand(0.4)
    image = np.full((H, W), 0.37)
    assert hands.hand_to_tips(lm, W, H, F, depth_image=image)[0, 2] == pytest.approx(0.37)


def test_cli_converts_a_recording(tmp_path, capsys):
    records = []
    for k, depth in enumerate((0.4, 0.45, None, 0.5)):
        if depth is None:
            records.append({"frame": k, "hands": []})
            continue
        _, lm, world = _hand(depth)
        records.append({"frame": k, "hands": [{"landmarks": lm.tolist(), "world_landmarks": world.tolist()}]})
    src = tmp_path / "hands.jsonl"
    src.write_text("\n".join(json.dumps(r) for r in records))
    out = tmp_path / "track.jsonl"
    assert main(["track", "--mediapipe", str(src), "--size", f"{W}x{H}", "--focal", str(F), "--out", str(out)]) == 0
    track = load_track(out)
    assert track.shape[:2] == (4, 5) and np.isnan(track[2]).all()
    assert np.all(np.diff(track[[0, 1, 3], 0, 2]) > 0)          # the hand moves away
    src.write_text('{"frame": 0, "hands": [{"landmarks": [[0, 0, 0]]}]}')
    assert main(["track", "--mediapipe", str(src), "--size", "640x480", "--focal", "540", "--out", str(out)]) == 2
    assert "not a hand record" in capsys.readouterr().err
