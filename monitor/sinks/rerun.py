"""Live state of the monitor, streamed to a Rerun viewer and/or recorded to an ``.rrd`` file.

The daemon feeds up to ~10,000 samples/s in total. A row-wise ``rr.log`` costs ~0.1 ms, so
every high-rate series goes through column batches: `RerunSink.add_sample` only stores the
values in preallocated per-node numpy buffers (float64, ``batch_size`` long, reused for the
whole run) and a full buffer, `RerunSink.flush`, or `RerunSink.maybe_flush` once
``flush_interval_s`` has elapsed, sends it with one ``RecordingStream.send_columns`` per entity.
Rerun copies the data when it builds its Arrow arrays, so reusing the buffers is safe. Rare
data (events, counters) is sent straight away; an event first flushes its node's buffers so it
never comes before samples that precede it in time.

The entity layout, the series styles and the default blueprint are in
`monitor.sinks.blueprint`.

The thresholds go with every gamma batch, at its first and last time stamp, with step
interpolation, so each threshold line spans exactly the data and a `RerunSink.set_thresholds`
change shows up as a step where it took effect.

Piecewise-constant series (`RUNS`: the thresholds, the rule count, the health state, the
model-mismatch flag, a simulator's true gamma) are recorded as their runs
(`monitor.sinks.runs`: the rows that draw the line; `close` and `switch_file` send the one
held back). All of them but the thresholds are rows of a sample: 4 of the 11 a sample fills on
a one-output rig (each further output adds three: measured, estimated and its noise factor).
The estimator's noise factors (each output's and the process noise's), which move over
seconds, keep ten rows a second (`monitor.sinks.runs.bin_starts`). The other 5 (the output
measured and estimated, gamma^ and its standard deviation, NIS) keep every sample, and so do
the inputs (own rate, own buffer).

All data goes on one timeline, ``time``: a timestamp timeline of the bus time in float seconds
since the Unix epoch (CAN kernel time stamps), sent as ``rr.TimeColumn("time",
timestamp=...)``. Series names, colours and interpolation modes are logged once as static
``rr.SeriesLines``. A default blueprint (one tab per node, plus one for the counters) is sent
with the recording.

The sink is not thread-safe: call it from one thread (the daemon's main loop).

Durability. `RecordingStream.send_columns` bypasses the SDK's micro-batcher: the chunk goes
straight to the `FileSink`'s writer thread, which writes every message (16-byte header and
payload) with one unbuffered ``write(2)``, about a millisecond later. Data in the kernel's page
cache survives a SIGKILL of the process (not a power cut: nothing calls ``fsync``). So the only
delay is this sink's own buffering: `RerunSink.maybe_flush` sends everything once
``flush_interval_s`` (default `DEFAULT_FLUSH_INTERVAL_S` = 0.1 s) has passed, so a SIGKILL
loses at most ``flush_interval_s`` plus the period of the ``maybe_flush`` calls (0.05 s in the
daemon's loop) plus ~1 ms. The rare row-wise ``log`` calls (static series styles) do go through
the batcher: the next `RerunSink.flush` after one pushes it (``flush(timeout_sec=0)``: started,
not waited for; a flush with nothing batched leaves the SDK's threads asleep), and its tick is
set explicitly (`monitor.sinks.recording`), so ``RERUN_FLUSH_TICK_SECS`` in the environment
cannot hold them back longer. `RerunSink.close` writes the ``.rrd`` footer (SIGTERM/SIGINT in
the daemon), and ``rerun rrd verify`` passes. A killed process leaves a file without footer
and, if the kill hit a ``write``, with a torn last message: the SDK's streaming decoder reads
it as it is (``rerun rrd verify --check-footers false``, ``rerun rrd print``, the viewer);
``rerun rrd optimize FILE -o NEW`` writes a compacted copy with a footer;
`monitor.sinks.salvage.salvage_rrd` cuts the torn message off in place, for strict readers
(``rerun.chunk.RrdReader`` refuses the whole file otherwise).

Size. Every flush sends one chunk per entity, and a chunk costs ~1 kB besides its rows (its
Arrow schema and metadata, LZ4-compressed like the rest of the message, and ~33 bytes of footer
manifest); a row of a scalar costs 36 bytes before compression (16-byte row id, 8-byte time,
8-byte float64 value, 4-byte list offset), ~16-24 after. One 100 Hz node (``python -m
tests.bench.recording_size``, bytes per hour, against 38 MB for the candump ``.log`` of its
frames and 12 MB for the ``.blf``): flushed every 0.1 s, 347 MB (framing, ~74 chunks/s); every
2 s, which is sound when another record bounds what a kill may lose (``run --raw-dir``), 88 MB;
compacted by ``rerun rrd optimize`` (`monitor.sinks.compact`: one chunk per entity and ~2 MiB),
45 MB, the rows themselves (gamma^'s standard deviation, a full-rate series like gamma^, is
8-9 MB of it; the noise factors about 2 MB): `RotatingRerunSink` compacts every file it
closes.

Week-long runs: `monitor.sinks.rotation.RotatingRerunSink` writes a directory of ``.rrd``
files; when the current one exceeds a size or an age it is finished (footer) and recording
goes on into a new one, with the same `RecordingStream` and a new `FileSink`; the oldest
files beyond a count or a total size are deleted. The footer's chunk manifest, which the
SDK keeps in memory while a file is open, is freed at each rotation: memory and disk stay
bounded however long the daemon runs.

The modules: `outlet` (the pipeline's events onto the column API), `batch` (the column
buffers), `runs` (the run thinning), `recording` (`RecordingSink`, one file and/or a live
viewer), `rotation` (`RerunSink`: its file in parts; `RotatingRerunSink`); this module names
them for their users.
"""

from __future__ import annotations

from monitor.sinks.outlet import (
    DEFAULT_FLUSH_INTERVAL_S,
    REPLAY_BATCH_SIZE,
    REPLAY_PART_BYTES,
    RecordingOutlet,
)
from monitor.sinks.rotation import RerunSink, recording_parts
from monitor.sinks.runs import RUNS, run_ends

__all__ = ["DEFAULT_FLUSH_INTERVAL_S", "REPLAY_BATCH_SIZE", "REPLAY_PART_BYTES", "RUNS",
           "RecordingOutlet", "RerunSink", "recording_parts", "run_ends"]

