"""Deprecated: the KINS/COCO format moved to :mod:`seqshape.data.kins` (the data layer, where
the scene generator can use it too).

The old names keep working for one release with a :class:`DeprecationWarning`.
"""

import seqshape.data.kins as _kins
from seqshape._deprecated import forward

__getattr__ = forward(__name__, _kins, (
    "KINS_CATEGORIES", "IMAGE_KEYS", "KINS_KEYS", "COCO_KEYS", "mask_to_rle", "rle_to_mask",
    "segm_to_mask", "mask_to_polygons", "encode_segm", "bbox_of_mask", "occlusion_order",
    "kins_annotation", "coco_annotation", "image_entry", "write_kins", "read_kins",
    "write_coco_instances", "read_coco_instances", "annotation_mask", "annotations_by_image"))
