"""Frames in, typed events out: decoding, E2E supervision, alignment, estimation and
diagnosis of every node (`core`), the events handed to the sinks (`events`) and the counter
names (`counters`)."""

from monitor.pipeline.core import MonitorConfig, MonitorPipeline, NodeMonitor
from monitor.pipeline.counters import Counters
from monitor.pipeline.events import (
    BusEvent,
    Diagnosis,
    DiagnosisEvent,
    InputSample,
    PlantSignals,
    Sample,
)

__all__ = ["BusEvent", "Counters", "Diagnosis", "DiagnosisEvent", "InputSample", "MonitorConfig",
           "MonitorPipeline", "NodeMonitor", "PlantSignals", "Sample"]
