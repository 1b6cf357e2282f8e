"""The run store: MLflow tracking (experiments, runs, tags), run records and checkpoints, the
headline metrics a run is summarised by, the per-instance tables of evaluations (Parquet or
CSV), the committed stores (packed as an archive or in the compact form, unpacked, rekeyed) and
the shipped network."""
