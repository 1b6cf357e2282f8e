"""A project's run store (:mod:`cloudpose.store`) packed to be committed beside its reports, and
unpacked anywhere (``cloudpose store-pack``, ``cloudpose store-unpack``):
:mod:`cloudpose.archive.pack` packs and unpacks a store's folder, as one ``.tar.xz`` or in the
compact form that git stores run by run (:mod:`cloudpose.archive.compact`), whose instance tables
are packed (:mod:`cloudpose.archive.packed`) and whose kept checkpoints take fewer bytes where
their poses do not move (:mod:`cloudpose.archive.checkpoints`, which also loads such a checkpoint).
It reads and writes the MLflow store through :mod:`cloudpose.store`; the run store never imports
it."""
