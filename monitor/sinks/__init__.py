"""The pipeline's outlets, each a `Sink` (`base`): the Rerun recording or live stream
(`rerun`, its look in `blueprint`, rotating files in `rotation`, crash recovery in
`salvage`), the diagnosis frames on the bus (`publisher`), JSON lines (`jsonl`), every
sample to a Parquet or CSV table (`samples`) and the log (`log`). `FanOut` joins several."""

from monitor.sinks.base import FanOut, Sink

__all__ = ["FanOut", "Sink"]
