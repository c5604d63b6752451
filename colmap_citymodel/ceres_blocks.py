"""Reach the parameter blocks of COLMAP's bundle adjustment (pycolmap 4.2.1) from Python.

COLMAP's `create_default_ceres_bundle_adjuster(options, config, reconstruction)` builds a
`pyceres.Problem` whose parameter blocks ARE the memory of the reconstruction's objects. pycolmap
hands out numpy views of that memory, so a residual added on such a view acts on the same unknown
as COLMAP's reprojection residuals (see docs/ceres_blocks.md for what was verified):

- point:  `reconstruction.points3D[id].xyz`                (3)
- frame:  `reconstruction.frames[id].rig_from_world.params` (7: qx, qy, qz, qw, tx, ty, tz;
          one block on a product manifold EigenQuaternion x R^3, tangent size 6, or 5 when the
          gauge fixes a frame's translation direction)
- sensor: `reconstruction.rigs[id].non_ref_sensors[sensor_id].params` (7, non-reference sensors
          of real rigs). Not `rig.sensor_from_rig(sensor_id)`: through `rec.rigs[id]` it was
          seen to return a copy.
- camera: `reconstruction.cameras[id].params`               (model dependent)

Lifetime rule (verified by crashing it): pyceres keeps a cost function, loss function and the
parameter arrays alive only as long as the *Python* `pyceres.Problem` object it was added through.
`adjuster.problem` returns the same Python object only while someone holds it, so
`adjuster.problem.add_residual_block(...)` on a temporary frees the cost before the solve. And
pyceres's `add_parameter_block(values, size, manifold)` passes the manifold unwrapped to COLMAP's
problem, which owns manifolds and deletes it a second time at the end. `HybridProblem` below
holds the adjuster, its problem and every object added, and sets manifolds via `set_manifold`
(which pyceres wraps), so neither can happen.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np
import pyceres
import pycolmap

#: Size of COLMAP 4's pose parameter block (Rigid3d.params: quaternion xyzw + translation).
POSE_BLOCK_SIZE = 7


def _check_view(block: np.ndarray, again: np.ndarray, what: str) -> np.ndarray:
    # Two accesses returning the same address prove the array is a view of the C++ object,
    # not a copy (a copy would silently decouple our residuals from COLMAP's).
    if block.__array_interface__["data"][0] != again.__array_interface__["data"][0]:
        raise RuntimeError(f"pycolmap returned a copy, not a view, of {what}")
    return block


def point_block(reconstruction: pycolmap.Reconstruction, point3D_id: int) -> np.ndarray:
    """The (3,) xyz array of a 3D point, aliasing the block COLMAP's bundle adjuster uses."""
    xyz = reconstruction.points3D[point3D_id].xyz
    return _check_view(xyz, reconstruction.points3D[point3D_id].xyz, f"point3D {point3D_id}")


def frame_pose_block(reconstruction: pycolmap.Reconstruction, frame_id: int) -> np.ndarray:
    """The (7,) rig_from_world.params array [qx, qy, qz, qw, tx, ty, tz] of a frame.

    In COLMAP 4 the rotation and the translation are ONE parameter block (not two as in COLMAP 3);
    `block[:4]` / `block[4:]` are views of the quaternion and the translation.
    """
    frame = reconstruction.frames[frame_id]
    if not frame.has_pose():
        raise ValueError(f"frame {frame_id} has no pose")
    params = frame.rig_from_world.params
    return _check_view(
        params, reconstruction.frames[frame_id].rig_from_world.params, f"frame {frame_id} pose"
    )


def sensor_from_rig_block(
    reconstruction: pycolmap.Reconstruction, rig_id: int, sensor_id: pycolmap.sensor_t
) -> np.ndarray:
    """The (7,) sensor_from_rig.params of a non-reference sensor (a block when refined)."""
    sensors = reconstruction.rigs[rig_id].non_ref_sensors
    if sensor_id not in sensors:
        raise ValueError(f"sensor {sensor_id} is not a non-reference sensor of rig {rig_id}")
    params = sensors[sensor_id].params
    again = reconstruction.rigs[rig_id].non_ref_sensors[sensor_id].params
    return _check_view(params, again, f"rig {rig_id} sensor {sensor_id}")


def camera_block(reconstruction: pycolmap.Reconstruction, camera_id: int) -> np.ndarray:
    """The intrinsics array of a camera (a block only if intrinsics are refined or constant)."""
    params = reconstruction.cameras[camera_id].params
    return _check_view(params, reconstruction.cameras[camera_id].params, f"camera {camera_id}")


def position_in_rig(reconstruction: pycolmap.Reconstruction, image_id: int) -> np.ndarray:
    """Projection centre of an image's camera in its rig frame (zero for the reference sensor).

    With it, `_core.ProjectionCenterPriorCost(C_obs, sigma, position_in_rig)` on the frame's pose
    block observes the camera's centre; add a lever arm (in rig coordinates) for a GNSS antenna.
    """
    image = reconstruction.images[image_id]
    frame = reconstruction.frames[image.frame_id]
    rig = reconstruction.rigs[frame.rig_id]
    sensor_id = image.camera.sensor_id
    if rig.is_ref_sensor(sensor_id):
        return np.zeros(3)
    cam_from_rig = rig.sensor_from_rig(sensor_id)
    # Centre of the camera in rig coordinates: -R_cam_from_rig^T t_cam_from_rig.
    return np.asarray(cam_from_rig.inverse().translation, dtype=float).copy()


def is_variable_block(problem: pyceres.Problem, block: np.ndarray) -> bool:
    """True if `block` is a parameter block of `problem` and not held constant."""
    return bool(problem.has_parameter_block(block)) and not problem.is_parameter_block_constant(
        block
    )


@dataclasses.dataclass
class PlaneBlocks:
    """A plane n . X + d = 0 as two parameter blocks: unit normal (3, sphere manifold), offset (1)."""

    normal: np.ndarray
    offset: np.ndarray

    @property
    def plane(self) -> np.ndarray:
        """(4,) [nx, ny, nz, d] with |n| = 1 (normalised copy)."""
        norm = float(np.linalg.norm(self.normal))
        return np.concatenate([self.normal / norm, self.offset / norm])


class HybridProblem:
    """COLMAP's bundle-adjustment problem plus our own residual blocks, with safe lifetimes.

    Build it from an adjuster made by `pycolmap.create_default_ceres_bundle_adjuster` (or the pose
    prior variant), add residuals on views from `point_block`/`frame_pose_block` and on new blocks
    from `add_plane`, then `solve()`. Keep this object alive until after the solve and until you
    stop using the adjuster.
    """

    def __init__(self, adjuster: pycolmap.CeresBundleAdjuster):
        self.adjuster = adjuster
        # Holding the Python problem object keeps everything pyceres ties to it alive.
        self.problem: pyceres.Problem = adjuster.problem
        self._keep: list[Any] = []

    def add_residual(
        self,
        cost: pyceres.CostFunction,
        loss: pyceres.LossFunction | None,
        blocks: Sequence[np.ndarray],
    ) -> pyceres.ResidualBlock:
        """Add one residual block; `blocks` must be float64 C-contiguous arrays (views or own)."""
        blocks = list(blocks)
        for i, block in enumerate(blocks):
            if not (
                isinstance(block, np.ndarray)
                and block.dtype == np.float64
                and block.flags["C_CONTIGUOUS"]
            ):
                # pyceres would silently convert, i.e. optimise a temporary copy.
                raise TypeError(
                    f"parameter block {i} must be a C-contiguous float64 numpy array, "
                    f"got {type(block).__name__} {getattr(block, 'dtype', '')}"
                )
        block_id = self.problem.add_residual_block(cost, loss, blocks)
        self._keep.append((cost, loss, blocks))
        return block_id

    def add_plane(self, normal: Sequence[float], offset: float) -> PlaneBlocks:
        """New plane blocks: the normal is normalised and put on pyceres.SphereManifold(3)."""
        n = np.array(normal, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(n))
        if not np.isfinite(norm) or norm == 0.0:
            raise ValueError(f"plane normal must be a finite non-zero vector, got {normal!r}")
        plane = PlaneBlocks(normal=n / norm, offset=np.array([float(offset) / norm]))
        self.problem.add_parameter_block(plane.normal, 3)
        self.problem.add_parameter_block(plane.offset, 1)
        manifold = pyceres.SphereManifold(3)
        # set_manifold wraps the manifold; add_parameter_block(.., manifold) would not, and
        # COLMAP's problem (manifold ownership TAKE_OWNERSHIP) would free it twice.
        self.problem.set_manifold(plane.normal, manifold)
        self._keep.append((plane, manifold))
        return plane

    def add_block(self, values: np.ndarray) -> np.ndarray:
        """Register a new free parameter block (e.g. a model vertex) and keep it alive."""
        if not (values.dtype == np.float64 and values.flags["C_CONTIGUOUS"]):
            raise TypeError("parameter blocks must be C-contiguous float64 numpy arrays")
        self.problem.add_parameter_block(values, values.size)
        self._keep.append(values)
        return values

    def set_constant(self, block: np.ndarray) -> None:
        self.problem.set_parameter_block_constant(block)

    def solve(self) -> Any:
        """Solve with COLMAP's own solver set-up; returns the BundleAdjustmentSummary."""
        return self.adjuster.solve()
