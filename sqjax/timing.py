"""Wall and compile seconds of a call, as `Segmentation.timings` reports them.

JAX reports each compilation (tracing, lowering, XLA, or a read of the persistent cache) through
`jax.monitoring`; the listener is registered on the first `Clock`, not at import.
"""

from __future__ import annotations

import time

_compile_seconds = 0.0
_listening = False


def _on_event(event: str, duration_secs: float, **_) -> None:
    global _compile_seconds
    if event.startswith("/jax/core/compile/"):
        _compile_seconds += duration_secs


def compile_seconds() -> float:
    """Seconds JAX has spent compiling in this process since the first `Clock` (0 before)."""
    return _compile_seconds


class Clock:
    """Started at construction; `timings()` -> {"total", "compile", "run"} seconds since then."""

    def __init__(self):
        global _listening
        if not _listening:
            import jax

            jax.monitoring.register_event_duration_secs_listener(_on_event)
            _listening = True
        self._t0, self._c0 = time.perf_counter(), _compile_seconds

    def timings(self) -> dict:
        total = time.perf_counter() - self._t0
        compile_s = _compile_seconds - self._c0
        return {"total": total, "compile": compile_s, "run": total - compile_s}
