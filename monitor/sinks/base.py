"""The interface of every outlet of the pipeline, `Sink`, and `FanOut` that joins several:
defined beside the events they receive (`monitor.pipeline.sink`), so that the pipeline
hands its events on without importing any outlet; here for the outlets to import."""

from monitor.pipeline.sink import FanOut, Sink

__all__ = ["FanOut", "Sink"]
