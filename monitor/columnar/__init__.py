"""Columnar replay of a recorded bus: a log read and diagnosed a chunk at a time.

    from monitor.columnar import replay_file
    result = replay_file("capture.log", db, cfg, sink)   # -> ReplayResult

`replay_file(path, db, cfg=None, sink=None, *, chunk_frames=262144) -> ReplayResult` is
the per-file engine: `db` the rig's decoder (`monitor.rig.build_decoder`), `cfg` the
`MonitorConfig`, `sink` any `monitor.sinks.Sink` (a `FanOut` too; not closed here).
`ReplayResult` holds the frames read, the final counters, every transition, the nodes'
final state, and whether the columnar path ran (`columnar`, else `fallback` says why).
A file that cannot be read raises `LogReadError` (a `MonitorError`, one line).

Per chunk (`reader.read_chunks`: every format of `monitor.bus.logfile.LOG_FORMATS`, each by
its module, laid out as python-can's ``can/io``: candump .log, .asc and .blf by compiled
scanners that hand what they do not take to python-can's readers, .mf4 as asammdf's columns,
.trc by python-can; under NUMBA_DISABLE_JIT all but candump by python-can):

1. `decode.RouteTable` routes every frame by (ID, extended) with the per-frame codec's own
   routes (`monitor.bus.route.Route`), checks them in the codec's order
   (`monitor.bus.codec.CHECK_ORDER`): frame format, length, E2E profile 2 (`e2e`:
   CRC-8/AUTOSAR by a table generated from and checked against crccheck/cantools),
   reserved bits and limits, and decodes the signals
   from cantools' signal definitions (`signals`), whole columns at once;
2. alive counters per stream (repeated, lost) vectorised;
3. per node, held inputs and truth vectorised, the admission rules (`kernels.admit`), the
   estimator stepped over all the node's samples in one compiled loop
   (`FuzzyUKF.step_many`: the same kernel as `FuzzyUKF.step`), then
   classification, model-mismatch detection, silence ticks and due diagnoses in one
   compiled loop (`kernels.classify`);
4. samples and inputs go to the sinks as columns (`sinks.SinkRouter`; `RerunSink` takes
   them with `on_sample_columns` and sends them with ``rr.send_columns``), transitions, due
   diagnoses and bus events in their order.

The same transitions, due diagnoses, bus events, samples and counters as
``feed_log(MonitorPipeline(db, cfg, sink), read_log(path))`` (tests/columnar/test_columnar.py). What
differs: samples and inputs reach a sink node by node per chunk (each node's in order),
before that chunk's events; the counters reach the sink once per chunk (at its last frame's
time) rather than about once a second of bus time. SecOC needs per-frame freshness state:
with a key the file goes through the per-frame path (one log line says so).

The engine (`replay.ColumnarEngine`) runs on a `MonitorPipeline`'s state -- its nodes,
counters, alive-counter tracker, drives, warnings and sink -- so chunks and single frames
can be mixed on one pipeline: the live daemon hands a socket's backlog to it in one call
and a few frames to the per-frame engine (`live.BacklogFeed`).
"""

from monitor.columnar.decode import NotColumnar
from monitor.columnar.reader import FrameChunk, LogReadError, read_chunks
from monitor.columnar.replay import (
    ReplayResult,
    columnar_obstacle,
    replay_chunks,
    replay_file,
)
from monitor.pipeline.events import SampleColumns

__all__ = ["FrameChunk", "LogReadError", "NotColumnar", "ReplayResult", "SampleColumns",
           "columnar_obstacle", "read_chunks", "replay_chunks", "replay_file"]
