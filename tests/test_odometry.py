"""LiDAR odometry (seqshape.data.odometry): registration against known motions, the chain
of a drive whose ego poses are stretched and jittered, bridges, and the tracks it feeds."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from seqshape.data.extract import extract_tracks
from seqshape.data.odometry import (
    OdometryConfig,
    lidar_odometry,
    register,
    registration_cloud,
    rigid_fit,
    thin,
    with_lidar_odometry,
)
from seqshape.data.sequence import Box3D, DrivingLog
from seqshape.errors import ConfigError


def _pose(x, y, yaw, z=0.0) -> np.ndarray:
    m = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = [x, y, z]
    return m


def _world(rng: np.random.Generator) -> np.ndarray:
    """A static street (fixed frame, sensor height 0): two building fronts with recesses,
    poles and parked boxes, 1.5 cm sampling noise; no ground (it is cut anyway)."""
    parts = []
    for side in (-1, 1):
        for x0 in np.arange(-20.0, 80.0, 8.0):  # facades stepping in and out by 0.7 m
            y = side * (9.0 + 0.7 * (int(x0 / 8) % 2))
            u = rng.uniform(x0, x0 + 8.0, 900)
            z = rng.uniform(-1.2, 4.0, 900)
            parts.append(np.c_[u, np.full(900, y), z])
            parts.append(np.c_[np.full(300, x0), side * rng.uniform(9.0, 9.7, 300),
                               rng.uniform(-1.2, 4.0, 300)])
    for x0 in np.arange(-15.0, 80.0, 11.0):  # poles
        a = rng.uniform(0, 2 * np.pi, 200)
        parts.append(np.c_[x0 + 0.15 * np.cos(a), 6.5 + 0.15 * np.sin(a),
                           rng.uniform(-1.2, 3.0, 200)])
    for x0, yaw in ((5.0, 0.1), (23.0, -0.2), (41.0, 0.3)):  # parked boxes
        q = rng.uniform(-0.5, 0.5, (1500, 3)) * [4.4, 1.8, 1.5]
        k = rng.integers(0, 3, len(q))
        q[np.arange(len(q)), k] = np.sign(q[np.arange(len(q)), k]) * [2.2, 0.9, 0.75][0]
        parts.append(q @ _pose(0, 0, yaw)[:3, :3].T + [x0, -5.5, -0.6])
    return np.concatenate(parts) + rng.normal(0, 0.015, (sum(len(p) for p in parts), 3))


class DriveLog(DrivingLog):
    """A drive through :func:`_world`, a sweep every ``period`` s: true poses ``truth``, the
    log's own ego poses stretched by ``scale`` with ``jitter`` (m) of noise (None: no ego
    poses); each sweep keeps a random 60 % of the visible points. ``holes``: frame numbers
    whose sweep is empty."""

    dataset, name, sensor = "drive", "d0", "fake-lidar"

    def __init__(self, n=12, speed=6.0, turn=0.15, scale=0.95, jitter=0.04, given=True,
                 holes=(), gap_after=None, period=0.1, seed=0):
        rng = np.random.default_rng(seed)
        self.world = _world(rng)
        self.frames = list(range(n))
        self.times = {f: period * f + (2.0 if gap_after is not None and f > gap_after else 0.0)
                      for f in self.frames}
        self.truth, self.given = {}, {}
        x = y = yaw = 0.0
        for f in self.frames:
            self.truth[f] = _pose(x, y, yaw, 0.05 * math.sin(f))
            gx = scale * x + rng.normal(0, jitter)
            gy = scale * y + rng.normal(0, jitter)
            self.given[f] = _pose(gx, gy, yaw + rng.normal(0, 0.002)) if given else None
            dt = period
            x += speed * dt * math.cos(yaw)
            y += speed * dt * math.sin(yaw)
            yaw += turn * dt
        self.sweeps = {}
        for f in self.frames:
            inv = np.linalg.inv(self.truth[f])
            p = self.world @ inv[:3, :3].T + inv[:3, 3]
            keep = (np.hypot(p[:, 0], p[:, 1]) < 45) & (rng.random(len(p)) < 0.6)
            self.sweeps[f] = (p[keep] if f not in holes else p[:0]).astype(np.float32)

    def timestamp(self, frame):
        return self.times[frame]

    def points(self, frame):
        return self.sweeps[frame]

    def boxes(self, frame):
        # one parked box (the one at x = 23), in the sensor frame of the frame
        centre = np.linalg.inv(self.truth[frame]) @ np.r_[23.0, -5.5, -0.6, 1.0]
        yaw = -0.2 - math.atan2(self.truth[frame][1, 0], self.truth[frame][0, 0])
        return [Box3D(centre=centre[:3], size=np.array([4.4, 1.8, 1.5]), yaw=yaw,
                      category="Car", cls="car", track_id="7")]

    def ego_pose(self, frame):
        return self.given[frame]


def _relative(poses, a, b):
    return np.linalg.inv(poses[a]) @ poses[b]


def _error(m, truth):
    d = np.linalg.inv(truth) @ m
    return (float(np.linalg.norm(d[:3, 3])),
            math.degrees(math.acos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1))))


def test_rigid_fit_recovers_a_known_motion():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(50, 3))
    m = _pose(1.3, -0.4, 0.7, 0.2)
    q = p @ m[:3, :3].T + m[:3, 3]
    np.testing.assert_allclose(rigid_fit(p, q), m, atol=1e-12)


def test_register_recovers_the_motion_between_two_sweeps_from_a_rough_start():
    log = DriveLog(n=3, given=False)
    cfg = OdometryConfig()
    a, b = (registration_cloud(log.points(f), cfg) for f in (0, 2))
    truth = _relative(log.truth, 0, 2)
    T, residual = register(thin(b, cfg.voxel), a, _pose(0.9, 0.2, 0.0), cfg)  # 0.35 m off
    dist, turn = _error(T, truth)
    assert dist < 0.02 and turn < 0.1
    assert residual < 0.03


def test_odometry_undoes_stretched_and_jittered_ego_poses():
    log = DriveLog(n=12)
    odo = lidar_odometry(log)
    assert [p.used for p in odo.pairs] == [True] * 11
    first, last = log.frames[0], log.frames[-1]
    np.testing.assert_allclose(odo.poses[first], log.given[first])  # anchored on the log
    dist, turn = _error(_relative(odo.poses, first, last), _relative(log.truth, first, last))
    given_dist, _ = _error(_relative(log.given, first, last), _relative(log.truth, first, last))
    assert dist < 0.05 and turn < 0.2, (dist, turn)
    assert given_dist > 0.25  # what the stretched poses carried over 6.6 m of travel
    for a, b in zip(log.frames[:-1], log.frames[1:], strict=True):  # each step, not the sum
        d, _ = _error(_relative(odo.poses, a, b), _relative(log.truth, a, b))
        assert d < 0.02
    s = odo.summary()
    assert s["used"] == 11 and s["bridged"] == 0
    assert s["travel_ratio"] == pytest.approx(0.95, abs=0.015)


def test_two_hertz_keyframes_are_registered():
    log = DriveLog(n=5, period=0.5)  # nuScenes-like: 3 m between sweeps
    odo = lidar_odometry(log)
    assert all(p.used for p in odo.pairs)
    dist, turn = _error(_relative(odo.poses, 0, 4), _relative(log.truth, 0, 4))
    assert dist < 0.05 and turn < 0.2


def test_odometry_without_ego_poses_starts_at_the_identity_and_follows_the_drive():
    log = DriveLog(n=8, given=False)
    odo = lidar_odometry(log)
    assert all(p.used for p in odo.pairs)
    np.testing.assert_allclose(odo.poses[0], np.eye(4))
    dist, turn = _error(_relative(odo.poses, 0, 7), _relative(log.truth, 0, 7))
    assert dist < 0.05 and turn < 0.2
    assert all(math.isnan(p.given_m) for p in odo.pairs)


def test_gaps_empty_sweeps_and_disagreements_are_bridged_by_the_logs_own_motion():
    log = DriveLog(n=8, holes=(3,), gap_after=5)
    odo = lidar_odometry(log)
    reasons = {(p.a, p.b): p.reason for p in odo.pairs if not p.used}
    assert reasons == {(2, 3): "too few points", (3, 4): "too few points",
                       (5, 6): "2.10 s apart"}
    for a, b in reasons:  # the log's own relative motion across each bridge
        np.testing.assert_allclose(_relative(odo.poses, a, b), _relative(log.given, a, b),
                                   atol=1e-9)
    strict = lidar_odometry(log, config=OdometryConfig(max_disagreement=1e-3,
                                                       max_disagreement_share=0.0))
    assert not any(p.used for p in strict.pairs)
    assert {p.reason for p in strict.pairs} >= {"disagrees with the ego poses"}
    for f in log.frames:  # nothing trusted: the log's own poses
        np.testing.assert_allclose(strict.poses[f], log.given[f], atol=1e-9)


def test_a_featureless_scene_is_not_trusted():
    log = DriveLog(n=3)
    for f in log.frames:  # an open field: a few scattered returns
        log.sweeps[f] = np.random.default_rng(f).uniform(-30, 30, (150, 3)).astype(np.float32)
    odo = lidar_odometry(log)
    assert [p.reason for p in odo.pairs] == ["too few points"] * 2


def test_tracks_carry_the_odometry_poses():
    log = with_lidar_odometry(DriveLog(n=10))
    tracks = extract_tracks(log, min_points=10)
    assert len(tracks) == 1
    meta = tracks[0].meta
    assert meta["ego_pose_source"] == "lidar"
    egos = np.array(meta["ego_poses"])
    np.testing.assert_allclose(egos, np.stack([log.odometry.poses[f] for f in meta["frames"]]))
    # the parked box in the fixed frame: still within 4 cm by odometry, drifting by the poses
    world = [e @ np.r_[tracks[0].poses[i][:3], 1.0] for i, e in enumerate(egos)]
    given = [log.given[f] @ np.r_[tracks[0].poses[i][:3], 1.0]
             for i, f in enumerate(meta["frames"])]
    spread = lambda w: float(np.ptp(np.array(w)[:, :2], axis=0).max())  # noqa: E731
    assert spread(world) < 0.04 < 0.2 < spread(given)
    plain = extract_tracks(DriveLog(n=10), min_points=10)
    assert plain[0].meta["ego_pose_source"] == "given"


def test_config_is_checked():
    with pytest.raises(ConfigError, match="voxel"):
        OdometryConfig(voxel=0)
    with pytest.raises(ConfigError, match="max_range"):
        OdometryConfig(min_range=50.0)
    with pytest.raises(ConfigError, match="keep"):
        OdometryConfig(keep=1.5)


class DriveDataset(DriveLog):
    """:class:`DriveLog` as a dataset reader (``(root, name)``; one log, ``d0``)."""

    def __init__(self, root, name):
        super().__init__(n=10)
        self.root, self.name = root, name

    @classmethod
    def log_names(cls, root):
        return ["d0"]


def test_seqshape_tracks_ego_poses_lidar(tmp_path, monkeypatch, capsys):
    from seqshape.cli import main
    from seqshape.data import TrackDataset, sequence

    monkeypatch.setitem(sequence.DATASETS, "drive", f"{__name__}:DriveDataset")
    for mode in ("given", "lidar"):
        out = tmp_path / mode
        assert main(["tracks", "--dataset", "drive", "--root", str(tmp_path), "--out", str(out),
                     "--no-reference", "--ego-poses", mode]) == 0
        tr = TrackDataset(out)[0]
        assert tr.meta["ego_pose_source"] == mode
        settings = json.loads((out / "tracks.json").read_text())
        assert settings.get("ego_poses", "given") == mode
        marker = json.loads(next((out / "logs").glob("*.json")).read_text())
        assert ("odometry" in marker) == (mode == "lidar")
    log = DriveDataset(tmp_path, "d0")
    lidar = np.array(TrackDataset(tmp_path / "lidar")[0].meta["ego_poses"])
    given = np.array(TrackDataset(tmp_path / "given")[0].meta["ego_poses"])
    truth = np.stack([log.truth[f] for f in log.frames])
    assert np.abs(given[:, :3, 3] - truth[:, :3, 3]).max() > 0.15
    # the lidar chain starts on the log's first pose: compare motions from there
    rel = np.linalg.inv(lidar[0]) @ lidar[-1]
    assert _error(rel, np.linalg.inv(truth[0]) @ truth[-1])[0] < 0.05
    capsys.readouterr()
    assert main(["tracks", "--dataset", "drive", "--root", str(tmp_path), "--out",
                 str(tmp_path / "lidar"), "--no-reference"]) != 0  # a folder, one setting
    assert "ego_poses: 'lidar' there" in capsys.readouterr().err
