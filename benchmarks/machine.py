"""Which machine a benchmark ran on: CPU model, cores, kernel, Python and the load, for its output and JSON.

Figures differ between CPUs of the same kind of machine (an AMD EPYC VM and an Intel Xeon one gave the live
service's latency 2-3 times apart), so every benchmark says which CPU and kernel gave its figures.
"""

from __future__ import annotations

import os
import platform
import subprocess


def cpu_model() -> str:
    """``lscpu``'s "Model name", else /proc/cpuinfo's "model name", else what platform knows."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10,
                             env=dict(os.environ, LC_ALL="C")).stdout
        for line in out.splitlines():
            if line.startswith("Model name:"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.SubprocessError):
        pass
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """CPU model, cores (and how many this process may use), kernel, Python and the load average now."""
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {"cpu_model": cpu_model(), "cpus": os.cpu_count(), "cpus_usable": usable,
            "kernel": f"{platform.system()} {platform.release()}", "python": platform.python_version(),
            "load_avg": list(os.getloadavg())}


def machine_line(info: dict | None = None) -> str:
    """One line for a benchmark's output: ``AMD EPYC, 2 cores, Linux 6.18.44, Python 3.11.7, load 0.4``."""
    m = info or machine_info()
    return (f"{m['cpu_model']}, {m['cpus']} cores, {m['kernel']}, Python {m['python']}, "
            f"load average {m['load_avg'][0]:.1f}")
