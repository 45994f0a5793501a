"""`tignn generate`: FEM data sets for training and evaluation."""
from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    g = sub.add_parser("generate", help="generate FEM data (beam-reference, beam-interactions, bunny, bunny-interactions, two-beams)",
                       description="Generate a data set with the FEM. Resumable: finished cases are kept in "
                                   "OUT.parts/ and skipped when the command is run again.")
    g.add_argument("scene", choices=("beam-reference", "beam-interactions", "bunny", "bunny-interactions", "two-beams"))
    g.add_argument("--out", required=True, help="output .npz path")
    g.add_argument("--cases", type=int, default=None, help="number of cases (interactions: 64, bunny: 100, two-beams: 6)")
    g.add_argument("--seed", type=int, default=0, help="random seed for load cases (default: %(default)s)")
    g.add_argument("--load-nodes", default=None, help="bunny: comma-separated node ids to load instead of --cases")
    g.add_argument("--velocity", choices=("gradient", "solver"), default=None,
                   help="z's velocity: solver (default; zero at the rest start) or gradient of q over the frames "
                        "(the reference data's convention; default for beam-reference)")
    g.add_argument("--rise-frames", type=int, default=10,
                   help="bunny: frames over which the point load rises smoothly, 0 = a step (default: %(default)s)")
    g.add_argument("--loads-per-case", type=int, default=1, metavar="K",
                   help="bunny: K simultaneous point loads per case, at least 6 edges apart (default: 1)")
    g.add_argument("--exclude-loads-of", default=None, metavar="DATA",
                   help="bunny with --loads-per-case: never load a node within 2 edges of a load position of the "
                        "val and test cases of this data set (its metadata's load_nodes), so they stay held out")
    g.add_argument("--load-radius", type=float, default=None, metavar="R",
                   help="bunny: spread each unit load over the free surface nodes within R of the load position "
                        "(weights (1 - (d/R)^2)^2, the position's normal) instead of one node: a fingertip-sized "
                        "press rather than a point force, whose dent is a property of the mesh (default: a point)")
    g.add_argument("--load-magnitude", type=float, default=None, metavar="F",
                   help="bunny single-load cases: the total force of each load instead of 1 (the paper's unit "
                        "load); larger loads reach the geometrically and materially non-linear range")
    g.add_argument("--smooth-loads", action="store_true",
                   help="interactions: C¹ force histories (smooth rises and falls, a cross-fade when the patch "
                        "moves) instead of piecewise-linear ones, whose jumps in loading rate the frames cannot "
                        "resolve (fem.cases.fingertip_forces)")
    g.add_argument("--damping", type=float, default=None, metavar="ALPHA",
                   help="mass-proportional damping coefficient [1/time] instead of the scene's (beam: 18.17, "
                        "identified against the reference data; bunny: 2.0)")
    g.add_argument("--integrator", choices=("explicit", "implicit"), default="explicit",
                   help="explicit central differences (default) or implicit backward Euler with the frame step "
                        "(fem.implicit: damps what a frame cannot resolve; elastic scenes without contact)")
    g.add_argument("--newton-iterations", type=int, default=12, metavar="K",
                   help="--integrator implicit: at most K Newton iterations per frame (default: %(default)s); "
                        "frames that stop above the tolerance keep their residual in the data (newton_residual)")
    g.add_argument("--density", type=float, default=None, metavar="RHO",
                   help="mass density instead of the scene's (beam: 7.135e-3, identified; bunny: 1e-5, chosen so "
                        "the first mode shows within the run; a much lighter bunny, e.g. 1e-7 with --integrator "
                        "implicit, responds quasi-statically)")
    g.add_argument("--worker", default="0/1", metavar="K/N",
                   help="run only cases c with c mod N = K, to share the work among N processes; the last to "
                        "finish writes --out (default: %(default)s)")
    g.add_argument("--batch", type=int, default=8, help="cases per vmapped batch (default: %(default)s)")
    g.add_argument("--xdmf", "--paraview", dest="xdmf", action="store_true", help="also write ParaView files per case (.pvd + VTU frames)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.set_defaults(func=run_generate)


def run_generate(args) -> int:
    import numpy as np

    from . import cases as cs
    from .generate import run_cases
    from .scenes import (beam_reference_forces, beam_scene, bunny_scene, setup_scene, two_beams_contact,
                         two_beams_forces, two_beams_scene)

    if args.cases is not None and args.cases < 1:
        raise SystemExit(f"--cases must be positive, got {args.cases}")
    if args.batch < 1:
        raise SystemExit(f"--batch must be positive, got {args.batch}")
    if args.newton_iterations < 1:
        raise SystemExit(f"--newton-iterations must be positive, got {args.newton_iterations}")
    if args.newton_iterations != 12 and args.integrator != "implicit":
        raise SystemExit("--newton-iterations applies only with --integrator implicit")
    try:
        worker = tuple(int(t) for t in args.worker.split("/"))
        if len(worker) != 2 or not 0 <= worker[0] < worker[1]:
            raise ValueError
    except ValueError:
        raise SystemExit(f"--worker must be K/N with 0 <= K < N, got {args.worker!r}")
    if args.scene != "bunny":
        for flag, value, unset in (("--load-nodes", args.load_nodes, None), ("--loads-per-case", args.loads_per_case, 1),
                                   ("--exclude-loads-of", args.exclude_loads_of, None),
                                   ("--load-radius", args.load_radius, None),
                                   ("--load-magnitude", args.load_magnitude, None)):
            if value != unset:
                raise SystemExit(f"{flag} applies only to the bunny scene, not {args.scene}")
    meta = {"seed": args.seed, "command": f"tignn generate {args.scene}"}
    sim_ids = None
    setup_kwargs = {}
    if args.scene == "two-beams":
        scene = two_beams_scene()
        forces = two_beams_forces(scene)
        if args.cases:
            forces = forces[: args.cases]
        setup_kwargs["contact"] = two_beams_contact(scene)
        meta["cases"] = "beam B pushed down onto beam A: load line on B's top face at x = 40, 36, 32; x1.0, x1.5 ramp"
        meta["contact"] = {k: v for k, v in setup_kwargs["contact"].items() if k not in ("a", "b")}
    elif args.scene == "beam-reference":
        scene = beam_scene()
        sim_ids = np.arange(1, 53)
        forces = beam_reference_forces(scene, sim_ids)
        meta["cases"] = "the 52 reference load cases (13 positions x 4 faces, 5000*(k+1) per node)"
    elif args.scene in ("beam-interactions", "bunny-interactions"):
        # Peak totals up to the reference maximum: 6 nodes x 100 000 on the beam, 6 unit point loads on the bunny.
        scene, peak = (beam_scene(), 600_000.0) if args.scene == "beam-interactions" else (bunny_scene(), 6.0)
        forces, described = cs.fingertip_forces(scene, args.cases or 64, args.seed, peak_total=peak,
                                                smooth=args.smooth_loads)
        meta["cases"] = described
        meta["smooth_loads"] = bool(args.smooth_loads)
    else:
        scene = bunny_scene()
        nodes = None
        if args.loads_per_case < 1:
            raise SystemExit(f"--loads-per-case must be >= 1, got {args.loads_per_case}")
        if args.exclude_loads_of and args.loads_per_case == 1:
            raise SystemExit("--exclude-loads-of applies only with --loads-per-case > 1 (single-load cases take "
                             "their positions from --cases/--seed or --load-nodes)")
        if args.load_nodes and args.loads_per_case > 1:
            raise SystemExit("--load-nodes cannot be combined with --loads-per-case > 1 (multi-load cases place "
                             "their loads themselves)")
        if args.load_radius is not None and args.loads_per_case > 1:
            raise SystemExit("--load-radius applies only to single-load cases (--loads-per-case 1)")
        if args.load_magnitude is not None and (args.loads_per_case > 1 or not np.isfinite(args.load_magnitude)
                                                or args.load_magnitude <= 0):
            raise SystemExit(f"--load-magnitude must be a positive number and applies only to single-load cases, "
                             f"got {args.load_magnitude} with --loads-per-case {args.loads_per_case}")
        if args.load_nodes:
            try:
                nodes = [int(t) for t in args.load_nodes.split(",") if t.strip()]
            except ValueError:
                raise SystemExit(f"--load-nodes must be comma-separated integers, got {args.load_nodes!r}")
        try:
            if args.loads_per_case > 1:
                held = _held_out_load_nodes(args.exclude_loads_of) if args.exclude_loads_of else []
                forces, picked = cs.multi_point_load_forces(scene, args.cases or 100, args.loads_per_case,
                                                            args.seed, exclude_nodes=held,
                                                            rise_frames=args.rise_frames)
                meta["excluded_load_nodes"] = list(map(int, held))
            else:
                forces, picked = cs.point_load_forces(scene, args.cases or 100, args.seed, load_nodes=nodes,
                                                      rise_frames=args.rise_frames,
                                                      radius=args.load_radius or 0.0,
                                                      magnitude=args.load_magnitude or 1.0)
                if args.load_radius:
                    meta["load_radius"] = args.load_radius
                if args.load_magnitude:
                    meta["load_magnitude"] = args.load_magnitude
        except ValueError as e:
            raise SystemExit(str(e))
        meta["load_nodes"] = np.asarray(picked).tolist()
        meta["rise_frames"] = args.rise_frames
    if args.damping is not None:
        if not (np.isfinite(args.damping) and args.damping >= 0):
            raise SystemExit(f"--damping must be a finite number >= 0, got {args.damping}")
        scene = scene._replace(damping=args.damping)
    if args.density is not None:
        from .material import mooney_rivlin

        m = scene.material   # rebuilt through mooney_rivlin, which validates (a bad value raises naming it)
        try:
            mat = mooney_rivlin(m.c10, m.c01, m.d1, density=args.density, g=np.asarray(m.g), tau=np.asarray(m.tau))
        except ValueError as e:
            raise SystemExit(f"--density: {e}")
        scene = scene._replace(material=mat)
        meta["density"] = args.density
    problem = setup_scene(scene, **setup_kwargs)
    if args.integrator == "implicit":
        from .implicit import check_scope

        try:
            check_scope(problem, scene.material)
        except ValueError as e:
            raise SystemExit(f"--integrator implicit on {args.scene}: {e}")
    steps = ("1 backward-Euler step" if args.integrator == "implicit"
             else f"{problem.config.n_sub} sub-steps")
    print(f"{scene.name}: {len(forces)} cases, {len(scene.points)} nodes, {problem.config.n_frames} frames x {steps}")
    out = run_cases(scene, problem, forces, args.out, batch_size=args.batch, progress=not args.no_progress,
                    xdmf=args.xdmf, metadata=meta, sim_ids=sim_ids,
                    velocity=args.velocity or ("gradient" if args.scene == "beam-reference" else "solver"),
                    worker=worker, integrator=args.integrator, newton_iterations=args.newton_iterations)
    print(f"wrote {out}" if out is not None else f"worker {args.worker} done; the last worker writes {args.out}")
    return 0


def _held_out_load_nodes(path) -> list:
    """The load nodes of the val and test cases of a bunny data set (its metadata's load_nodes by sim id)."""
    import json

    import numpy as np

    with np.load(path) as d:
        meta = json.loads(str(d["metadata"]))
        ids = np.concatenate([d[k] for k in ("split_val", "split_test") if k in d.files])
        sims = list(d["sim_id"])
    if "load_nodes" not in meta:
        raise SystemExit(f"--exclude-loads-of {path}: its metadata has no load_nodes")
    nodes = np.asarray(meta["load_nodes"])
    return sorted({int(nodes[sims.index(i)]) for i in ids})
