"""Geometry core: camera models, Jacobians, normals, voxel downsampling, SE(3), reprojection."""

from image2sim.simulator.geometry.cameras import Camera, EquirectCamera, PinholeCamera, camera_from_dict

__all__ = ["Camera", "EquirectCamera", "PinholeCamera", "camera_from_dict"]
