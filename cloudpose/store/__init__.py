"""The run store: MLflow tracking (experiments, runs, tags), run records and checkpoints, the
headline metrics a run is summarised by, the per-instance tables of evaluations (Parquet or
CSV), runs rekeyed to today's data keys and the shipped network. A store packed to be committed
(an archive or the compact form) and unpacked is :mod:`cloudpose.archive`'s."""
