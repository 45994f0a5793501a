"""Describe the machine a benchmark ran on (written next to every result), time variants alike, and write a
result's .json and .md."""
from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

RESULTS_DIR = Path(__file__).resolve().parent / "results"


def describe() -> dict:
    import jax

    cpu = "unknown"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "jax": jax.__version__,
            "backend": jax.default_backend(), "load_average_1m": round(load[0], 2), "cpus_allowed": allowed,
            "note": "load_average_1m > cores means other processes shared the CPU during the run"}


def machine_line(m: dict) -> str:
    """The report line's start that names the machine of ``describe()``: "Machine: CPU, N cores, jax V (backend)";
    each report adds its own details (load average, flags). A process held to fewer CPUs than the machine has
    (``taskset``, `tignn_jax.mr.pin_cores`) says so: "…, pinned to CPU 1"."""
    line = f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']} ({m['backend']})"
    allowed = m.get("cpus_allowed")
    if allowed and m.get("cores") and len(allowed) < m["cores"]:
        line += f", pinned to CPU{'s' if len(allowed) > 1 else ''} {', '.join(map(str, allowed))}"
    return line


def interleaved_ms(fns: dict, repeats: int, seed: int = 0) -> dict:
    """Milliseconds per call of each zero-argument function, ``repeats`` samples each ({name: [ms]}): each is
    called once first (to compile), then the functions are called in turn, so a change of the machine's load
    hits all variants alike. Each round calls them in a new random order (seeded): a call runs slower after one
    that swept the caches (a long rollout, a large mesh), and a fixed or merely rotated order would make the same
    variant follow that one round after round. A function's result is awaited with ``jax.block_until_ready``."""
    import jax

    for fn in fns.values():
        jax.block_until_ready(fn())
    times = {k: [] for k in fns}
    names = list(fns)
    rng = np.random.default_rng(seed)
    for _ in range(repeats):
        for i in rng.permutation(len(names)):
            fn = fns[names[i]]
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            times[names[i]].append(1e3 * (time.perf_counter() - t0))
    return times


def write_results(stem: str, result: dict, md: str, folder: Path = RESULTS_DIR, indent: int = 1,
                  echo: bool = True) -> None:
    """Write ``result`` to ``folder/stem.json`` (``json.dumps`` with ``indent``) and ``md`` to ``folder/stem.md``,
    creating ``folder`` if need be, and print ``md`` unless ``echo`` is False (for a script that prints its own
    summary, or nothing)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{stem}.json").write_text(json.dumps(result, indent=indent))
    (folder / f"{stem}.md").write_text(md)
    if echo:
        print(md)
