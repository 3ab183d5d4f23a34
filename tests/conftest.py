import collections
import json
import os
import sys

# The suite compiles far more than it runs: XLA:CPU's legacy emitters build its programs faster than
# the newer fusion emitters, and run them a little slower (figures in BENCHMARKS.md). XLA reads the
# flag when jaxlib is first imported, so it is set before any import of jax; subprocesses (command
# lines, notebook kernels) inherit it.
os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), "--xla_cpu_use_fusion_emitters=false"]).strip()

sys.path.insert(0, os.path.dirname(__file__))

import jax  # noqa: E402
import jax.monitoring  # noqa: E402
import pytest  # noqa: E402

import pcrjax  # noqa: E402
from pcrjax import executables  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "allow")
pcrjax.enable_compilation_cache()

# What this process asked of XLA, from JAX's own monitoring events: functions traced, programs
# built (the backend-compile event, which a persistent-cache hit also sends) and of those the ones
# loaded from the persistent compilation cache; the rest XLA compiled.
_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "traced",
    "/jax/core/compile/backend_compile_duration": "built",
    "/jax/compilation_cache/cache_hits": "loaded from cache",
}
_counts: collections.Counter = collections.Counter()


def _count(event, *args, **kwargs):
    name = _EVENTS.get(event)
    if name:
        _counts[name] += 1


jax.monitoring.register_event_listener(_count)
jax.monitoring.register_event_duration_secs_listener(_count)


@pytest.fixture(autouse=True)
def _headroom_for_executables():
    """A worker runs many tests in one process: release compiled code before it nears the kernel's
    cap on memory mappings (see `pcrjax.executables`), which would crash the worker."""
    yield
    executables.make_room(0.4, warn=False)


def pytest_sessionfinish(session):
    if hasattr(session.config, "workeroutput"):  # a pytest-xdist worker: hand the counts to the controller
        session.config.workeroutput["jax_programs"] = json.dumps(_counts)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    _counts.update(json.loads(getattr(node, "workeroutput", {}).get("jax_programs", "{}")))


def pytest_terminal_summary(terminalreporter):
    if hasattr(terminalreporter.config, "workerinput"):
        return
    c = _counts
    terminalreporter.write_line(
        f"JAX in the test processes: {c['built'] - c['loaded from cache']} programs compiled, {c['loaded from cache']} loaded "
        f"from the persistent cache, {c['traced']} traces (notebook kernels and subprocesses not counted)"
    )
