"""The run store: MLflow tracking (experiments, runs, tags), run records and checkpoints, the
headline metrics a run is summarised by, the committed store archives (pack, unpack, rekey) and
the shipped network."""
