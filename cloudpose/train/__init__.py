"""Training: the loop (:mod:`~cloudpose.train.loop`), one optimiser step
(:mod:`~cloudpose.train.step`), the batch augmentations (:mod:`~cloudpose.train.augment`), the
random streams (:mod:`~cloudpose.train.seeds`), DDP on several processes
(:mod:`~cloudpose.train.distributed`) and the per-epoch validation
(:mod:`~cloudpose.train.validation`)."""
