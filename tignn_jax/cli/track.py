"""``tignn track``: convert a hand tracker's output into a fingertip track (`tignn_jax.mr.track`'s format)."""
from __future__ import annotations

import math
from pathlib import Path

from tignn_jax.cli import UsageError


def register(sub) -> None:
    p = sub.add_parser("track", help="convert MediaPipe hand landmarks into a fingertip track",
                       description="Convert MediaPipe hand landmarks (JSON lines, one record per camera frame: "
                                   "{\"frame\": k, \"hands\": [{\"landmarks\": 21 x [x, y, z], \"world_landmarks\": "
                                   "...}]}) into a fingertip track for `tignn demo --track`: pixels from the "
                                   "normalised landmarks, depth from the hand's size (tignn_jax.mr.hands).")
    p.add_argument("--mediapipe", required=True, metavar="FILE", help="the landmarks, JSON lines")
    p.add_argument("--size", required=True, metavar="WxH", help="the camera image's width x height in pixels")
    p.add_argument("--focal", type=float, required=True, help="the camera's focal length in pixels")
    p.add_argument("--tips", default="index", help="comma-separated fingertips: thumb, index, middle, ring, pinky "
                                                   "(default: %(default)s)")
    p.add_argument("--palm", type=float, default=None, metavar="M",
                   help="the palm loop's length in metres where the records have no world landmarks (default: an "
                        "adult hand's, 0.27)")
    p.add_argument("--out", required=True, help="the track file to write (JSON lines)")
    p.set_defaults(func=run)


def run(args) -> int:
    from tignn_jax.cli.demo import _parse_size
    from tignn_jax.mr import hands

    if not Path(args.mediapipe).is_file():
        raise UsageError(f"--mediapipe {args.mediapipe}: no such file")
    width, height = _parse_size(args.size)
    if not (math.isfinite(args.focal) and args.focal > 0):
        raise UsageError(f"--focal must be a positive number, got {args.focal}")
    tips = tuple(t.strip() for t in args.tips.split(",") if t.strip())
    bad = [t for t in tips if t not in hands.FINGERTIPS]
    if not tips or bad:
        raise UsageError(f"--tips {args.tips!r}: fingertips are {', '.join(hands.FINGERTIPS)}")
    palm = hands.PALM_M if args.palm is None else args.palm
    if not (math.isfinite(palm) and palm > 0):
        raise UsageError(f"--palm must be a positive number, got {args.palm}")
    out = hands.convert(args.mediapipe, args.out, width, height, args.focal, tips=tips, palm_m=palm)
    print(f"wrote {out}")
    return 0
