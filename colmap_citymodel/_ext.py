"""Load the compiled extension `colmap_citymodel._core` and check it works with pyceres.

Use `load_core()` instead of importing `_core` directly: it turns the two ways the extension
can be unusable into one readable `ExtensionImportError`:

- `_core` is missing or cannot be loaded (not built, or a Debian library such as libceres is
  missing): the message says how to build it;
- `_core` was built against other pybind11 internals than pycolmap 4.2.1 / pyceres 2.6
  (pybind11 3.0.x, internals v11). Then its factories cannot hand a `ceres::CostFunction*` to
  pyceres ("Unable to convert function return value to a Python type"); the self-check below
  catches that at load time instead of in the middle of a bundle adjustment.

The self-check evaluates one point-to-plane cost in a tiny `pyceres.Problem` (well below 1 ms)
and runs once per process.
"""

from __future__ import annotations

import functools
import importlib
import logging
from types import ModuleType

import numpy as np

from .errors import ExtensionImportError

logger = logging.getLogger(__name__)

#: pybind11 internals version shared by pycolmap 4.2.1 and pyceres 2.6 (pybind11 3.0.x).
EXPECTED_PYBIND11_INTERNALS_VERSION = 11

BUILD_HINT = (
    "build it from the repository root with `bash scripts/bootstrap.sh` or "
    "`.venv/bin/pip install --no-build-isolation -e .` (needs the Debian packages "
    "libceres-dev libeigen3-dev libgoogle-glog-dev g++ cmake and pybind11>=3.0,<3.1)"
)


def _import_core() -> ModuleType:
    try:
        return importlib.import_module("colmap_citymodel._core")
    except ModuleNotFoundError as exc:
        if exc.name not in ("colmap_citymodel._core", None):
            # e.g. pyceres itself is missing: _core imports it at load time.
            raise ExtensionImportError(
                f"the extension colmap_citymodel._core needs the Python package "
                f"'{exc.name}', which is not installed (pip install pyceres==2.6 pycolmap==4.2.1)"
            ) from exc
        raise ExtensionImportError(
            f"the compiled extension colmap_citymodel._core is not built; {BUILD_HINT}"
        ) from exc
    except ImportError as exc:
        # A shared library could not be loaded (e.g. libceres.so.2 after removing libceres-dev)
        # or the module was built for another Python.
        raise ExtensionImportError(
            f"the compiled extension colmap_citymodel._core cannot be loaded ({exc}); "
            f"rebuild it: {BUILD_HINT}"
        ) from exc


def _self_check(core: ModuleType) -> None:
    """Pass one of our cost functions through pyceres and compare with the closed form."""
    import pyceres

    ours = getattr(core, "__pybind11_internals_version__", None)
    mismatch_hint = (
        f"colmap_citymodel._core was built with pybind11 {getattr(core, '__pybind11_version__', '?')} "
        f"(internals v{ours}), but pycolmap 4.2.1 and pyceres 2.6 use pybind11 internals "
        f"v{EXPECTED_PYBIND11_INTERNALS_VERSION} (pybind11 3.0.x), so pyceres cannot accept its "
        f"cost functions. Reinstall with pybind11 3.0.x: `.venv/bin/pip install 'pybind11>=3.0,<3.1'` "
        f"then `.venv/bin/pip install --no-build-isolation -e .` (or `bash scripts/bootstrap.sh`)"
    )
    try:
        cost = core.PointPlaneDistanceCost(0.5)
    except TypeError as exc:  # "Unable to convert function return value to a Python type"
        raise ExtensionImportError(f"{mismatch_hint}. Original error: {exc}") from exc
    if not isinstance(cost, pyceres.CostFunction):
        raise ExtensionImportError(f"{mismatch_hint} (got a {type(cost).__name__!r} object)")

    point = np.array([1.0, 2.0, 3.0])
    normal = np.array([0.0, 0.0, 1.0])
    offset = np.array([-1.0])
    problem = pyceres.Problem()
    try:
        problem.add_residual_block(cost, None, [point, normal, offset])
        residuals = problem.evaluate_residuals()
    except TypeError as exc:
        raise ExtensionImportError(f"{mismatch_hint}. Original error: {exc}") from exc
    expected = (point @ normal + offset[0]) / 0.5
    if len(residuals) != 1 or abs(residuals[0] - expected) > 1e-12:
        raise ExtensionImportError(
            f"colmap_citymodel._core evaluates a point-plane distance as {residuals}, expected "
            f"[{expected}]: the extension and pyceres disagree on ceres::CostFunction "
            f"(Ceres {getattr(core, '__ceres_version__', '?')} vs pyceres's "
            f"{getattr(pyceres, '__ceres_version__', '?')}); rebuild it: {BUILD_HINT}"
        )


@functools.cache
def load_core() -> ModuleType:
    """Return the checked `colmap_citymodel._core` module, or raise ExtensionImportError."""
    core = _import_core()
    _self_check(core)
    logger.debug(
        "loaded %s (Ceres %s, pybind11 %s)",
        core.__file__,
        getattr(core, "__ceres_version__", "?"),
        getattr(core, "__pybind11_version__", "?"),
    )
    return core


def sqrt_information(covariance: np.ndarray) -> np.ndarray:
    """Square-root information matrix L with L^T L = covariance^-1 (residual = L (x - x_obs)).

    Raises ValueError if the covariance is not a symmetric positive definite 3x3 matrix.
    """
    cov = np.asarray(covariance, dtype=float)
    if cov.shape != (3, 3) or not np.all(np.isfinite(cov)) or not np.allclose(cov, cov.T):
        raise ValueError(f"covariance must be a finite symmetric 3x3 matrix, got {cov!r}")
    try:
        chol = np.linalg.cholesky(cov)  # cov = C C^T
    except np.linalg.LinAlgError as exc:
        raise ValueError(f"covariance is not positive definite: {cov!r}") from exc
    # L = C^-1 gives L^T L = C^-T C^-1 = (C C^T)^-1.
    return np.linalg.inv(chol)
