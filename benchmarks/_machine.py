"""Describe the machine a benchmark ran on (written next to every result)."""
from __future__ import annotations

import os
import platform


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
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "jax": jax.__version__,
            "backend": jax.default_backend(), "load_average_1m": round(load[0], 2),
            "note": "load_average_1m > cores means other processes shared the CPU during the run"}
