"""Track data: the Track record, dataset folders, KITTI tracking I/O and torch datasets."""

from seqshape.data.dataset import TrackDataset, write_dataset, write_manifest
from seqshape.data.track import Track, load_track, save_track

__all__ = ["Track", "TrackDataset", "load_track", "save_track", "write_dataset",
           "write_manifest"]
