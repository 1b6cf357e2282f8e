"""The ``cloudpose`` command line: every stage of the pipeline, and the ablation suite.

The Makefile's targets are thin calls of these commands. Each command parses its options,
calls one library function and prints: :mod:`~cloudpose.cli.info` (what the suite holds),
:mod:`~cloudpose.cli.data` (synthetic data, export, segment caches), :mod:`~cloudpose.cli.stages`
(train, evaluate, predict, run, baseline), :mod:`~cloudpose.cli.sweep` (ablations),
:mod:`~cloudpose.cli.serve` (MLflow) and :mod:`~cloudpose.cli.reports`; the app, its error
handling and the options they share are :mod:`~cloudpose.cli.app`.
"""

import importlib

from cloudpose.cli.app import app, recorded_command

COMMAND_MODULES = ("info", "data", "stages", "pretrained", "sweep", "serve", "reports", "stress")
"""The modules whose commands register on :data:`app`, in the order ``--help`` lists them."""
for _name in COMMAND_MODULES:
    importlib.import_module(f"cloudpose.cli.{_name}")

from cloudpose.cli.stages import (  # noqa: E402 (registered above, in order)
    EXPECTED_WARNINGS,
    _mark_expected,
    _next_steps,
    _print_summary,
)

__all__ = [
    "EXPECTED_WARNINGS",
    "_mark_expected",
    "_next_steps",
    "_print_summary",
    "app",
    "recorded_command",
]
