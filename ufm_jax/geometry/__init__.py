"""Ground-truth geometry (numpy): cameras, depth reprojection, covisibility, supervision masks.

Conventions: OpenCV camera axes (x right, y down, z forward), camera-to-world 4x4 poses, pixel
(u, v) = (column, row) with pixel centres at integer coordinates, z-depth, invalid depth = 0/inf/nan.
Scene flow (FlyingThings3D / Monkaa): `sceneflow_covisibility`, from `ufm_jax.geometry.sceneflow`.
The official training code's static-pair rule: `official_labels` with `rendering_parameters`.
"""

from ufm_jax.geometry.camera import (OPENGL_TO_OPENCV, axis_angle_to_rotation, intrinsics,
                                     invert_pose, look_at, ned_to_opencv, opengl_to_opencv,
                                     pixel_grid, pose_from_rt, project, quaternion_to_rotation,
                                     range_to_z, ray_norms, rays, rotation_angle, transform,
                                     unproject, valid_depth, world2cam_to_cam2world, z_to_range)
from ufm_jax.geometry.covisibility import (bilinear_sample, correspondence_from_depth,
                                           covisibility_from_points, inside_image, nearest_sample,
                                           official_labels)
from ufm_jax.geometry.masks import (covis_supervision_mask, flyingchairs_labels,
                                    fov_mask_from_flow, labels_from_correspondence,
                                    other_view_validity)
from ufm_jax.geometry.rigid import correspondence_from_rigid_objects, object_motions
from ufm_jax.geometry.sceneflow import sceneflow_covisibility
from ufm_jax.geometry.thresholds import (COVIS_THRESHOLDS, RENDERING_PARAMETERS, covis_thresholds,
                                         rendering_parameters)

__all__ = [
    "axis_angle_to_rotation", "bilinear_sample", "correspondence_from_depth",
    "correspondence_from_rigid_objects", "covis_supervision_mask", "COVIS_THRESHOLDS",
    "covis_thresholds", "covisibility_from_points", "flyingchairs_labels", "fov_mask_from_flow",
    "inside_image", "intrinsics", "invert_pose", "labels_from_correspondence", "look_at",
    "nearest_sample", "ned_to_opencv", "object_motions", "official_labels", "OPENGL_TO_OPENCV",
    "opengl_to_opencv", "other_view_validity", "pixel_grid", "pose_from_rt", "project",
    "quaternion_to_rotation", "range_to_z", "ray_norms", "rays", "RENDERING_PARAMETERS",
    "rendering_parameters", "rotation_angle", "sceneflow_covisibility", "transform",
    "unproject", "valid_depth", "world2cam_to_cam2world", "z_to_range",
]
