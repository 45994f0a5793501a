"""FEM continuations of the reference beam cases past their 20-frame ramp, for training on longer horizons.

The reference data stop at frame 20, at the end of a load ramp, so a model trained on them has never seen a
held load or a release: the two things a long rollout (and `benchmarks/stability.py`) does next.
``generate`` runs our FEM (the identified reference scene, `fem.scenes.beam_scene`) on the 13 load positions
of face 0 (sims 1..13) for 20 + K frames: the reference ramp, then the final load held (``hold``, case ids
1..13) or no load (``release``, ids 14..26); resumable, shareable by two processes (``--worker k/2``).
``merge`` maps those runs onto the other three faces (`fem.scenes.BEAM_FACE_MAPS`: the four face groups of
the reference data are exact mirror images), cuts each run into 20-frame windows (21 states) starting at
``--first`` every ``--stride`` frames (``--modes hold``: the held runs only), and appends the windows to a
copy of a reference-format data set as new cases (ids after the last); a window joins the split of the
reference case it continues.

    python scripts/beam_continuation.py generate --after 20 --out data/beam_cont.npz [--worker 0/2]
    python scripts/beam_continuation.py merge --base ../shared/data/abaqus_beam.npz --cont data/beam_cont.npz \
        --out data/abaqus_beam_long.npz

The merged file holds the Abaqus data: keep it out of git (data/ is ignored). What training on such files
did to the learned beam's long rollouts: README, row "stability with held-load training".
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def generate(args) -> None:
    from fem import scenes
    from fem.generate import run_cases

    scene = scenes.beam_scene()
    ids = np.arange(1, scenes.BEAM_FACE_GROUP + 1)      # face 0: the other faces are its mirror images (merge)
    forces = np.concatenate([scenes.beam_reference_forces(scene, ids, args.after, m)
                             for m in scenes.BEAM_CONTINUATIONS])
    scene = scene._replace(n_frames=scene.n_frames + args.after)
    problem = scenes.setup_scene(scene)
    k, n = (int(x) for x in args.worker.split("/"))
    run_cases(scene, problem, forces, Path(args.out), batch_size=args.batch_size, worker=(k, n),
              sim_ids=np.arange(1, len(forces) + 1), velocity="gradient", progress=not args.no_progress,
              metadata={"cases": f"reference cases 1..13 ramped 20 frames, then {args.after} frames held (ids "
                                 f"1..13) or released (ids 14..26)", "after_frames": args.after})


def merge(args) -> None:
    from fem.scenes import BEAM_CONTINUATIONS, BEAM_FACE_GROUP, BEAM_FACE_MAPS, mirror_case

    keep = args.modes.split(",")
    unknown = [m for m in keep if m not in BEAM_CONTINUATIONS]
    if unknown:
        raise SystemExit(f"--modes: unknown {unknown}; choose from {BEAM_CONTINUATIONS}")
    base, cont = np.load(args.base), np.load(args.cont)
    n_ref = len(base["sim_id"])
    frames = base["f"].shape[1]
    q0 = base["q0"].astype(np.float64)
    zc, fc = cont["z"].astype(np.float64), cont["f"].astype(np.float64)
    total = fc.shape[1]
    starts = list(range(args.first, total - frames + 1, args.stride))
    z_new, f_new, src, mode = [], [], [], []
    for g, (rot, shift) in enumerate(BEAM_FACE_MAPS):
        zg, fg = mirror_case(zc, fc, q0, rot, shift)
        for c in range(len(zc)):
            kind = BEAM_CONTINUATIONS[c // BEAM_FACE_GROUP]
            if kind not in keep:
                continue
            for s in starts:
                z_new.append(zg[c, s:s + frames + 1])
                f_new.append(fg[c, s:s + frames])
                src.append(g * BEAM_FACE_GROUP + c % BEAM_FACE_GROUP + 1)
                mode.append(kind)
    ids = np.arange(n_ref + 1, n_ref + len(z_new) + 1, dtype=np.int32)
    src = np.asarray(src)
    out = {k: base[k] for k in base.files}
    out["z"] = np.concatenate([base["z"], np.asarray(z_new, base["z"].dtype)])
    out["f"] = np.concatenate([base["f"], np.asarray(f_new, base["f"].dtype)])
    out["sim_id"] = np.concatenate([base["sim_id"], ids])
    for split in ("train", "val", "test"):
        key = f"split_{split}"
        out[key] = np.concatenate([base[key], ids[np.isin(src, base[key])]]).astype(np.int32)
    meta = {"continuation": {"source": str(args.cont), "windows_start": starts, "ids": [int(ids[0]), int(ids[-1])],
                             "source_sim": src.tolist(), "mode": mode}}
    out["metadata"] = np.array(json.dumps(meta))
    np.savez(args.out, **out)
    print(f"{args.out}: {n_ref} base cases + {len(ids)} windows (starts {starts}); train {len(out['split_train'])}, "
          f"val {len(out['split_val'])}, test {len(out['split_test'])}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="FEM runs of face 0's cases continued past the ramp (resumable)")
    g.add_argument("--after", type=int, default=20, help="frames after the 20-frame ramp (default: %(default)s)")
    g.add_argument("--out", required=True, help="output .npz (finished cases are kept in OUT.parts/)")
    g.add_argument("--worker", default="0/1", help="k/n: run every n-th case from k, one process per core")
    g.add_argument("--batch-size", type=int, default=8, help="cases per vmapped batch (default: %(default)s)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    m = sub.add_parser("merge", help="mirror the runs onto the four faces, window them, append them to --base")
    m.add_argument("--base", required=True, help="reference-format data set (e.g. ../shared/data/abaqus_beam.npz)")
    m.add_argument("--cont", required=True, help="the generate step's output")
    m.add_argument("--out", required=True, help="merged .npz")
    m.add_argument("--modes", default="hold,release", help="which continuations to keep (default: %(default)s)")
    m.add_argument("--first", type=int, default=10, help="first window's start frame (default: %(default)s)")
    m.add_argument("--stride", type=int, default=10, help="frames between window starts (default: %(default)s)")
    a = p.parse_args()
    generate(a) if a.cmd == "generate" else merge(a)


if __name__ == "__main__":
    main()
