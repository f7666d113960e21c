"""Re-diagnose an archive of bus logs: `motor-monitor replay PATH... --out DIR`.

* `engine`: the per-file engine interface (`PerFileEngine`, `EngineRun`) and today's
  engine, the per-frame pipeline (`per_frame_engine`);
* `run`: `replay_one` (one log, what a worker runs) and `run_archive` (every log, serially,
  on local processes or a Dask cluster);
* `inputs`: files, directories and glob patterns to logs and their output names;
* `result`, `summary`, `fleet`: each log's result, the summary table (Parquet, CSV) and
  the fleet overview (PNG);
* `progress`: the progress bar.

Dask distributed, tqdm and matplotlib come with the `archive` extra and are imported only
where they are used.
"""
