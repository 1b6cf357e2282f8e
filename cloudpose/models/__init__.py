"""Networks: BaseNet (PointNet without spatial transformers) and pose networks built from a variant."""

from cloudpose.models.basenet import (
    BaseNet,
    PointLayer,
    PointLayerMaxPool,
    RegressionHead,
    point_stages,
    scaled_width,
)
from cloudpose.models.pose import (
    ROTATION_SIZES,
    PoseNet,
    PoseOutput,
    build_model,
    count_parameters,
    raw_rotation_to_rotmat,
    segment_centre,
    variant_table,
)

__all__ = [
    "ROTATION_SIZES",
    "BaseNet",
    "PointLayer",
    "PointLayerMaxPool",
    "PoseNet",
    "PoseOutput",
    "RegressionHead",
    "build_model",
    "count_parameters",
    "point_stages",
    "raw_rotation_to_rotmat",
    "scaled_width",
    "segment_centre",
    "variant_table",
]
