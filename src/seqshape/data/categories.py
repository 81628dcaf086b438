"""The one category table: seqshape's vehicle classes, the KINS category ids, KITTI types.

Every module that names a category takes it from here: the readers map their dataset's own
category names to :data:`VEHICLE_CLASSES`, the labeller and the scene generator write the
KINS ids of :data:`CLASS_TO_KINS` (a KITTI type through :data:`KITTI_TYPE_TO_KINS`) and
every KINS/COCO file lists :data:`KINS_CATEGORIES`.

>>> CLASS_TO_KINS["van"], KITTI_CLASSES["Van"], KITTI_TYPE_TO_KINS["Car"]
(7, 'van', 4)
"""

from __future__ import annotations

#: seqshape's vehicle classes, smallest first.
VEHICLE_CLASSES = ("car", "van", "truck", "bus", "trailer")

#: KINS categories: ids 1-8 as in the KINS release, plus bus 9 and trailer 10 (no KINS id;
#: written by the labeller for datasets that have them).
KINS_CATEGORIES = [
    {"id": 1, "name": "cyclist"}, {"id": 2, "name": "pedestrian"}, {"id": 4, "name": "car"},
    {"id": 5, "name": "tram"}, {"id": 6, "name": "truck"}, {"id": 7, "name": "van"},
    {"id": 8, "name": "misc"}, {"id": 9, "name": "bus"}, {"id": 10, "name": "trailer"},
]

#: KINS category id of each vehicle class (the KINS category of the same name: car 4,
#: van 7, truck 6, bus 9, trailer 10).
CLASS_TO_KINS = {c: next(k["id"] for k in KINS_CATEGORIES if k["name"] == c)
                 for c in VEHICLE_CLASSES}

#: KITTI tracking types that are vehicles seqshape handles, and their class.
KITTI_CLASSES = {"Car": "car", "Van": "van", "Truck": "truck"}

#: The KITTI type written for a class (the inverse of :data:`KITTI_CLASSES`).
CLASS_TO_KITTI = {c: t for t, c in KITTI_CLASSES.items()}

#: KINS category id of each KITTI type in :data:`KITTI_CLASSES`.
KITTI_TYPE_TO_KINS = {t: CLASS_TO_KINS[c] for t, c in KITTI_CLASSES.items()}
