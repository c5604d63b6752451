"""Typed errors. Domain errors become one-line CLI messages only at the edge (cli.py)."""

from __future__ import annotations

from pathlib import Path


class CityModelError(Exception):
    """Base class of every error this package raises on purpose.

    `path` names the file or directory the problem is about; the CLI prints
    "error: <path>: <message>" and exits with `exit_code`.
    """

    exit_code = 2

    def __init__(self, message: str, path: str | Path | None = None):
        self.message = message
        self.path = None if path is None else Path(path)
        super().__init__(f"{path}: {message}" if path is not None else message)


class InputError(CityModelError):
    """A file is missing, unreadable, malformed or not of the expected kind."""


class CityGMLError(InputError):
    """A CityGML/CityJSON file cannot be turned into a building model."""


class CRSError(CityModelError):
    """No, unknown, mixed or unusable coordinate reference system."""


class GNSSError(InputError):
    """GNSS positions are missing, too few, or name unknown images."""


class GeoregistrationError(CityModelError):
    """The reconstruction cannot be brought into the model frame."""


class DatumError(CityModelError):
    """Too few model planes (and no GNSS) to fix the 7 datum parameters."""


class NoOverlapError(CityModelError):
    """The city model does not overlap the reconstruction."""


class ExtensionImportError(ImportError):
    """The compiled extension cannot be used together with pycolmap/pyceres."""
