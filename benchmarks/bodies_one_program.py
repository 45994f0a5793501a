"""Several bodies stepped in one program on a CPU: the layouts the loop and `api.stepper` choose between.

Two beams (`beam-abaqus`, a moving state, small forces), five ways, interleaved in the same process: one body
alone; both as two plain steps in one program; the same with each step inside its own ``lax.cond`` (what the
scene loop runs without devices, `scene._fused_frames`); both as one graph (``stepper(params, 2,
one_graph=True)``); both one after another inside the program (``stepper(params, 2)``'s CPU default,
``lax.map``); and 4 and 8 copies, one graph against one after another. Each configuration runs in a child process of its own, because how XLA:CPU runs a program
depends on how many CPU devices the process made (``tignn demo --cores N`` makes N, see
`scene.cpu_devices`) and on the cores the process may use:

* one CPU device, both cores (a user's process that did not pin itself);
* one CPU device, pinned to one core (``tignn demo`` and ``benchmarks/realtime.py`` since session 48, whose
  default ``--cores 1`` pins the process before JAX starts, ``scene.pin_cores``; or a one-core machine);
* two CPU devices, both cores (``tignn demo --cores 2`` on this machine).

    python benchmarks/bodies_one_program.py [--repeats 40]

Writes benchmarks/results/bodies_one_program.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, interleaved_ms, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
CONFIGS = {"one device, two cores": (1, None), "one device, one core": (1, 0), "two devices, two cores": (2, None)}
COPIES = (4, 8)
LAYOUTS = ("one body", "two plain steps in one program", "two steps, each in a lax.cond",
           "one graph of both", "one after another (lax.map)")


def two_bodies(params):
    """(z, f, {layout: zero-argument function}) for two bodies of ``params``'s mesh in a moving state under small
    forces, the ``LAYOUTS`` in order; raises RuntimeError if a layout does not step both bodies to the states of
    one body's step."""
    import jax
    import jax.numpy as jnp

    from tignn_jax import api

    rng = np.random.default_rng(0)
    n = len(params["mesh"]["node_type"])
    z = jnp.asarray(np.concatenate([np.asarray(params["mesh"]["q0"]), 0.01 * rng.normal(size=(n, 9))], 1),
                    jnp.float32)
    f = jnp.asarray(0.01 * rng.normal(size=(n, 3)), jnp.float32)
    one = api.stepper(params)
    keep = lambda z_, f_: z_   # noqa: E731 (the branch not taken)
    plain = jax.jit(lambda za, zb, fa, fb: (one(za, fa), one(zb, fb)))
    in_cond = jax.jit(lambda za, zb, fa, fb, on: (jax.lax.cond(on, keep, one, za, fa),
                                                  jax.lax.cond(on, keep, one, zb, fb)))
    graph2, mapped = api.stepper(params, 2, one_graph=True), api.stepper(params, 2, one_graph=False)
    z2, f2 = jnp.concatenate([z, z]), jnp.concatenate([f, f])
    fns = dict(zip(LAYOUTS, (lambda: one(z, f), lambda: plain(z, z, f, f), lambda: in_cond(z, z, f, f, False),
                             lambda: graph2(z2, f2), lambda: mapped(z2, f2))))
    ref = np.asarray(one(z, f))
    for name, fn in list(fns.items())[1:]:   # every layout steps both bodies to the same states
        out = fn()
        both = np.concatenate([np.asarray(x) for x in out]) if isinstance(out, tuple) else np.asarray(out)
        if not np.allclose(both, np.concatenate([ref, ref]), rtol=1e-5, atol=1e-5):
            raise RuntimeError(f"{name}: the states differ from one body's step")
    return z, f, fns


def child(devices: int, repeats: int) -> dict:
    """The five layouts' step times in this process ({layout: p50 ms}); JAX must not have started yet."""
    from tignn_jax import scene as sc

    sc.real_time_xla_flags()
    sc.cpu_devices(devices)
    import jax
    import jax.numpy as jnp

    from tignn_jax import api

    params, _ = api.load_pretrained("beam-abaqus")
    z, f, fns = two_bodies(params)
    times = interleaved_ms(fns, repeats)
    copies = {}
    for k in COPIES:   # more bodies: one graph against one after another
        zk, fk = jnp.concatenate([z] * k), jnp.concatenate([f] * k)
        fk_fns = {og: (lambda st=api.stepper(params, k, one_graph=og), zk=zk, fk=fk: st(zk, fk)) for og in (True, False)}
        t = interleaved_ms(fk_fns, max(repeats // 4, 1))
        copies[k] = {"one graph": float(np.median(t[True])), "one after another": float(np.median(t[False]))}
    return {"devices": len(jax.local_devices()), "p50_ms": {k: float(np.median(v)) for k, v in times.items()},
            "p99_ms": {k: float(np.percentile(v, 99)) for k, v in times.items()}, "copies": copies}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=40, help="interleaved calls per layout")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.repeats < 1:
        raise SystemExit(f"--repeats must be at least 1, got {args.repeats}")
    if args.child is not None:
        print(json.dumps(child(int(args.child), args.repeats)))
        return 0
    machine = describe()
    rows = {}
    for name, (devices, core) in CONFIGS.items():
        cmd = [sys.executable, __file__, "--child", str(devices), "--repeats", str(args.repeats)]
        if core is not None:
            if not hasattr(os, "sched_setaffinity"):
                continue
            cmd = ["taskset", "-c", str(core)] + cmd
        print(f"{name} ...", flush=True)
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        rows[name] = json.loads(out.strip().splitlines()[-1])
    result = {"machine": machine, "repeats": args.repeats, "rows": rows}
    write_results("bodies_one_program", result, format_md(result), RESULTS)
    return 0


def format_md(r: dict) -> str:
    m = r["machine"]
    lines = ["# Two bodies in one program on a CPU", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']}; load average {m['load_average_1m']} at "
             f"start. `beam-abaqus`, p50 of {r['repeats']} interleaved calls per layout, each configuration in "
             "its own process (see the script's docstring). In brackets: the ratio to the plain program.", "",
             "| process | " + " | ".join(LAYOUTS) + " |", "|---|" + "---|" * len(LAYOUTS)]
    for name, row in r["rows"].items():
        base = row["p50_ms"]["two plain steps in one program"]
        cells = [f"{row['p50_ms'][k]:.2f} ms" + ("" if k == "one body" else f" ({base / row['p50_ms'][k]:.2f}×)")
                 for k in LAYOUTS]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "More copies of the beam, `stepper(params, k)` as one graph against one after another (its CPU "
              "default; p50 of a quarter as many calls):", "", "| process | " + " | ".join(
                  f"{k} copies: one graph / one after another" for k in COPIES) + " |", "|---|" + "---|" * len(COPIES)]
    for name, row in r["rows"].items():
        c = {int(k): v for k, v in row.get("copies", {}).items()}
        lines.append(f"| {name} | " + " | ".join(
            f"{c[k]['one graph']:.1f} / {c[k]['one after another']:.1f} ms "
            f"({c[k]['one graph'] / c[k]['one after another']:.2f}×)" if k in c else "" for k in COPIES) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
