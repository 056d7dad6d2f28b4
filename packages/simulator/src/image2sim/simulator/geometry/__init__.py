"""Geometry core: camera models, Jacobians, normals, voxel downsampling, SE(3), reprojection."""

from image2sim.simulator.geometry.cameras import Camera, EquirectCamera, PinholeCamera, camera_from_dict
from image2sim.simulator.geometry.normals import (
    SurfaceNormalEstimator,
    pad_equirect,
    point_normals,
    sobel_normals,
)
from image2sim.simulator.geometry.reproject import (
    CUBEMAP_FACES,
    cubemap_to_equirect,
    equirect_crop,
    equirect_to_cubemap,
    perspective_from_equirect,
    sample_equirect,
)
from image2sim.simulator.geometry.se3 import (
    invert_pose,
    make_pose,
    matrix_to_quat,
    normalize_quat,
    quat_multiply,
    quat_to_matrix,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
    rotation_error,
    transform_points,
)
from image2sim.simulator.geometry.voxel import voxel_downsample, voxel_keys

__all__ = [
    "Camera",
    "EquirectCamera",
    "PinholeCamera",
    "camera_from_dict",
    "sobel_normals",
    "SurfaceNormalEstimator",
    "point_normals",
    "pad_equirect",
    "voxel_downsample",
    "voxel_keys",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_multiply",
    "normalize_quat",
    "quat_wxyz_to_xyzw",
    "quat_xyzw_to_wxyz",
    "make_pose",
    "invert_pose",
    "transform_points",
    "rotation_error",
    "perspective_from_equirect",
    "equirect_crop",
    "equirect_to_cubemap",
    "cubemap_to_equirect",
    "sample_equirect",
    "CUBEMAP_FACES",
]
