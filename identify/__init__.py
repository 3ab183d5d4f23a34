"""Identification of pcrjax models from recorded motion: damping, rod lengths and the nuisance
parameters of the experiment (camera frame, clock offset, initial push). See `identify.fit`."""

from .recording import Recording, RecordingError, load_recording

__all__ = ["Recording", "RecordingError", "load_recording"]
