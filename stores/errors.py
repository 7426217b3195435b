"""One error hierarchy for the whole project (after zarr's ``errors.py``).

Each class also inherits the matching builtin, so callers can catch either.
Messages say what went wrong, where, and how to fix it.
"""


class PersonaError(Exception):
    """Base class of every error Persona raises on purpose."""


class InputError(PersonaError, ValueError):
    """Bad user input: a missing file, an empty folder, a broken video."""


class StorageError(PersonaError, RuntimeError):
    """Object storage cannot be reached: a missing bucket or key, an unreachable endpoint, missing or
    refused credentials, or fsspec's driver for the URL not installed."""
