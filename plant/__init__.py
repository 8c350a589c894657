"""Feed-drive plant models: numba kernels on flat arrays, configured by TOML machine files.

``plant`` imports nothing from ``hil`` or ``io_adapters``.
"""

from plant import _cache

_cache.configure()

from plant.config import MachineConfig, load_machine  # noqa: E402  (after the cache)
from plant.errors import ConfigError, PlantError, PlantFault  # noqa: E402
from plant.model import INPUTS, OUTPUTS, Plant, Trace  # noqa: E402

__all__ = ["ConfigError", "INPUTS", "MachineConfig", "OUTPUTS", "Plant", "PlantError",
           "PlantFault", "Trace", "load_machine"]
