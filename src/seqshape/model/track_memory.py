"""A parked vehicle's earlier points, fed with its new frame (``Estimator(track_memory="parked")``).

A vehicle parked by the road and passed by a moving ego is seen from a changing angle: first
its rear from afar, then its side, then its front. One frame shows one view, and where a
frame does not show the far end of a car the networks fill it in from the fleet they learned
(docs/history/model.md, "Where the real radial bias comes from"). The vehicle does not move, so
the ego poses alone carry every earlier frame's points into the new sensor frame exactly (to
the accuracy of the ego poses): the way offboard detectors treat static objects. The
recurrent state was meant to carry that evidence, but on real sequences it carries little
(docs/results.md, "Real sequences").

:class:`TrackMemory` keeps, per track, a random subset of each frame's points in the fixed
frame of the ego poses and where the track's estimates put the vehicle. A frame is fed with
its memory when the track *looks parked* (:meth:`TrackMemory.parked`):

* at least :data:`MIN_DETECTIONS` earlier estimates, all within :data:`PARK_RADIUS` of their
  median in the fixed frame (a moving vehicle leaves that circle within a few frames, so its
  points are never stacked over more than that radius);
* the ego has moved at least :data:`MIN_EGO_TRAVEL` over the track (a static sensor repeats
  one view: nothing to add).

The input is then half the new frame (a random subset of at most ``N / 2`` of its points; all
of them when it has fewer) and, for the rest, a random sample of the stored points of frames
taken within :data:`MEMORY_REACH` of the current ego position, moved into the current sensor
frame: the network still sees mostly a frame like the ones it was trained on, and an error of
the ego poses that grows with the distance travelled (KITTI 0000's oxts poses are 3.5 % short)
blurs the memory by at most a few per cent of that reach. An identity switch (another vehicle
under the same id) leaves the parked circle, and the memory stops feeding.

Measured (docs/history/model.md, "Track memory for parked vehicles"; ``python
benchmarks/bm_realdata.py ... [--ego-poses lidar] [--track-memory none]``): on KITTI 0000 the
online median centre error from the 9th detection goes from 0.89x the per-frame baseline's to
0.79x with LiDAR-odometry ego poses and to 0.85x with the log's oxts poses; the synthetic sets
gain a little online and move under 0.7 % otherwise. The sequential model's default; the
per-frame baseline's is ``"none"``. It costs about 0.1-0.2 ms of Python per track and step
given ego poses (``python benchmarks/bm_streaming.py --drive-by``).
"""

from __future__ import annotations

import numpy as np

from seqshape.errors import ConfigError

#: The values of ``Estimator(track_memory=...)``.
TRACK_MEMORY = ("none", "parked")
#: Fewest earlier estimates with points before a track can count as parked.
MIN_DETECTIONS = 5
#: A parked track's estimates lie within this distance (m) of their median in the fixed frame.
PARK_RADIUS = 0.5
#: The ego's least travel (m, the largest extent of its positions over the track) for a memory.
MIN_EGO_TRAVEL = 1.0
#: Frames whose ego position is within this distance (m) of the current one feed the memory.
MEMORY_REACH = 3.0
#: Frames a track's memory keeps (the newest).
MEMORY_FRAMES = 64
#: Points kept of each frame (a random subset of a larger one).
FRAME_POINTS = 512
#: Share of the network's input points taken from the new frame.
CURRENT_SHARE = 0.5


def check_track_memory(value) -> str:
    """``value`` if it is one of :data:`TRACK_MEMORY`, else :class:`ConfigError`."""
    if value not in TRACK_MEMORY:
        raise ConfigError(f"track_memory must be one of {TRACK_MEMORY}, got {value!r}")
    return value


class TrackMemory:
    """One track's stored points and estimated positions in the fixed frame (module doc), in
    ring buffers allocated at its first frame (:data:`MEMORY_FRAMES` x :data:`FRAME_POINTS`
    points, float32 about the first frame's ego position: 0.4 MB a track)."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng  # its own: a track the memory never feeds gets the same subsets as without
        self._points: np.ndarray | None = None  # (F, P, 3) float32, about _origin
        self._counts = np.zeros(MEMORY_FRAMES, np.int64)  # points of each slot (0: empty)
        self._egos = np.zeros((MEMORY_FRAMES, 3))  # each slot's ego position
        self._origin = np.zeros(3)
        self._frames = 0  # frames recorded (the newest MEMORY_FRAMES are kept)
        self._centres = np.zeros((MEMORY_FRAMES, 2))  # estimated positions (ring)
        self._n_centres = 0
        self._in_circle = False  # the stored positions within PARK_RADIUS of their median
        self._ego_lo = np.full(3, np.inf)
        self._ego_hi = np.full(3, -np.inf)

    def __len__(self) -> int:
        """Frames stored."""
        return min(self._frames, MEMORY_FRAMES)

    def parked(self, here: np.ndarray) -> bool:
        """Whether the track looks parked and the ego, now at ``here`` (3,), has moved
        (module doc)."""
        if not self._in_circle or not self._frames:
            return False
        lo, hi = np.minimum(self._ego_lo, here), np.maximum(self._ego_hi, here)
        return bool(np.linalg.norm(hi - lo) >= MIN_EGO_TRAVEL)

    def feeds(self, ego: np.ndarray) -> bool:
        """Whether a frame with points taken at ego pose ``ego`` (4, 4) would be fed the
        memory (:meth:`parked`, and a stored frame within :data:`MEMORY_REACH`)."""
        return self._near(np.asarray(ego, dtype=np.float64)) is not None

    def _near(self, here: np.ndarray) -> np.ndarray | None:
        """The slots of the stored frames that feed a frame taken at ego pose ``here``, or None
        when the memory does not feed it."""
        if not self.parked(here[:3, 3]):
            return None
        near = np.flatnonzero((self._counts > 0) & (np.linalg.norm(
            self._egos - here[:3, 3], axis=1) <= MEMORY_REACH))
        return near if len(near) else None

    def frame_input(self, points: np.ndarray, ego: np.ndarray, n_max: int
                    ) -> np.ndarray | None:
        """The network's input for a frame of ``points`` (sensor frame, ``ego`` its pose in
        the fixed frame) with the memory mixed in (float32, at most ``n_max`` points), or None
        when the memory does not apply (:meth:`parked` is False, an empty frame, or no stored
        frame within :data:`MEMORY_REACH`)."""
        here = np.asarray(ego, dtype=np.float64)
        near = self._near(here) if len(points) else None
        if near is None:
            return None
        rng = self.rng
        n_cur = min(len(points), max(1, int(n_max * CURRENT_SHARE)))
        cur = points if n_cur == len(points) else \
            points[np.sort(rng.choice(len(points), n_cur, replace=False))]
        ends = np.cumsum(self._counts[near])
        n_old = min(int(ends[-1]), n_max - n_cur)
        if n_old < 1:
            return None
        pick = rng.choice(int(ends[-1]), n_old, replace=False)  # over the near frames' points
        slot = np.searchsorted(ends, pick, side="right")
        old = self._points[near[slot], pick - (ends[slot] - self._counts[near[slot]])]
        inv = np.linalg.inv(here)
        old = (old + self._origin) @ inv[:3, :3].T + inv[:3, 3]
        return np.concatenate([np.asarray(cur, dtype=np.float32), old.astype(np.float32)])

    def record(self, points: np.ndarray, ego: np.ndarray, pose: np.ndarray | None) -> None:
        """Store a frame with points (at most :data:`FRAME_POINTS` of them, in the fixed
        frame) and, when ``pose`` is a valid estimate, where it put the vehicle."""
        if not len(points):
            return
        e = np.asarray(ego, dtype=np.float64)
        if self._points is None:
            self._points = np.zeros((MEMORY_FRAMES, FRAME_POINTS, 3), np.float32)
            self._origin = e[:3, 3].copy()
        if len(points) > FRAME_POINTS:
            points = points[self.rng.choice(len(points), FRAME_POINTS, replace=False)]
        slot = self._frames % MEMORY_FRAMES
        world = np.asarray(points, dtype=np.float64) @ e[:3, :3].T + (e[:3, 3] - self._origin)
        self._points[slot, :len(world)] = world
        self._counts[slot] = len(world)
        self._egos[slot] = e[:3, 3]
        self._frames += 1
        self._ego_lo = np.minimum(self._ego_lo, e[:3, 3])
        self._ego_hi = np.maximum(self._ego_hi, e[:3, 3])
        if pose is not None and np.all(np.isfinite(pose)):
            self._centres[self._n_centres % MEMORY_FRAMES] = \
                e[:2, :2] @ np.asarray(pose[:2], dtype=np.float64) + e[:2, 3]
            self._n_centres += 1
            if self._n_centres >= MIN_DETECTIONS:
                c = self._centres[:min(self._n_centres, MEMORY_FRAMES)]
                d = c - np.median(c, axis=0)
                self._in_circle = bool((np.einsum("ij,ij->i", d, d) <= PARK_RADIUS ** 2).all())


def memory_would_feed(poses: np.ndarray, egos, has_points: np.ndarray) -> bool:
    """Whether a track's memory would feed any of its frames, given its estimates ``poses``
    (T, 4) without the memory, ``egos`` (T entries, (4, 4) or None) and which frames have
    points: the memory's own rule (:meth:`TrackMemory.feeds`) replayed on one-point frames
    (until it first feeds a frame the estimates with the memory are these)."""
    mem = TrackMemory(np.random.default_rng(0))
    one = np.zeros((1, 3), np.float32)
    for pose, ego, has in zip(poses, egos, has_points, strict=True):
        if not has or ego is None:
            continue
        if mem.feeds(ego):
            return True
        mem.record(one, ego, pose)
    return False
