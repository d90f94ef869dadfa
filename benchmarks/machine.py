"""What the benchmarks record about the machine they ran on."""

import platform


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo (Linux), else `platform.processor()`."""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def machine(**extra) -> dict:
    """The CPU, its cores, Python's and JAX's versions (JAX: the one imported), and `extra` (e.g. devices)."""
    import os
    import sys

    jax = sys.modules.get("jax")
    info = {"cpu": cpu_name(), "cores": os.cpu_count(), "python": platform.python_version()}
    if jax is not None:
        info["jax"] = jax.__version__
    return {**info, **extra}
