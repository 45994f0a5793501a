"""MediaPipe hand landmarks → fingertip tracks (`tignn_jax.mr.track`'s format).

MediaPipe's hand landmarker reports, per hand and camera frame, 21 landmarks with normalised image coordinates
x, y ∈ [0, 1] (x to the right, y down) and a relative depth z (zero at the wrist, landmark 0; smaller is nearer;
in about the units of x, i.e. image widths), and optionally the same 21 points as "world landmarks" in metres
about the hand's centre. Landmark 8 is the index fingertip (4, 12, 16, 20 the other tips).

A track needs (u, v, depth_m) per tip: the pixel u = x · W, v = y · H, and the metric depth along the optical
axis. With an aligned depth image (an RGB-D or stereo camera, as in the paper) the depth is read there
(``depth_images``). A single camera has no depth, so it is estimated from the hand's known size: the palm
points P = (0, 5, 9, 13, 17) span a metric length L (from the world landmarks, or ``palm_m`` when there are none)
and ℓ pixels in the image, so by the pinhole model the wrist lies at

    d_wrist = f · L / ℓ,

and a tip at relative depth z at d_tip = d_wrist + z · W · d_wrist / f (z in image widths is z·W pixels, which
at depth d are z·W·d/f metres). L and ℓ are the summed lengths of the palm's segments 0–5, 5–9, 9–13, 13–17,
17–0, so the estimate does not depend on the hand's turn within the image plane; a hand turned out of that plane
looks smaller and is placed too far (its depth error grows as 1/cos of the tilt).

Input records, one JSON object per camera frame (JSON lines), as MediaPipe's Python and JavaScript solutions
return them::

    {"frame": 0, "hands": [{"landmarks": [[x, y, z], ... 21], "world_landmarks": [[x, y, z], ... 21]}]}

(``world_landmarks`` optional; a frame with no hand has ``"hands": []``.) `tignn view` and `tignn demo --track`
read the converted track.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

FINGERTIPS = {"thumb": 4, "index": 8, "middle": 12, "ring": 16, "pinky": 20}
PALM = (0, 5, 9, 13, 17)          # wrist and the four finger bases: a rigid loop
PALM_M = 0.27                     # summed length of the palm loop of an adult hand (m), when no world landmarks


def palm_length(points) -> np.ndarray:
    """The summed length of the palm loop 0–5–9–13–17–0 of landmarks [..., 21, 2 or 3] (in their units)."""
    p = np.asarray(points, np.float64)[..., PALM, :]
    return np.sum(np.linalg.norm(p - np.roll(p, -1, axis=-2), axis=-1), axis=-1)


def hand_to_tips(landmarks, width: int, height: int, focal: float, world_landmarks=None, depth_image=None,
                 tips=("index",), palm_m: float = PALM_M) -> np.ndarray:
    """One hand's fingertips as track rows (u, v, depth_m) (module docstring).

    Args:
      landmarks: [21, 3] normalised (x, y, z).
      width, height: the image size in pixels.
      focal: the camera's focal length in pixels.
      world_landmarks: [21, 3] metres, optional: the hand's own palm size instead of ``palm_m``.
      depth_image: [height, width] metres, optional: read the depth there instead of estimating it.
      tips: names from ``FINGERTIPS``.
      palm_m: the palm loop's length (m) when there are no world landmarks.

    Returns:
      [len(tips), 3] float64.

    Raises:
      ValueError: landmarks not [21, 3], a non-positive image size or focal length, or an unknown tip name.
    """
    lm = np.asarray(landmarks, np.float64)
    if lm.shape != (21, 3) or not np.all(np.isfinite(lm)):
        raise ValueError(f"landmarks must be 21 finite (x, y, z) rows, got shape {lm.shape}")
    if width <= 0 or height <= 0 or not focal > 0:
        raise ValueError(f"width, height and focal must be positive, got {width}, {height}, {focal}")
    unknown = [t for t in tips if t not in FINGERTIPS]
    if unknown:
        raise ValueError(f"unknown fingertips {unknown}; known: {sorted(FINGERTIPS)}")
    idx = [FINGERTIPS[t] for t in tips]
    u, v = lm[idx, 0] * width, lm[idx, 1] * height
    if depth_image is not None:
        img = np.asarray(depth_image, np.float64)
        iu = np.clip(u.astype(int), 0, img.shape[1] - 1)
        iv = np.clip(v.astype(int), 0, img.shape[0] - 1)
        return np.stack([u, v, img[iv, iu]], axis=1)
    metric = palm_m if world_landmarks is None else float(palm_length(world_landmarks))
    pixels = float(palm_length(lm[:, :2] * [width, height]))
    if not pixels > 0:
        raise ValueError("the palm has no extent in the image: cannot estimate the hand's depth")
    d_wrist = focal * metric / pixels
    depth = d_wrist + (lm[idx, 2] - lm[0, 2]) * width * d_wrist / focal
    return np.stack([u, v, depth], axis=1)


def convert(path, out, width: int, height: int, focal: float, tips=("index",), palm_m: float = PALM_M) -> Path:
    """Convert a JSON-lines file of MediaPipe hand records (module docstring) into a fingertip track file.

    Every hand of a frame contributes its ``tips``; frames are numbered by their ``frame`` key (else the line).

    Returns:
      The written track's path.

    Raises:
      ValueError: a line that is not a record of this form (naming the line), or a file with no record.
    """
    from tignn_jax.mr.track import save_track

    frames = {}
    for n, line in enumerate(Path(path).read_text().splitlines()):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            if not isinstance(record, dict):
                raise TypeError(f"a JSON {type(record).__name__}, not an object")
            rows = [hand_to_tips(h["landmarks"], width, height, focal, h.get("world_landmarks"), tips=tips,
                                 palm_m=palm_m) for h in record.get("hands", [])]
        except (ValueError, KeyError, TypeError) as err:
            raise ValueError(f"{path}:{n + 1}: not a hand record ({err})") from None
        frames[int(record.get("frame", n))] = np.concatenate(rows) if rows else np.zeros((0, 3))
    if not frames:
        raise ValueError(f"{path}: no hand records (an empty file)")
    count = max(len(r) for r in frames.values())
    track = np.full((max(frames) + 1, max(count, 1), 3), np.nan)
    for i, r in frames.items():
        track[i, : len(r)] = r
    save_track(out, track)
    return Path(out)
