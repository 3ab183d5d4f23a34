"""Traced programs kept on disk, so that a later process skips the trace.

JAX's persistent compilation cache saves the compile, not the trace that comes before it, and
tracing is Python holding the interpreter lock: a Triskele fit's Jacobian program (the `jvp` of
a scan of Newton solves, `vmap`ped over the unknowns) takes some 9 s to trace and 1 s to
compile from a warm cache. `jit` exports the traced and lowered program (`jax.export`) to a file
named by a fingerprint of everything its trace depends on: the source of the packages it runs,
the versions of JAX and its companions, the JAX settings that change a trace, the function's
name, what it closes over, and the structure, shapes and dtypes of its arguments. A later
process loads that file and only compiles (from the compilation cache when that is warm).

A program is kept only where every part of the fingerprint is plain data (arrays, numbers,
strings, dataclasses and containers of them); anything else (a function, an object whose text
names its address) leaves the program traced as usual. A file that cannot be read is traced
again and replaced.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.metadata
import os
import pickle
import sys
import threading
from pathlib import Path
from types import ModuleType

import jax
import numpy as np
from jax import export

import pcrjax

from . import config

_VERSIONED = ("jax", "jaxlib", "equinox", "lineax", "optimistix", "numpy")
_SETTINGS = ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_rank_promotion", "jax_numpy_dtype_promotion")
_sources: dict[str, bytes] = {}


class _NotPlain(Exception):
    """Part of a fingerprint that is not plain data."""


def _feed(h, obj):
    """Hash ``obj``'s content into ``h``; raise `_NotPlain` for what has no stable content."""
    if isinstance(obj, (np.ndarray, np.generic, jax.Array)):
        a = np.asarray(obj)
        h.update(f"array{a.dtype.str}{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    elif obj is None or isinstance(obj, (bool, int, float, complex, str, bytes)):
        h.update(repr((type(obj).__name__, obj)).encode())
    elif isinstance(obj, os.PathLike):
        h.update(repr(("path", os.fspath(obj))).encode())
    elif isinstance(obj, (tuple, list)):
        h.update(f"{type(obj).__name__}{len(obj)}(".encode())
        for o in obj:
            _feed(h, o)
        h.update(b")")
    elif isinstance(obj, dict):
        h.update(f"dict{len(obj)}(".encode())
        for k in sorted(obj, key=repr):
            _feed(h, k)
            _feed(h, obj[k])
        h.update(b")")
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):  # equinox modules included
        h.update(f"{type(obj).__module__}.{type(obj).__qualname__}(".encode())
        for f in dataclasses.fields(obj):
            h.update(f.name.encode())
            _feed(h, getattr(obj, f.name))
        h.update(b")")
    else:
        raise _NotPlain(type(obj).__qualname__)


def _source(package: ModuleType) -> bytes:
    """Digest of every Python file of ``package`` (read once a process)."""
    name = package.__name__
    if name not in _sources:
        h = hashlib.sha256()
        root = Path(package.__file__).parent
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
        _sources[name] = h.digest()
    return _sources[name]


def _environment() -> list:
    versions = []
    for d in _VERSIONED:
        try:
            versions.append(importlib.metadata.version(d))
        except importlib.metadata.PackageNotFoundError:
            versions.append(None)
    device = jax.devices()[0]
    return [sys.version, versions, [str(getattr(jax.config, s)) for s in _SETTINGS], device.platform, device.device_kind]


def fingerprint(name: str, closure, packages: tuple[ModuleType, ...]) -> str | None:
    """Hex digest naming the program ``name`` that closes over ``closure`` and runs the code of
    ``packages``; None where ``closure`` is not plain data."""
    h = hashlib.sha256()
    try:
        _feed(h, [name, _environment(), closure])
    except _NotPlain:
        return None
    for p in packages:
        h.update(_source(p))
    return h.hexdigest()


def _signature(args) -> str:
    leaves, tree = jax.tree.flatten(args)
    return str(tree) + "".join(str(jax.typeof(a)) for a in leaves)


def _load(path: Path):
    try:
        return pickle.loads(path.read_bytes())
    except Exception:  # absent, cut short by a crash, or written by another version: trace again
        return None


def _store(path: Path, exported):
    """Write atomically (a rename), so a process that reads never sees half a file."""
    data = pickle.dumps(dataclasses.replace(exported, _get_vjp=None))  # a closure: not kept
    tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError:  # a full or read-only disk loses the saving, not the result
        tmp.unlink(missing_ok=True)


def jit(fn, name: str, closure, packages: tuple[ModuleType, ...] = (), fixed: tuple = ()):
    """``jax.jit(fn)``, with its traced programs kept on disk where `config.trace_cache_dir` is set.

    ``closure``: everything ``fn``'s trace depends on besides the code of ``packages`` (pcrjax's
    own is always included) and the arguments' structure, shapes and dtypes: the arrays and
    settings ``fn`` closes over. Naming too little makes a stale program load, so name the
    objects ``fn`` reads whole. ``fixed``: leading arguments of every call (the result's
    ``call(*args)`` runs ``fn(*fixed, *args)``), whose structure, shapes and dtypes are read
    once rather than at each call. The result is for calling, not for transforming (`vmap`, `grad`).
    Its ``trace(*args)`` traces the program for such arguments without compiling it (tracing
    holds Python's lock, compiling does not: a caller traces first what another thread is to
    compile or run meanwhile).
    """
    jitted = jax.jit(fn)
    folder, key = _folder_and_key(name, closure, packages)
    programs, lock = {}, threading.Lock()

    def program(args):
        sig = _signature(args)
        with lock:
            if sig not in programs:
                programs[sig] = jitted if key is None else _kept(jitted, folder, name, key, (*fixed, *args))
        return programs[sig]

    def call(*args):
        return program(args)(*fixed, *args)

    def trace(*args):
        if program(args) is jitted:
            jitted.trace(*fixed, *args)

    call.trace = trace
    return call


def compiled(fn, name: str, closure, args, packages: tuple[ModuleType, ...] = ()):
    """``jax.jit(fn).lower(*args).compile()`` (compiled before it is called, e.g. to time a run
    apart from its compile), its traced program kept on disk as `jit` keeps it."""
    jitted = jax.jit(fn)
    folder, key = _folder_and_key(name, closure, packages)
    program = jitted if key is None else _kept(jitted, folder, name, key, args)
    return program.lower(*args).compile()


def _folder_and_key(name: str, closure, packages: tuple[ModuleType, ...]):
    """(`config.trace_cache_dir`, the `fingerprint` of ``name`` with pcrjax's code and
    ``packages``'): key None where nothing is kept (no folder, or a closure not plain data)."""
    folder = config.trace_cache_dir()
    return folder, None if folder is None else fingerprint(name, closure, (pcrjax, *packages))


def _kept(jitted, folder: Path, name: str, key: str, args):
    """``jitted``'s program for ``args``' structure, shapes and dtypes as a jitted call of its
    export, loaded from ``folder`` or traced and stored there; ``jitted`` itself where export
    cannot hold it (a host callback), or where tracing fails (the plain call then reports why)."""
    path = folder / f"{name}-{hashlib.sha256((key + _signature(args)).encode()).hexdigest()[:32]}.pkl"
    exported = _load(path)
    if exported is None:
        try:
            exported = export.export(jitted)(*args)
        except Exception:
            return jitted
        _store(path, exported)
    return jax.jit(exported.call)


def jit_over(fn, name: str, tree, closure, packages: tuple[ModuleType, ...] = (), fixed: tuple = ()):
    """``fn(tree, *fixed, *args)`` as a program of ``*args`` (`jit`) in which ``tree`` (a pytree,
    e.g. a scene) is an argument too, passed as its leaves: a program kept on disk cannot rebuild
    equinox modules from its own record of the arguments' structure, so ``tree``'s structure
    names the program instead (beside ``closure``), and trees of that structure share it.
    ``fixed``: further leading arguments of every call, as `jit`'s."""
    leaves, structure = jax.tree.flatten(tree)
    return jit(
        lambda leaves, *args: fn(jax.tree.unflatten(structure, leaves), *args),
        name,
        (str(structure), closure),
        packages,
        (leaves, *fixed),
    )
