"""colmap-citymodel: georeference and refine COLMAP reconstructions with a CityGML LOD2 model."""

from __future__ import annotations

import logging

__version__ = "0.2.0"

logger = logging.getLogger("colmap_citymodel")
if not logger.handlers:
    _handler = logging.StreamHandler()
    _handler.setFormatter(
        logging.Formatter("[%(asctime)s %(name)s %(levelname)s] %(message)s", "%H:%M:%S")
    )
    logger.addHandler(_handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False

from .citymodel.read import read_city_model  # noqa: E402
from .errors import CityModelError  # noqa: E402
from .options import RefineOptions  # noqa: E402
from .output.result import RefineResult
from .workflow import refine  # noqa: E402

__all__ = ["CityModelError", "RefineOptions", "RefineResult", "logger", "read_city_model",
           "refine", "__version__"]
