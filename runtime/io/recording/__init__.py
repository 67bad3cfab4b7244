"""MCAP recordings of a run (recorder.py: written from a thread outside the tick; reader.py:
read back, also when cut off). Channel schemas: schemas.py; the messages on them: messages.py."""
from runtime.io.recording.reader import Recording, RecordingReadError, read_recording
from runtime.io.recording.recorder import RecordingError, RunRecorder

__all__ = ["Recording", "RecordingError", "RecordingReadError", "RunRecorder", "read_recording"]
