"""The two errors a user of pcrjax meets: a scene it cannot use, and a solve that failed."""

from __future__ import annotations


class SceneError(ValueError):
    """A scene file or value that pcrjax cannot use; the message names the cause."""


class ConvergenceError(RuntimeError):
    """A solve that failed: ``time`` (s), ``residual`` (scaled) and ``reason`` (why) say where and
    why; ``partial`` (if set) holds the steps completed before it."""

    def __init__(self, message, time=None, residual=None, reason=None):
        super().__init__(message)
        self.time = time
        self.residual = residual
        self.reason = reason
        self.partial = None
