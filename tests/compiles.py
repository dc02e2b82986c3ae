"""Counting XLA's backend compilations, for tests that guard against programs compiled again."""

from __future__ import annotations

import contextlib

import jax

_EVENT = "/jax/core/compile/backend_compile_duration"


@contextlib.contextmanager
def counting_compilations():
    """``with counting_compilations() as compiles:`` — ``compiles`` is a list that gets one entry
    per program XLA compiles inside the block (``len(compiles)`` is the count so far)."""
    compiles: list[str] = []

    def listen(event, secs, **kw):
        if event == _EVENT:
            compiles.append(kw.get("fun_name", ""))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield compiles
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
