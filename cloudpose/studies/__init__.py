"""The studies beside the paper, each a loop over methods x conditions x refinements on top of
:mod:`cloudpose.methods`: ``cloudpose compare`` (:mod:`.compare`: the network and the classical
registrations on the same frames), ``stress`` (:mod:`.stress`, its conditions in
:mod:`.perturbations`), ``showcase`` (:mod:`.showcase`: the shipped network at work) and the
baseline runs logged to MLflow (:mod:`.baseline_runs`, ``cloudpose baseline``)."""
