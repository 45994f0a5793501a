"""``tignn generate SCENE``: FEM data sets of the paper's scenes or of your own mesh, resumable, in the documented
data format.

Each scene is a subcommand with only its own options (``tignn generate bunny --help``); the options every scene
shares (output, workers, material overrides, integrator) are listed under "common options". ``tignn generate mesh
--mesh FILE`` runs any tet4 or hex8 mesh meshio reads, with the material, clamps and loads given on the command
line (`fem.user_mesh`). The file format is ``docs/data_format.md``.
"""
from __future__ import annotations

from pathlib import Path

from tignn_jax.cli import UsageError

SCENES = {
    "beam-reference": "the 52 reference load cases of the 40x10x10 beam (13 positions x 4 faces), as in the paper",
    "beam-interactions": "fingertip-like patch loads on the beam that ramp, hold, move and release",
    "bunny": "point or fingertip-sized patch loads on the Stanford bunny",
    "bunny-interactions": "fingertip-like patch loads on the bunny that ramp, hold, move and release",
    "two-beams": "the upper of two crossed beams pushed down onto the lower one through contact",
    "mesh": "your own tet4 or hex8 mesh (any file meshio reads): material, clamps and loads from the options",
}
# the value of every scene-specific option where a scene does not have it
DEFAULTS = {"cases": None, "seed": 0, "load_nodes": None, "rise_frames": 10, "loads_per_case": 1,
            "exclude_loads_of": None, "load_radius": None, "load_magnitude": None, "smooth_loads": False}


def register(sub) -> None:
    p = sub.add_parser("generate", help="generate FEM data sets of the paper's scenes or your mesh (resumable)",
                       description="Generate a data set with the FEM. Resumable: finished cases are kept in "
                                   "OUT.parts/ and skipped when the command is run again. One subcommand per scene; "
                                   "see `tignn generate SCENE --help` for its options.")
    scenes = p.add_subparsers(dest="scene", metavar="SCENE", required=True)
    for name, what in SCENES.items():
        s = scenes.add_parser(name, help=what, description=f"{what[0].upper()}{what[1:]}.")
        own = s.add_argument_group(f"{name} options")
        if name == "mesh":
            s.set_defaults(func=run_mesh)
            _mesh_options(own)
            _common_options(s.add_argument_group("common options"), name)
            continue
        s.set_defaults(func=run, **DEFAULTS)
        if name != "beam-reference":
            default = {"two-beams": 6, "bunny": 100}.get(name, 64)
            own.add_argument("--cases", type=int, default=None, help=f"number of cases (default: {default})")
        if name not in ("beam-reference", "two-beams"):
            own.add_argument("--seed", type=int, default=0, help="random seed of the load cases (default: 0)")
        if name.endswith("interactions"):
            own.add_argument("--smooth-loads", action="store_true",
                             help="C¹ force histories (smooth rises and falls, a cross-fade when the patch moves)")
        if name == "bunny":
            _bunny_options(own)
        _common_options(s.add_argument_group("common options"), name)


def _bunny_options(g) -> None:
    g.add_argument("--load-nodes", default=None, help="comma-separated node ids to load instead of --cases")
    g.add_argument("--rise-frames", type=int, default=10,
                   help="frames over which each load rises smoothly, 0 = a step (default: %(default)s)")
    g.add_argument("--loads-per-case", type=int, default=1, metavar="K",
                   help="K simultaneous point loads per case, at least 6 edges apart (default: %(default)s)")
    g.add_argument("--exclude-loads-of", default=None, metavar="DATA",
                   help="with --loads-per-case > 1: never load within 2 edges of a val or test load of this data set")
    g.add_argument("--load-radius", type=float, default=None, metavar="R",
                   help="spread each load over the free surface nodes within R of its position (a fingertip-sized "
                        "press; default: a point)")
    g.add_argument("--load-magnitude", type=float, default=None, metavar="F",
                   help="total force of each load instead of 1 (the paper's unit load)")


def _mesh_options(g) -> None:
    g.add_argument("--mesh", required=True, metavar="FILE",
                   help="a tet4 or hex8 mesh in any format meshio reads (.msh, .vtu, .vtk, .inp, .med, ...)")
    g.add_argument("--c10", type=float, required=True, help="Mooney-Rivlin C10 (stress units)")
    g.add_argument("--c01", type=float, default=0.0, help="Mooney-Rivlin C01 (default: %(default)s)")
    g.add_argument("--d1", type=float, required=True, help="Mooney-Rivlin D1: bulk modulus 2/D1 (1/stress units)")
    g.add_argument("--prony", action="append", default=[], metavar="G:TAU",
                   help="a Prony term: relative modulus g and relaxation time tau (repeat for more; default: none)")
    g.add_argument("--clamp", action="append", default=[], metavar="EXPR",
                   help="clamped nodes: a plane x=0, a half-space z<=0.5, an extreme z=min, a box "
                        "box:x0,y0,z0,x1,y1,z1, or a file of node ids; repeat for a union (required)")
    g.add_argument("--load", default="fingertip", metavar="KINDS",
                   help="comma-separated load kinds, cycled over the cases: fingertip (patches that ramp, hold, "
                        "move, release), point (a press that rises and holds), pressure (a patch of pressure) "
                        "(default: %(default)s)")
    g.add_argument("--force", type=float, default=None, metavar="F",
                   help="largest total force of a fingertip or point case; each case's peak is uniform in "
                        "[0.1, 1] x F (required with those kinds)")
    g.add_argument("--pressure", type=float, default=None, metavar="P",
                   help="largest pressure of a pressure case, peaks uniform in [0.1, 1] x P (required with it)")
    g.add_argument("--radius", type=float, default=0.0, metavar="R",
                   help="spread of a point load over the surface within R, and the radius of a pressure patch "
                        "(default: a point; a pressure patch of two edge lengths)")
    g.add_argument("--rise-frames", type=int, default=10,
                   help="frames over which point and pressure loads rise, then hold (default: %(default)s)")
    g.add_argument("--frames", type=int, default=20, help="frames per case (default: %(default)s)")
    g.add_argument("--frame-dt", type=float, default=0.05, help="time between frames (default: %(default)s)")
    g.add_argument("--cases", type=int, default=32, help="number of cases (default: %(default)s)")
    g.add_argument("--seed", type=int, default=0, help="random seed of the load cases (default: 0)")


def _common_options(g, scene: str) -> None:
    g.add_argument("--out", required=True, help="output .npz path")
    own = scene == "mesh"
    g.add_argument("--damping", type=float, default=None, metavar="ALPHA",
                   help="mass-proportional damping [1/time] " + ("(default: 0)" if own else
                                                                 "instead of the scene's (beam 18.17, bunny 2.0)"))
    g.add_argument("--density", type=float, default=None, metavar="RHO", required=own,
                   help="mass density" + (" (required)" if own else " instead of the scene's (beam 7.135e-3, "
                                                                    "bunny 1e-5)"))
    g.add_argument("--integrator", choices=("explicit", "implicit"), default="explicit",
                   help="explicit central differences (default) or backward Euler at the frame step (elastic "
                        "scenes without contact)")
    g.add_argument("--newton-iterations", type=int, default=12, metavar="K",
                   help="with --integrator implicit: at most K Newton iterations per frame (default: %(default)s)")
    default = "gradient" if scene == "beam-reference" else "solver"
    g.add_argument("--velocity", choices=("gradient", "solver"), default=None,
                   help="z's velocity: the solver's (zero at the rest start) or the gradient of q over the frames "
                        f"(the reference data's convention); default: {default}")
    g.add_argument("--worker", default="0/1", metavar="K/N",
                   help="run only cases c with c mod N = K (N processes share the work; the last writes --out)")
    g.add_argument("--batch", type=int, default=8, help="cases per vmapped batch (default: %(default)s)")
    g.add_argument("--paraview", dest="xdmf", action="store_true", help="also write a ParaView series per case "
                                                                         "(.pvd + VTU frames)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args) -> int:
    import numpy as np

    from fem import cases as cs
    from fem.generate import run_cases
    from fem.scenes import (beam_reference_forces, beam_scene, bunny_scene, setup_scene, two_beams_contact,
                         two_beams_forces, two_beams_scene)

    if args.cases is not None and args.cases < 1:
        raise UsageError(f"--cases must be positive, got {args.cases}")
    if args.batch < 1:
        raise UsageError(f"--batch must be positive, got {args.batch}")
    if args.newton_iterations < 1:
        raise UsageError(f"--newton-iterations must be positive, got {args.newton_iterations}")
    if args.newton_iterations != 12 and args.integrator != "implicit":
        raise UsageError("--newton-iterations applies only with --integrator implicit")
    try:
        worker = tuple(int(t) for t in args.worker.split("/"))
        if len(worker) != 2 or not 0 <= worker[0] < worker[1]:
            raise ValueError
    except ValueError:
        raise UsageError(f"--worker must be K/N with 0 <= K < N, got {args.worker!r}")
    meta = {"seed": args.seed, "command": f"tignn generate {args.scene}"}
    sim_ids = None
    setup_kwargs = {}
    if args.scene == "two-beams":
        scene = two_beams_scene()
        forces = two_beams_forces(scene)
        if args.cases and args.cases > len(forces):
            raise UsageError(f"--cases {args.cases}: the two-beams scene has {len(forces)} cases")
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
            raise UsageError(f"--loads-per-case must be >= 1, got {args.loads_per_case}")
        if args.exclude_loads_of and args.loads_per_case == 1:
            raise UsageError("--exclude-loads-of applies only with --loads-per-case > 1 (single-load cases take "
                             "their positions from --cases/--seed or --load-nodes)")
        if args.load_nodes and args.loads_per_case > 1:
            raise UsageError("--load-nodes cannot be combined with --loads-per-case > 1 (multi-load cases place "
                             "their loads themselves)")
        if args.load_radius is not None and args.loads_per_case > 1:
            raise UsageError("--load-radius applies only to single-load cases (--loads-per-case 1)")
        if args.load_magnitude is not None and (args.loads_per_case > 1 or not np.isfinite(args.load_magnitude)
                                                or args.load_magnitude <= 0):
            raise UsageError(f"--load-magnitude must be a positive number and applies only to single-load cases, "
                             f"got {args.load_magnitude} with --loads-per-case {args.loads_per_case}")
        if args.load_nodes:
            try:
                nodes = [int(t) for t in args.load_nodes.split(",") if t.strip()]
            except ValueError:
                raise UsageError(f"--load-nodes must be comma-separated integers, got {args.load_nodes!r}")
        if not 0 <= args.rise_frames <= scene.n_frames:
            raise UsageError(f"--rise-frames must be in 0..{scene.n_frames}, got {args.rise_frames}")
        if args.load_radius is not None and not (np.isfinite(args.load_radius) and args.load_radius >= 0):
            raise UsageError(f"--load-radius must be a finite number >= 0, got {args.load_radius}")
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
            raise UsageError(f"--load-nodes {args.load_nodes}: {e}" if nodes else str(e))
        meta["load_nodes"] = np.asarray(picked).tolist()
        meta["rise_frames"] = args.rise_frames
    if args.damping is not None:
        if not (np.isfinite(args.damping) and args.damping >= 0):
            raise UsageError(f"--damping must be a finite number >= 0, got {args.damping}")
        scene = scene._replace(damping=args.damping)
    if args.density is not None:
        from fem.material import mooney_rivlin

        m = scene.material   # rebuilt through mooney_rivlin, which validates (a bad value raises naming it)
        try:
            mat = mooney_rivlin(m.c10, m.c01, m.d1, density=args.density, g=np.asarray(m.g), tau=np.asarray(m.tau))
        except ValueError as e:
            raise UsageError(f"--density: {e}")
        scene = scene._replace(material=mat)
        meta["density"] = args.density
    problem = setup_scene(scene, **setup_kwargs)
    if args.integrator == "implicit":
        from fem.implicit import check_scope

        try:
            check_scope(problem, scene.material)
        except ValueError as e:
            raise UsageError(f"--integrator implicit on {args.scene}: {e}")
    steps = ("1 backward-Euler step" if args.integrator == "implicit"
             else f"{problem.config.n_sub} sub-steps")
    print(f"{scene.name}: {len(forces)} cases, {len(scene.points)} nodes, {problem.config.n_frames} frames x {steps}")
    out = run_cases(scene, problem, forces, args.out, batch_size=args.batch, progress=not args.no_progress,
                    xdmf=args.xdmf, metadata=meta, sim_ids=sim_ids,
                    velocity=args.velocity or ("gradient" if args.scene == "beam-reference" else "solver"),
                    worker=worker, integrator=args.integrator, newton_iterations=args.newton_iterations)
    print(f"wrote {out}" if out is not None else f"worker {args.worker} done; the last worker writes {args.out}")
    return 0


def run_mesh(args) -> int:
    """``tignn generate mesh``: check the mesh, material, clamps and loads, then run the cases (resumable)."""
    import numpy as np

    from fem import user_mesh as um
    from fem.generate import run_cases
    from fem.material import mooney_rivlin
    from fem.scenes import setup_scene

    _check_run_options(args)
    for name in ("cases", "frames", "batch"):
        if getattr(args, name) < 1:
            raise UsageError(f"--{name} must be positive, got {getattr(args, name)}")
    if not 0 <= args.rise_frames <= args.frames:
        raise UsageError(f"--rise-frames must be in 0..{args.frames}, got {args.rise_frames}")
    for name in ("frame_dt", "density"):
        value = getattr(args, name)
        if not (np.isfinite(value) and value > 0):
            raise UsageError(f"--{name.replace('_', '-')} must be a positive number, got {value}")
    try:
        g, tau = zip(*(_prony(t) for t in args.prony)) if args.prony else ((), ())
        material = mooney_rivlin(args.c10, args.c01, args.d1, density=args.density, g=g, tau=tau)
    except ValueError as e:
        raise UsageError(f"material: {e}")
    kinds = [k.strip() for k in args.load.split(",") if k.strip()]
    bad = [k for k in kinds if k not in um.LOAD_KINDS]
    if not kinds or bad:
        raise UsageError(f"--load {args.load!r}: kinds must be among {', '.join(um.LOAD_KINDS)}")
    for flag, value, needs in (("--force", args.force, ("fingertip", "point")), ("--pressure", args.pressure,
                                                                                   ("pressure",))):
        if any(k in kinds for k in needs) and value is None:
            raise UsageError(f"{flag} is required with --load {','.join(k for k in kinds if k in needs)}")
        if value is not None and not (np.isfinite(value) and value > 0):
            raise UsageError(f"{flag} must be a positive number, got {value}")
    if not (np.isfinite(args.radius) and args.radius >= 0):
        raise UsageError(f"--radius must be a finite number >= 0, got {args.radius}")
    if args.damping is not None and not (np.isfinite(args.damping) and args.damping >= 0):
        raise UsageError(f"--damping must be a finite number >= 0, got {args.damping}")
    try:
        mesh = um.read_volume_mesh(args.mesh)
    except ValueError as e:
        raise UsageError(str(e))
    try:
        clamped = um.clamp_nodes(mesh.points, args.clamp, mesh.file_ids)
    except ValueError as e:
        raise UsageError(f"--clamp: {e}")
    try:
        um.check_surface(mesh.points, mesh.cells)
    except ValueError as e:
        raise UsageError(f"--mesh {args.mesh}: {e}")
    scene = um.mesh_scene(mesh, material, clamped, frame_dt=args.frame_dt, n_frames=args.frames,
                          damping=args.damping or 0.0, name=Path(args.mesh).stem)
    try:
        forces, described = um.mesh_forces(scene, kinds, args.cases, args.seed, force=args.force,
                                           pressure=args.pressure, radius=args.radius,
                                           rise_frames=args.rise_frames)
    except ValueError as e:
        raise UsageError(str(e))
    problem = setup_scene(scene)
    if args.integrator == "implicit":
        from fem.implicit import check_scope

        try:
            check_scope(problem, scene.material)
        except ValueError as e:
            raise UsageError(f"--integrator implicit on {args.mesh}: {e}")
    meta = {"seed": args.seed, "command": "tignn generate mesh", "mesh_file": str(args.mesh),
            "clamp": list(args.clamp), "clamped_nodes": int(len(clamped)), "loads": kinds,
            "force": args.force, "pressure": args.pressure, "cases": described}
    steps = "1 backward-Euler step" if args.integrator == "implicit" else f"{problem.config.n_sub} sub-steps"
    print(f"{scene.name}: {len(forces)} cases, {len(scene.points)} nodes ({len(clamped)} clamped), "
          f"{len(scene.cells)} {scene.cell_type} cells, {problem.config.n_frames} frames x {steps}")
    worker = _worker(args.worker)
    out = run_cases(scene, problem, forces, args.out, batch_size=args.batch, progress=not args.no_progress,
                    xdmf=args.xdmf, metadata=meta, velocity=args.velocity or "solver", worker=worker,
                    integrator=args.integrator, newton_iterations=args.newton_iterations)
    print(f"wrote {out}" if out is not None else f"worker {args.worker} done; the last worker writes {args.out}")
    return 0


def _prony(text: str):
    try:
        g, tau = (float(t) for t in text.split(":"))
    except ValueError:
        raise UsageError(f"--prony {text!r}: a term is G:TAU, e.g. 0.3:0.2") from None
    return g, tau


def _check_run_options(args) -> None:
    if args.newton_iterations < 1:
        raise UsageError(f"--newton-iterations must be positive, got {args.newton_iterations}")
    if args.newton_iterations != 12 and args.integrator != "implicit":
        raise UsageError("--newton-iterations applies only with --integrator implicit")


def _worker(text: str) -> tuple:
    try:
        worker = tuple(int(t) for t in text.split("/"))
        if len(worker) != 2 or not 0 <= worker[0] < worker[1]:
            raise ValueError
    except ValueError:
        raise UsageError(f"--worker must be K/N with 0 <= K < N, got {text!r}") from None
    return worker


def _held_out_load_nodes(path) -> list:
    """The load nodes of the val and test cases of a bunny data set (its metadata's load_nodes by sim id)."""
    import json

    import numpy as np

    from tignn_jax.data import NOT_AN_ARCHIVE

    try:
        with np.load(path, allow_pickle=False) as d:
            if not {"metadata", "sim_id"} <= set(d.files):
                raise UsageError(f"--exclude-loads-of {path}: not a generated bunny data set (no metadata or sim_id)")
            meta = json.loads(str(d["metadata"]))
            ids = np.concatenate([d[k] for k in ("split_val", "split_test") if k in d.files])
            sims = list(d["sim_id"])
    except NOT_AN_ARCHIVE as err:
        raise UsageError(f"--exclude-loads-of {path}: not a data file ({type(err).__name__})") from err
    if not isinstance(meta, dict) or "load_nodes" not in meta:
        raise UsageError(f"--exclude-loads-of {path}: its metadata has no load_nodes")
    nodes = np.asarray(meta["load_nodes"])
    return sorted({int(nodes[sims.index(i)]) for i in ids})
