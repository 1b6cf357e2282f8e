"""The variant registry, training presets and baseline settings, as data (``variants.toml``,
``presets.toml``, ``baselines.toml``).

Loaded and validated by :mod:`cloudpose.config`; nothing here is code but the file paths.
"""

from importlib import resources
from pathlib import Path

VARIANTS_FILE = Path(str(resources.files(__name__).joinpath("variants.toml")))
PRESETS_FILE = Path(str(resources.files(__name__).joinpath("presets.toml")))
BASELINES_FILE = Path(str(resources.files(__name__).joinpath("baselines.toml")))
