"""A tiny rerun recording for the tests of the viewer."""

from __future__ import annotations

from pathlib import Path


def write_tiny_recording(path: Path) -> Path:
    """One text line at decision 1, saved to ``path`` (an .rrd the viewer can open)."""
    import rerun as rr

    rec = rr.RecordingStream("agos", recording_id="ep")
    rec.save(str(path))
    rec.set_time("decision", sequence=1)
    rec.log("log/steps", rr.TextLog("step 1"))
    rec.flush()
    rec.disconnect()
    return path
