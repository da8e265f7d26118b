"""Dataset readers: ModelNet40 synthetic pairs and RGB-D frames (7-Scenes, SUN3D). Pure numpy, no ROS.

Every pair dict holds `source`, `target` and `transform` = T_target_source (target = R source + t).
"""

from genreg_core.data.modelnet40 import (
    CATEGORY_SETS,
    NUM_SEEN,
    VARIANTS,
    ModelNetPairs,
    ModelNetShapes,
    balanced_sampler_indices,
    load_class_names,
    load_modelnet40,
    modelnet40_dir,
)
from genreg_core.data.rgbd import (
    REDKITCHEN_TRAIN_FRAMES,
    REDKITCHEN_VAL_FRAMES,
    SEQUENCES,
    SEVEN_SCENES_INTRINSICS,
    FMRPairs,
    FramePairs,
    RGBDSequence,
    depth_to_points,
    read_depth,
    read_intrinsics,
    read_pose,
)

__all__ = [
    "CATEGORY_SETS",
    "NUM_SEEN",
    "REDKITCHEN_TRAIN_FRAMES",
    "REDKITCHEN_VAL_FRAMES",
    "SEQUENCES",
    "SEVEN_SCENES_INTRINSICS",
    "VARIANTS",
    "FMRPairs",
    "FramePairs",
    "ModelNetPairs",
    "ModelNetShapes",
    "RGBDSequence",
    "balanced_sampler_indices",
    "depth_to_points",
    "load_class_names",
    "load_modelnet40",
    "modelnet40_dir",
    "read_depth",
    "read_intrinsics",
    "read_pose",
]
