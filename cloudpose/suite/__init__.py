"""Running the suite: one run through the pipeline (train, evaluate, baselines), the ablation
runner over the registry's groups, the segmentation ablation, the plan printed before long work
and the Ray executor."""
