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
"""The modules whose commands register on :data:`app` (``--help`` lists them by :data:`PANELS`)."""
for _name in COMMAND_MODULES:
    importlib.import_module(f"cloudpose.cli.{_name}")

PANELS = {
    "Pipeline": ("run", "train", "evaluate", "predict", "synth", "prepare", "export"),
    "Ablations and reports": ("ablate", "ablate-masks", "report", "occlusion-report",
                              "real-report", "curves", "experiments", "variants", "presets",
                              "symmetries"),
    "Studies beside the paper": ("compare", "baseline", "stress", "showcase"),
    "Stores and tracking": ("mlflow-ui", "mlflow-server", "store-pack", "store-unpack",
                            "same-data", "ship"),
}  # fmt: skip
"""The panels ``cloudpose --help`` groups the commands in; every command is in one."""
_ORDER = [name for names in PANELS.values() for name in names]


def _command_name(info) -> str:
    return info.name or info.callback.__name__.replace("_", "-")


for _info in app.registered_commands:
    _info.rich_help_panel = next(p for p, names in PANELS.items() if _command_name(_info) in names)
app.registered_commands.sort(key=lambda info: _ORDER.index(_command_name(info)))

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
