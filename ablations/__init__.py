"""The variant registry and training presets, as data (``variants.toml``, ``presets.toml``).

Loaded and validated by :mod:`cloudpose.config`; nothing here is code but the file paths.
"""

from importlib import resources
from pathlib import Path

VARIANTS_FILE = Path(str(resources.files(__name__).joinpath("variants.toml")))
PRESETS_FILE = Path(str(resources.files(__name__).joinpath("presets.toml")))
