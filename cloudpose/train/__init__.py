"""Training: the loop (:mod:`~cloudpose.train.loop`), DDP on several processes
(:mod:`~cloudpose.train.distributed`) and the per-epoch validation
(:mod:`~cloudpose.train.validation`)."""
