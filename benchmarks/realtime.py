"""The real-time budget: does the demo's mixed-reality loop, and the public step, fit a frame on this CPU?

Question: with the shipped models, does each stage of the loop `tignn demo` runs meet its budget, and does the
public, checked ``tignn_jax.step(params, graph, forces)`` meet the same budgets as the unchecked
``tignn_jax.stepper`` the loop steps with? Budgets: simulation (forces + step) p50 ≤ 9 ms for one beam, ≤ 18 ms for
the two beams, ≤ 11 ms for the bunny, p99 ≤ 1.5 × p50 (judged on the frames the learned model stepped); the whole
frame p50 ≤ 33 ms (≥ 30 frames per second).

How:

* The process is set up as ``tignn demo``'s: XLA:CPU options (`tignn_jax.mr.runtime.real_time_xla_flags`), then
  pinned to ``--cores`` cores (default 1, the demo's) with one CPU device per core
  (`tignn_jax.mr.runtime.real_time_cores`), both before JAX's first operation.
* Each row is a demo scene built by `tignn_jax.cli.demo.build_scene` with its shipped model (``beam``: one beam,
  ``two-beams``: two beams in contact, ``bunny``), so the bodies step through ``tignn_jax.stepper`` exactly as in
  the demo; every frame is stepped (no rest skip), at 640×480. `tignn_jax.mr.run` plays the fingertip press for
  ``--frames`` frames after ``--warmup`` untimed ones and times forces, step, render, write and the whole frame.
  Once a body is touched the loop dispatches forces and step together (``Scene.fuse``), so the forces' time is
  inside the step's; simulation = forces + step.
* Each scene's loop runs ``--rounds`` times; the round with the median simulation p99 / p50 is judged, and every
  round's p50 / p99 is reported.
* After each round, in the same process, the step is timed on its own, the variants interleaved call by call (so
  a change of the machine's load hits all alike), the same input every call (the scene's initial states under
  the forces of the track's middle frame, the fingertip pressing): the loop's step program (`tignn_jax.mr.build`),
  ``tignn_jax.stepper(params, bodies)`` and ``tignn_jax.step(params, graph, forces)`` on
  ``tignn_jax.rest_graph(params, bodies)``, with the forces as the device array the loop's forces stage returns
  and as a host (numpy) array. ``step`` checks its arguments on every call and then runs the stepper's compiled
  program (their states are compared). The public step's budget verdict: the loop's simulation p50 with the
  loop's step program replaced by the public step (p50 against p50), and the public step's own p99 / p50.
* ``--fusion-rounds``: the loop fused against its stages dispatched and awaited one by one (``Scene.fuse``),
  alternating in the same process.
* The machine's own tail: fixed programs of the loop's duration that do the same work every call
  (`platform_jitter`); a loop cannot have a smaller tail than its machine.

Writes ``realtime.{json,md}`` (``realtime_TAG.*`` with ``--tag``) to ``--out`` (default benchmarks/results), with
the CPU, its core count and load average at start and end: a load above the core count means other processes
shared the CPU. ``--quick`` is a smoke test (few frames, one round), not a measurement.

    python benchmarks/realtime.py [--frames 500] [--warmup 20] [--rounds 3] [--scenes beam,two-beams,bunny]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import RESULTS_DIR, describe, machine_line, interleaved_ms, write_results  # noqa: E402

BUDGET_MS = {"beam": 9.0, "two-beams": 18.0, "bunny": 11.0}
FRAME_BUDGET_MS = 1e3 / 30
P99_RATIO = 1.5
# the step variants timed on their own after every round (`step_programs`)
LOOP_STEP, STEPPER, STEP_DEVICE, STEP_HOST = ("loop's step program", "tignn_jax.stepper",
                                              "tignn_jax.step, device forces", "tignn_jax.step, host forces")
QUICK = {"frames": 10, "warmup": 2, "rounds": 1, "fusion_rounds": 0, "fusion_frames": 10}


def percentiles(ms) -> dict:
    ms = np.asarray(ms, float)
    return {"p50_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)), "mean_ms": float(ms.mean()),
            "p99_over_p50": float(np.percentile(ms, 99) / np.median(ms))}


def moving_scene(name: str, frames: int, devices: tuple = (), model: str | None = None):
    """(scene, dynamics) of ``tignn demo``'s scene ``name`` for ``frames`` frames with the demo's model, every
    frame stepped (no rest skip): the budget is for a body in motion."""
    from tignn_jax.cli.demo import build_scene

    scene, dynamics = build_scene(name, frames, model, devices=devices)
    return scene._replace(skip_rest=False), dynamics


def run_scene(name: str, frames: int, warmup: int, devices: tuple = (), model: str | None = None,
              rounds: int = 1, public: bool = True) -> dict:
    """The scene's loop, ``rounds`` times ``frames`` frames after ``warmup``, each round followed by its step
    programs alone (`step_programs`; without ``public`` the loop's program only). The round whose simulation
    p99 / p50 over the learned-step frames is the median of the rounds' (the lower median for an even count) is
    judged."""
    from tignn_jax import mr

    scene, dynamics = moving_scene(name, frames + warmup, devices, model)
    programs_fn = step_programs(scene, name, model, public)
    played, programs = [], []
    for _ in range(rounds):
        _, t = mr.run(scene, frames=frames + warmup, warmup=warmup)
        summary = t.summary(bodies=len(scene.bodies))
        learned = summary.get("simulation_learned", summary["simulation"])
        played.append((learned["p99_ms"] / learned["p50_ms"], learned, t, summary))
        programs.append(programs_fn(frames))
    judged = sorted(range(rounds), key=lambda i: played[i][0])[(rounds - 1) // 2]
    _, learned, t, summary = played[judged]
    out = {"dynamics": dynamics, "valid": not dynamics.startswith("STAND-IN"), "bodies": len(scene.bodies),
           "nodes": int(sum(len(b.q0) for b in scene.bodies)), "image": [scene.camera.width, scene.camera.height],
           "frames": summary["frames"], "learned_frames": summary.get("learned_frames", summary["frames"]),
           "reallocations": t.reallocations, "guard_trips": t.guard_trips, "fused_frames": t.fused_frames,
           "rounds": [{"p50_ms": x[1]["p50_ms"], "p99_ms": x[1]["p99_ms"]} for x in played],
           "judged_round": judged, "step_programs": programs,
           **{k: summary[k] for k in ("forces", "step", "simulation", "render", "frame")},
           "simulation_learned": learned, "simulation_by_class": summary.get("simulation_by_class", {})}
    p50, p99 = learned["p50_ms"], learned["p99_ms"]
    out["budget"] = {"simulation_p50_ms": BUDGET_MS[name], "simulation_p50_ok": p50 <= BUDGET_MS[name],
                     "p99_over_p50": p99 / p50, "p99_ok": p99 <= P99_RATIO * p50,
                     "frame_p50_ok": out["frame"]["p50_ms"] <= FRAME_BUDGET_MS,
                     "fps_at_p50": 1e3 / out["frame"]["p50_ms"]}
    out["public_step"] = public_verdict(out, programs[judged], name)
    return out


def step_programs(scene, name: str, model: str | None, public: bool = True):
    """``fn(calls) -> {variant: percentiles, ...}``: the step on its own, ``calls`` calls of each variant
    interleaved, every call awaited: the loop's step program over all bodies (`tignn_jax.mr.build`'s, as the loop
    dispatches it, on its device with ``Scene.devices``; no guard, no render between calls),
    ``tignn_jax.stepper(params, bodies)`` and ``tignn_jax.step`` on ``rest_graph(params, bodies)`` with device and
    host forces. The same input every call: the scene's initial states under the forces of the track's middle
    frame. Without ``public``, or for a dynamics that is not a model (``fem-newton``), the loop's program only. Also
    returned: the largest difference between the states of ``step`` and ``stepper`` (0: the same program)."""
    import jax
    import jax.numpy as jnp

    import tignn_jax
    from tignn_jax import api, mr
    from tignn_jax.cli.demo import DEFAULT_MODELS, FEM_NEWTON

    forces_fn, step_fn, _, _ = mr.build(scene)
    zs = tuple(jnp.asarray(b.z, jnp.float32) for b in scene.bodies)
    if scene.devices:
        zs = tuple(jax.device_put(z, scene.devices[0]) for z in zs)
    forces = jax.block_until_ready(forces_fn(zs, jnp.asarray(scene.track[len(scene.track) // 2])))
    fns = {LOOP_STEP: lambda: step_fn(zs, forces)}
    extra = {}
    model = model or DEFAULT_MODELS[name]
    if public and model != FEM_NEWTON:
        params, _ = api.load_pretrained(model)   # (memoised by `share_loaded_models`)
        bodies = len(scene.bodies)
    if public and model != FEM_NEWTON and scene.step is not None:
        # bodies in contact: their public step is tignn_jax.contact_stepper (one frame of all of them); the
        # stepper column is its function called directly, the step columns it with device and host forces
        from tignn_jax.cli.demo import IMPLICIT_CONTACT
        contact = tignn_jax.contact_stepper(params, [np.asarray(b.model) for b in scene.bodies], *IMPLICIT_CONTACT)
        host = tuple(np.asarray(f) for f in forces)
        fns[STEPPER] = lambda: contact(zs, forces)
        fns[STEP_DEVICE] = lambda: contact(zs, forces)
        fns[STEP_HOST] = lambda: contact(zs, host)
        ref = [np.asarray(z) for z in step_fn(zs, forces)]
        extra["public_api"] = "tignn_jax.contact_stepper"
        extra["max_abs_difference_step_vs_stepper"] = max(
            float(np.abs(np.asarray(a) - b).max()) for a, b in zip(contact(zs, host), ref))
    elif public and model != FEM_NEWTON:
        graph = tignn_jax.rest_graph(params, bodies)
        graph = graph._replace(nodes={**graph.nodes, "z": jnp.concatenate(zs)})
        f_device = jax.block_until_ready(jnp.concatenate(forces))
        f_host = np.asarray(f_device)
        stepper = tignn_jax.stepper(params, bodies)
        z = graph.nodes["z"]
        fns[STEPPER] = lambda: stepper(z, f_device)
        fns[STEP_DEVICE] = lambda: tignn_jax.step(params, graph, f_device).nodes["z"]
        fns[STEP_HOST] = lambda: tignn_jax.step(params, graph, f_host).nodes["z"]
        ref = np.asarray(stepper(z, f_device))
        extra["max_abs_difference_step_vs_stepper"] = max(
            float(np.abs(np.asarray(tignn_jax.step(params, graph, f).nodes["z"]) - ref).max())
            for f in (f_device, f_host))
    for fn in fns.values():   # compiled and warm (interleaved_ms calls each once more)
        for _ in range(3):
            jax.block_until_ready(fn())

    def run(calls: int) -> dict:
        return {**{k: percentiles(v) for k, v in interleaved_ms(fns, calls).items()}, **extra}

    return run


def share_loaded_models() -> None:
    """Load each model once per process: ``tignn_jax.load_pretrained`` memoised by name, so the demo's scene
    (`tignn_jax.cli.demo.build_scene`, which loads its model on every call) and the public-step comparison share
    one copy (a linear model's A⁻¹ is computed when it is loaded). The returned models are not changed."""
    from functools import lru_cache

    from tignn_jax import api

    if not hasattr(api.load_pretrained, "cache_info"):
        api.load_pretrained = lru_cache(maxsize=None)(api.load_pretrained)


def public_verdict(s: dict, programs: dict, name: str) -> dict | None:
    """Whether the loop would meet the simulation budget stepping with ``tignn_jax.step`` instead of its own step
    program: its simulation p50 (learned-step frames) with the loop's step program's p50 replaced by the public
    step's (the slower of device and host forces), and the public step's own p99 / p50. Also the public step's
    extra time over the stepper (its checks)."""
    if STEPPER not in programs:
        return None
    public = max(programs[k]["p50_ms"] for k in (STEP_DEVICE, STEP_HOST))
    extra = public - programs[LOOP_STEP]["p50_ms"]
    p50 = s["simulation_learned"]["p50_ms"] + max(extra, 0.0)
    ratio = max(programs[k]["p99_over_p50"] for k in (STEP_DEVICE, STEP_HOST))
    return {"public_step_p50_ms": public, "extra_over_loop_step_p50_ms": extra,
            "check_overhead_p50_ms": public - programs[STEPPER]["p50_ms"],
            "stepper_over_loop_step_p50": programs[STEPPER]["p50_ms"] / programs[LOOP_STEP]["p50_ms"],
            "simulation_p50_ms_estimated": p50, "simulation_p50_ok": p50 <= BUDGET_MS[name],
            "public_step_p50_ok": public <= BUDGET_MS[name], "p99_over_p50": ratio, "p99_ok": ratio <= P99_RATIO,
            "meets": bool(p50 <= BUDGET_MS[name] and ratio <= P99_RATIO)}


def loop_fusion(name: str, frames: int, warmup: int, devices: tuple, rounds: int, model: str | None = None) -> dict:
    """The scene's loop with its simulation stages fused (``Scene.fuse``: forces, step and guard dispatched
    together and awaited once per frame) against the stages dispatched and awaited one by one, alternating for
    ``rounds`` rounds of ``frames`` frames in this process. Simulation p50 / p99 over the learned-step frames per
    run, their medians over the rounds and the ratio of the p50s."""
    from tignn_jax import mr

    scene, _ = moving_scene(name, frames + warmup, devices, model)
    runs = {"staged": [], "fused": []}
    for _ in range(rounds):
        for label, fuse in (("staged", False), ("fused", True)):
            _, t = mr.run(scene._replace(fuse=fuse), frames=frames + warmup, warmup=warmup)
            summary = t.summary()
            runs[label].append(summary.get("simulation_learned", summary["simulation"]))
    p50 = {k: float(np.median([r["p50_ms"] for r in v])) for k, v in runs.items()}
    return {"frames": frames, "rounds": rounds, "runs": runs, "p50_ms": p50,
            "p99_ms": {k: float(np.median([r["p99_ms"] for r in v])) for k, v in runs.items()},
            "speedup_fused_vs_staged": p50["staged"] / p50["fused"]}


def platform_jitter(target_ms: float, calls: int = 500) -> dict:
    """p50, p99 and their ratio for fixed programs of about ``target_ms`` that do the same work every call, timed
    like the loop's stages: a jitted XLA program (dense 420×420 products and tanh in a loop; its data fit in the
    caches), an element-wise numpy loop (tanh over 420×420, one thread) and a jitted XLA loop of products of a
    3000×3000 float32 matrix (36 MB) with a vector, bound by memory traffic like a linear model's product with
    A⁻¹ (the beam's 21 MB, the bunny's 64 MB). Their p99/p50 is the tail this machine gives a program of that
    duration and kind."""
    import jax
    import jax.numpy as jnp

    a = np.random.default_rng(0).normal(size=(420, 420)).astype(np.float32)
    big = jnp.asarray(np.random.default_rng(1).normal(size=(3000, 3000)).astype(np.float32) / 3000 ** 0.5)

    def xla_program(n):
        fn = jax.jit(lambda x: jax.lax.fori_loop(0, n, lambda i, y: jnp.tanh(y @ x * 1e-3), x))
        xa = jnp.asarray(a)
        return lambda: fn(xa).block_until_ready()

    def xla_matvec_program(n):
        fn = jax.jit(lambda m, y: jax.lax.fori_loop(0, n, lambda i, y: jnp.tanh(m @ y), y))
        y0 = jnp.ones(3000, jnp.float32)
        return lambda: fn(big, y0).block_until_ready()

    def numpy_program(n):
        def fn():
            x = a
            for _ in range(n):
                x = np.tanh(x * 0.999 + 1e-3)
            return x
        return fn

    out = {}
    for name, make in (("XLA, cache-resident", xla_program), ("numpy element-wise, one thread", numpy_program),
                       ("XLA matrix-vector products over 36 MB, memory-bound", xla_matvec_program)):
        probe = make(4)
        probe()
        t0 = time.perf_counter()
        for _ in range(5):
            probe()
        per_iteration = 1e3 * (time.perf_counter() - t0) / 20
        n = max(1, round(target_ms / per_iteration))
        fn = make(n)
        fn()
        ms = []
        for _ in range(calls):
            t0 = time.perf_counter()
            fn()
            ms.append(1e3 * (time.perf_counter() - t0))
        out[name] = {**percentiles(ms), "iterations": n}
    return out


def parse_args(argv=None):
    parser = argparse.ArgumentParser(
        description="The real-time budget of the demo's mixed-reality loop per stage, and the public "
                    "tignn_jax.step against tignn_jax.stepper, with the shipped models; writes realtime.{json,md}.")
    parser.add_argument("--frames", type=int, default=None,
                        help="timed frames per scene and round, at least 10; also the calls per step variant "
                             "after each round (default: 500; --quick: 10)")
    parser.add_argument("--warmup", type=int, default=None,
                        help="untimed first frames of every loop, at least 1 (default: 20; --quick: 2)")
    parser.add_argument("--rounds", type=int, default=None,
                        help="runs of each scene's loop; the one with the median simulation p99 / p50 is judged, "
                             "every round reported (default: 3; --quick: 1)")
    parser.add_argument("--scenes", default="beam,two-beams,bunny",
                        help=f"rows, comma-separated, from {list(BUDGET_MS)} (default: %(default)s)")
    parser.add_argument("--fusion-rounds", type=int, default=None,
                        help="rounds of the fused-against-staged loop comparison per scene; 0 skips it "
                             "(default: 2; --quick: 0)")
    parser.add_argument("--fusion-frames", type=int, default=None,
                        help="timed frames per run of that comparison, at least 10 (default: 200; --quick: 10)")
    parser.add_argument("--cores", type=int, default=1,
                        help="cores the process runs on, as `tignn demo --cores`: pinned to that many of the CPUs it "
                             "may use, one CPU device per core, one body per device (default: %(default)s, the "
                             "demo's)")
    parser.add_argument("--model", default=None,
                        help="the dynamics of every scene, as `tignn demo --model`: a shipped model, a model folder "
                             "or .npz on the scenes' mesh, or 'fem-newton' (the FEM's Newton-CG step, not learned; "
                             "run without the learned loop's XLA:CPU option and without the public-step "
                             "comparison) (default: each scene's shipped model)")
    parser.add_argument("--quick", action="store_true",
                        help="a smoke test: 10 frames after 2, one round, no fusion comparison (each unless given)")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR,
                        help="folder the results are written to (default: benchmarks/results)")
    parser.add_argument("--tag", default="", help="write realtime_TAG.{json,md} instead of realtime.*")
    args = parser.parse_args(argv)
    defaults = QUICK if args.quick else {"frames": 500, "warmup": 20, "rounds": 3, "fusion_rounds": 2,
                                         "fusion_frames": 200}
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.frames < 10 or args.warmup < 1 or args.rounds < 1 or args.fusion_rounds < 0 or args.fusion_frames < 10:
        raise SystemExit(f"--frames must be ≥ 10, --warmup ≥ 1, --rounds ≥ 1, --fusion-rounds ≥ 0 and "
                         f"--fusion-frames ≥ 10, got {args.frames}, {args.warmup}, {args.rounds}, "
                         f"{args.fusion_rounds} and {args.fusion_frames}")
    if args.cores < 1:
        raise SystemExit(f"--cores must be at least 1, got {args.cores}")
    args.scene_list = [s for s in args.scenes.split(",") if s]
    bad = [s for s in args.scene_list if s not in BUDGET_MS]
    if bad or not args.scene_list:
        raise SystemExit(f"unknown scene(s) {bad}; choose from {list(BUDGET_MS)}")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    from tignn_jax import mr
    from tignn_jax.cli.demo import FEM_NEWTON

    share_loaded_models()
    fem = args.model == FEM_NEWTON
    flagged = False if fem else mr.real_time_xla_flags()   # before JAX's first operation, as `tignn demo`
    try:
        pinned, devices = mr.real_time_cores(args.cores)   # likewise: pinned, one CPU device per core
    except ValueError as e:
        raise SystemExit(f"--cores {args.cores}: {e}")
    machine = describe()
    machine.update(cpu_devices=len(devices), pinned_cpus=list(pinned), xla_flags=os.environ.get("XLA_FLAGS", "") + (
        " (fem-newton: the learned loop's option left unset)" if fem else "" if flagged else " (set by the user)"))
    scenes, fusion = {}, {}
    for name in args.scene_list:
        print(f"scene {name}: {args.rounds} round(s) of {args.frames} frames after {args.warmup} ...", flush=True)
        scenes[name] = run_scene(name, args.frames, args.warmup, devices, args.model, args.rounds)
        if args.fusion_rounds > 0 and scenes[name]["valid"]:
            print(f"scene {name}: fused against staged loop, {args.fusion_rounds} round(s) ...", flush=True)
            fusion[name] = loop_fusion(name, args.fusion_frames, args.warmup, devices, args.fusion_rounds,
                                       args.model)
    target = float(np.median([s["simulation_learned"]["p50_ms"] for s in scenes.values()]))
    print(f"platform tail: fixed programs of about {target:.1f} ms ...", flush=True)
    jitter = platform_jitter(target, calls=args.frames)
    machine["load_average_1m_at_end"] = describe()["load_average_1m"]
    result = {"machine": machine, "model": args.model, "quick": args.quick, "frames": args.frames,
              "warmup": args.warmup, "rounds": args.rounds, "scenes": scenes, "loop_fusion": fusion,
              "platform_jitter": jitter,
              "budgets_ms": {"simulation_p50": BUDGET_MS, "frame_p50": FRAME_BUDGET_MS, "p99_over_p50": P99_RATIO}}
    write_results(f"realtime_{args.tag}" if args.tag else "realtime", result, format_md(result), folder=args.out)
    return 0


def forces_cell(s: dict) -> str:
    """The forces stage's p50, or where most frames ran forces and step fused a note that it is in the step's."""
    fused = s.get("fused_frames", 0)
    if 2 * fused > s["frames"]:
        return f"in step ({fused}/{s['frames']} fused)"
    return f"{s['forces']['p50_ms']:.2f}"


def verdict(s: dict) -> str:
    b = s["budget"]
    if not s["valid"]:
        return "STAND-IN, not valid"
    why = [w for w, ok in (("sim p50", b["simulation_p50_ok"]), ("p99 > 1.5·p50", b["p99_ok"]),
                           ("frame", b["frame_p50_ok"])) if not ok]
    return "meets" if not why else "misses: " + ", ".join(why)


def public_cell(s: dict) -> str:
    v = s.get("public_step")
    if v is None:
        return "—"
    why = [w for w, ok in (("sim p50", v["simulation_p50_ok"]), ("p99 > 1.5·p50", v["p99_ok"])) if not ok]
    return (f"{v['simulation_p50_ms_estimated']:.2f} ({v['extra_over_loop_step_p50_ms']:+.2f}); "
            + ("meets" if not why else "misses: " + ", ".join(why)))


def format_md(result: dict) -> str:
    m = result["machine"]
    pinned = (f"pinned to CPU {', '.join(map(str, m['pinned_cpus']))} of {m['cores']} with {m['cpu_devices']} CPU "
              f"device(s) (`tignn_jax.mr.real_time_cores`, as `tignn demo --cores {len(m['pinned_cpus'])}`; one "
              "core against two: `pinning.md`)" if m.get("pinned_cpus") else
              f"not pinned, {m.get('cpu_devices', '?')} CPU device(s)")
    lines = ["# Real-time budget: the demo's loop per frame, and the public step", "",
             machine_line(m) + "; load average "
             f"{m['load_average_1m']} at start, {m['load_average_1m_at_end']} at end ({m['note']}). "
             f"{result['frames']} timed frames per scene and round after {result['warmup']} warm-up frames, "
             f"{result['rounds']} round(s), 640×480; XLA_FLAGS `{m['xla_flags']}`; the process {pinned}."
             + (" QUICK RUN (smoke test): not a measurement." if result.get("quick") else ""), "",
             "Each scene as `tignn demo` builds it (`tignn_jax.cli.demo.build_scene`), its bodies stepped by "
             "`tignn_jax.stepper`. Simulation = forces + step per frame, judged on the frames the learned model "
             f"stepped: p50 ≤ the budget, p99 ≤ {P99_RATIO} × p50; whole frame p50 ≤ 33 ms. The last column: "
             "the same loop stepping with `tignn_jax.step` (checked), its simulation p50 estimated as the loop's "
             "with the loop's step program replaced by the public step (the difference of their p50s alone, next "
             "table, in brackets), and its verdict (p99 of the public step alone ≤ 1.5 × its p50).", "",
             "| scene | dynamics | nodes | forces p50 | step p50 | simulation p50 / p99 (budget; frames) | "
             "render p50 | frame p50 / p99 | fps | guard trips | verdict | with tignn_jax.step: sim p50 ms "
             "(extra); verdict |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, s in result["scenes"].items():
        b, sim = s["budget"], s["simulation_learned"]
        lines.append(
            f"| {name} | {s['dynamics']} | {s['nodes']} | {forces_cell(s)} | {s['step']['p50_ms']:.2f} | "
            f"{sim['p50_ms']:.2f} / {sim['p99_ms']:.2f} ({b['simulation_p50_ms']:.0f}; {s['learned_frames']}) | "
            f"{s['render']['p50_ms']:.2f} | {s['frame']['p50_ms']:.2f} / {s['frame']['p99_ms']:.2f} | "
            f"{b['fps_at_p50']:.1f} | {s['guard_trips']} | {verdict(s)} | {public_cell(s)} |")
    rows = {n: s for n, s in result["scenes"].items() if STEPPER in s["step_programs"][s["judged_round"]]}
    if rows:
        lines += ["", "The step alone, after the judged round, in the same process: the variants interleaved call "
                  "by call, the same input every call (the initial states under the pressing fingertip's forces), "
                  "p50 / p99 ms (p99/p50). `tignn_jax.step` and `tignn_jax.stepper` step all the scene's bodies "
                  "as one graph (`rest_graph(params, bodies)`, `stepper(params, bodies)`); the loop's program (the "
                  "demo's step functions jitted again by `tignn_jax.mr.build`) steps each body in its own branch. "
                  "Both hold the model's arrays as constants of the program. A scene of bodies in contact steps "
                  "them with its public step `tignn_jax.contact_stepper` in both the stepper's and the step's "
                  "columns (the latter with device and host forces).", "",
                  f"| scene | budget | {LOOP_STEP} | {STEPPER} | {STEP_DEVICE} | {STEP_HOST} | "
                  "stepper ÷ loop's program (p50) | step − stepper (p50): the checks | largest state difference, "
                  "step vs stepper |", "|---|---|---|---|---|---|---|---|---|"]
        for name, s in rows.items():
            p = s["step_programs"][s["judged_round"]]
            cell = lambda k: f"{p[k]['p50_ms']:.2f} / {p[k]['p99_ms']:.2f} ({p[k]['p99_over_p50']:.2f}×)"  # noqa
            label = f"{name} (`{p['public_api']}` in both columns)" if "public_api" in p else name
            lines.append(f"| {label} | {BUDGET_MS[name]:.0f} ms | {cell(LOOP_STEP)} | {cell(STEPPER)} | "
                         f"{cell(STEP_DEVICE)} | {cell(STEP_HOST)} | "
                         f"{s['public_step']['stepper_over_loop_step_p50']:.2f}× | "
                         f"{s['public_step']['check_overhead_p50_ms']:+.2f} ms | "
                         f"{p['max_abs_difference_step_vs_stepper']:.1e} |")
    if result["rounds"] > 1:
        lines += ["", "Every round, simulation p50 / p99 ms (p99/p50), learned-step frames; the judged round in "
                  "bold; in brackets the public step's p50 (device forces) after that round:", ""]
        for name, s in result["scenes"].items():
            cells = []
            for i, (r, p) in enumerate(zip(s["rounds"], s["step_programs"])):
                text = f"{r['p50_ms']:.2f} / {r['p99_ms']:.2f} ({r['p99_ms'] / r['p50_ms']:.2f}×)"
                text = f"**{text}**" if i == s["judged_round"] else text
                cells.append(text + (f" [{p[STEP_DEVICE]['p50_ms']:.2f}]" if STEP_DEVICE in p else ""))
            lines.append(f"- {name}: " + "; ".join(cells))
    split = {n: s["simulation_by_class"] for n, s in result["scenes"].items() if len(s["simulation_by_class"]) > 1}
    if split:
        lines += ["", "Learned-step frames by what the bodies did (simulation p50 / p99 ms, frames):", ""] + [
            f"- {n}: " + "; ".join(f"{k} {v['p50_ms']:.2f} / {v['p99_ms']:.2f} ({v['frames']})" for k, v in c.items())
            for n, c in split.items()]
    if result.get("loop_fusion"):
        lines += ["", "The loop fused (`Scene.fuse`: forces, step and guard dispatched together, awaited once per "
                  "frame) against its stages dispatched and awaited one by one, alternating runs in the same "
                  "process (simulation p50 / p99 over the learned-step frames, median over the rounds):", "",
                  "| scene | frames × rounds | staged p50 / p99 | fused p50 / p99 | speed-up (p50) |",
                  "|---|---|---|---|---|"]
        for name, f in result["loop_fusion"].items():
            lines.append(f"| {name} | {f['frames']} × {f['rounds']} | {f['p50_ms']['staged']:.2f} / "
                         f"{f['p99_ms']['staged']:.2f} | {f['p50_ms']['fused']:.2f} / {f['p99_ms']['fused']:.2f} | "
                         f"{f['speedup_fused_vs_staged']:.2f}× |")
    lines += ["", "The machine's own tail, same run: fixed programs doing the same work every call, timed "
              f"{result['frames']} times like the loop's stages (`platform_jitter`): " + "; ".join(
                  f"{k} p50 {v['p50_ms']:.2f} ms, p99 {v['p99_ms']:.2f} ms ({v['p99_over_p50']:.2f}×)"
                  for k, v in result["platform_jitter"].items()) +
              f". The {P99_RATIO} × p50 rule cannot be judged finer than that."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
