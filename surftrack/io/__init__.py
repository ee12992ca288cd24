"""Output formats: MCAP tracking logs for Foxglove."""

from surftrack.io.mcap_writer import SCHEMAS, TrackWriter, time_to_ns

__all__ = ["SCHEMAS", "TrackWriter", "time_to_ns"]
