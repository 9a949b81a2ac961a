"""What the benchmarks print about the machine they ran on (imported by the scripts beside it)."""

from __future__ import annotations

import os
import platform

from image2sphere.data.workers import available_cpus

__all__ = ["available_cpus", "cpu_model", "load_line"]


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux, else ``platform.processor()``)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def load_line(when: str, consequence: str = "timings may be slower and noisier") -> str:
    """The 1-minute load average, with a warning when other processes compete for the CPUs."""
    if not hasattr(os, "getloadavg"):
        return f"load average {when}: n/a"
    load = os.getloadavg()[0]
    line = f"load average {when}: {load:.2f} ({available_cpus()} CPUs available)"
    if load > 1.0:
        line += f" -- WARNING: other processes use the CPUs; {consequence}"
    return line
