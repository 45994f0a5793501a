"""Fingertip tracks: what a hand tracker reports per camera frame, read, written and synthesised.

A track in memory is an array [F, K, 3] of (u, v, depth_m) per frame and fingertip, NaN rows for no fingertip.
On disk it is JSON lines, one object per camera frame, in order::

    {"frame": 0, "tips": [[u, v, depth_m], [u, v, depth_m]]}
    {"frame": 1, "tips": []}

* ``u, v``: pixel coordinates of the fingertip in the camera image: u to the right, v down, origin at the
  top-left corner of the image, pixel centres at +0.5 (so a MediaPipe hand landmark with normalised (x, y) is
  ``u = x * width, v = y * height``; landmarks 4, 8, 12, 16, 20 are the five fingertips).
* ``depth_m``: the depth camera's reading at that pixel, in metres along the optical axis (the value of the
  aligned depth image at (u, v); MediaPipe's relative z is not a depth).
* Any number of tips per frame up to the scene's maximum (more are dropped with a warning); extra keys are
  ignored; a frame with no line or an empty list has no fingertips. ``frame`` numbers the lines from 0.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from tignn_jax.mr.camera import Camera, camera_projection, project


def press_track(camera: Camera, point, normal, frames: int, approach: float = 0.03,
                press: float = 0.01) -> np.ndarray:
    """A one-fingertip track that pushes on a world point along ``-normal`` and lets go.

    The tip starts ``approach`` outside the surface along ``normal``, moves in to ``press`` inside it at
    mid-track and back out along a cosine ramp, s_k = ½ (1 - cos(2π k / (frames - 1))):

        x_k = point + ((1 - s_k) · approach - s_k · press) · normal.

    Args:
      camera: the camera that sees it.
      point: [3] world point pressed (m).
      normal: [3] outward surface normal there (any length > 0).
      frames: the track's length.
      approach: start distance outside the surface (m).
      press: deepest distance inside the surface (m).

    Returns:
      [frames, 1, 3] float32 (u, v, depth_m) per frame.
    """
    point, normal = np.asarray(point, np.float64), np.asarray(normal, np.float64)
    normal = normal / np.linalg.norm(normal)
    s = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(frames) / max(frames - 1, 1))   # 0 -> 1 -> 0
    world = point + ((1 - s) * approach - s * press)[:, None] * normal
    pixels, depth = project(jnp.asarray(world, jnp.float32), jnp.asarray(camera_projection(camera) @ camera.view),
                            (0.0, 0.0, float(camera.width), float(camera.height)))
    return np.concatenate([np.asarray(pixels), np.asarray(depth)[:, None]], axis=1)[:, None, :].astype(np.float32)


def load_track(path, max_tips: int = 5) -> np.ndarray:
    """Read a JSON-lines fingertip track (the module's format).

    Args:
      path: the file.
      max_tips: fingertips kept per frame; more are dropped with a warning.

    Returns:
      [F, max_tips, 3] float32, NaN-padded; F is one more than the largest frame number.

    Raises:
      ValueError: a line is not a track record ({"frame": int, "tips": [[u, v, depth], ...]}), naming its line,
        or the file holds no record.
    """
    frames = {}
    for n, line in enumerate(Path(path).read_text().splitlines()):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            if not isinstance(record, dict):
                raise TypeError(f"a JSON {type(record).__name__}, not an object")
            tips = np.asarray(record.get("tips", []), np.float32).reshape(-1, 3)
            frame = int(record.get("frame", n))
            if frame < 0:
                raise ValueError(f"frame {frame} is negative")
        except (ValueError, TypeError) as err:
            raise ValueError(f"{path}:{n + 1}: not a track record ({err})") from None
        if len(tips) > max_tips:
            warnings.warn(f"{path}:{n + 1}: {len(tips)} fingertips, keeping the first {max_tips}")
        frames[frame] = tips[:max_tips]
    if not frames:
        raise ValueError(f"{path}: no track records (an empty file)")
    track = np.full((max(frames) + 1, max_tips, 3), np.nan, np.float32)
    for i, tips in frames.items():
        track[i, : len(tips)] = tips
    return track


def save_track(path, track) -> None:
    """Write a track [F, K, 3] (NaN rows = no fingertip) as JSON lines, rounded to 1e-5 pixel / 1e-5 m."""
    with open(path, "w") as f:
        for i, tips in enumerate(np.asarray(track)):
            keep = np.all(np.isfinite(tips), axis=1)
            f.write(json.dumps({"frame": i, "tips": tips[keep].astype(np.float64).round(5).tolist()}) + "\n")
