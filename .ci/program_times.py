"""pytest plugin for measuring the suite: per test, its wall time, the programs XLA built (name and
seconds, from `jax.monitoring`), persistent-cache hits and seconds spent tracing and lowering;
one JSON line per test in ``$COUNT_DIR/tests-PID.jsonl`` (default ``out/test_programs``).

    PYTHONPATH=.ci COUNT_DIR=out/test_programs .venv/bin/python -m pytest -q -p program_times

jax is imported at session start, after `tests/conftest.py` has set XLA_FLAGS."""

import json
import os
import time

import pytest

_now = {"programs": [], "trace_s": 0.0, "lower_s": 0.0, "cache_hits": 0}


def _duration(event, seconds, **kwargs):
    if event.endswith("backend_compile_duration"):
        _now["programs"].append((kwargs.get("fun_name", "?"), round(seconds, 3)))
    elif event.endswith("jaxpr_trace_duration"):
        _now["trace_s"] += seconds
    elif event.endswith("jaxpr_to_mlir_module_duration"):
        _now["lower_s"] += seconds


def _event(event, **kwargs):
    if event.endswith("cache_hits"):
        _now["cache_hits"] += 1


def pytest_sessionstart(session):
    import jax.monitoring

    jax.monitoring.register_event_duration_secs_listener(_duration)
    jax.monitoring.register_event_listener(_event)
    folder = os.environ.get("COUNT_DIR", "out/test_programs")
    os.makedirs(folder, exist_ok=True)
    session.config._program_times = open(os.path.join(folder, f"tests-{os.getpid()}.jsonl"), "a")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _now.update(programs=[], trace_s=0.0, lower_s=0.0, cache_hits=0)
    t0 = time.time()
    yield
    row = {"test": item.nodeid, "start": round(t0, 1), "wall_s": round(time.time() - t0, 2), **_now}
    row["trace_s"], row["lower_s"] = round(row["trace_s"], 2), round(row["lower_s"], 2)
    out = item.config._program_times
    out.write(json.dumps(row) + "\n")
    out.flush()
