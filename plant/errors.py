"""Exceptions of the plant package; each also inherits the matching builtin."""


class PlantError(Exception):
    """Base class of every error the plant package raises."""


class ConfigError(PlantError, ValueError):
    """A machine file is unreadable, incomplete or physically impossible.

    The message names the file, the key and the expected unit or range.
    """


class PlantFault(PlantError, RuntimeError):
    """The kernel reported a fault status (non-finite or diverging state)."""
