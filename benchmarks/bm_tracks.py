"""Throughput of real-track extraction (``seqshape tracks``) per dataset format, and where the
time goes per box.

Run: python benchmarks/bm_tracks.py --av2 ../shared/realdata/av2/sensor/val
         --kitti ../shared/realdata/kitti-tracking/training --kitti-sequence 0000
         [--nuscenes ROOT] [--workers 2] [--min-points 10] [--repeats 3]

Without ``--nuscenes``, the nuScenes row runs on the fixture that ``tests/_nuscenes_fixture.py``
writes (when that file exists), and says so. Each dataset: one untimed warm-up run, then
``--repeats`` timed runs; the table gives the median and, for the per-box lines, ms per box.

* ``open logs``: the readers' constructors (label/annotation tables, calibration).
* ``read sweeps``: ``log.points`` of every frame with a vehicle box (file reading alone).
* ``extract_tracks``: the whole crop of a fresh log (read + crop + ground), in-process.
* ``accumulated reference``: ``accumulated_reference`` of every extracted track.
* ``seqshape tracks``: the command end to end (``--workers``, reference on, writing the
  files) into a fresh folder; its parallelism is over logs, so one log uses one core.
* per box: the box crop alone (``ground="none"``), the local ground fit alone
  (``local_ground``; how many boxes it fails on), the full ``crop_vehicle`` (box crop + local
  plane, the sweep plane fitted once per sweep where needed, as ``extract_tracks`` does), the
  same on the sweep pre-sliced by a sorted-x index (a proposed change of ``extract_tracks``;
  the output is checked identical; the sort, once per sweep, is included), and per sweep the
  whole-sweep plane (``ground_plane``, the fallback when the local fit has too few points).
"""

from __future__ import annotations

import importlib.util
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _bench import bench_parser, print_table, time_it

from seqshape.data.crop import CropConfig, crop_vehicle, local_ground
from seqshape.data.extract import extract_tracks
from seqshape.data.ground import ground_plane
from seqshape.data.reference import accumulated_reference
from seqshape.data.sequence import VEHICLE_CLASSES, log_names, open_log
from seqshape.data.tracks_export import TracksConfig, extract_dataset

ROOT = Path(__file__).resolve().parents[1]


def nuscenes_fixture(tmp: Path) -> Path | None:
    """Write the test fixture of ``tests/_nuscenes_fixture.py`` into ``tmp``; its root."""
    path = ROOT / "tests" / "_nuscenes_fixture.py"
    if not path.is_file():
        return None
    spec = importlib.util.spec_from_file_location("_nuscenes_fixture", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["_nuscenes_fixture"] = mod
    spec.loader.exec_module(mod)
    for name in ("write_nuscenes", "write_fixture", "make_fixture", "write_dataset"):
        fn = getattr(mod, name, None)
        if callable(fn):
            out = fn(tmp / "nuscenes")
            return Path(out) if isinstance(out, (str, Path)) else tmp / "nuscenes"
    raise SystemExit(f"{path}: no writer function found (write_nuscenes/write_fixture ...)")


def _logs(dataset, root, names):
    return [open_log(dataset, root, n) for n in (names or log_names(dataset, root))]


class _Sliced:
    """A sweep with an index sorted by x: the points near a box without a pass over all."""

    def __init__(self, sweep: np.ndarray):
        self.sweep = sweep
        self.order = np.argsort(sweep[:, 0], kind="stable")
        self.xs = sweep[self.order, 0]

    def near(self, box, reach_extra: float) -> np.ndarray:
        """The sweep's points with ``|x - box x| <= reach``, in their original order."""
        reach = float(np.hypot(box.size[0] / 2, box.size[1] / 2)) + reach_extra + 1e-3
        lo, hi = np.searchsorted(self.xs, [box.centre[0] - reach, box.centre[0] + reach])
        return self.sweep[np.sort(self.order[lo:hi])]


def _per_box(logs, repeats):
    """Per-box costs (ms): crop only, local ground only, crop_vehicle, crop_vehicle on a
    pre-sliced sweep; per sweep: the sweep plane; and how often the local fit fails."""
    cases = []
    for log in logs:
        for f in log.frames:
            boxes = log.vehicle_boxes(f)
            if boxes:
                cases.append((log.points(f), boxes))
    n_boxes = sum(len(b) for _, b in cases)
    none, plane = CropConfig(ground="none"), CropConfig()
    reach = max(plane.margin, plane.context)

    def crop_only():
        for sweep, boxes in cases:
            for b in boxes:
                crop_vehicle(sweep, b.pose, b.size, none)

    def ground_only():
        return [local_ground(sweep, b.pose, b.size, plane) for sweep, boxes in cases
                for b in boxes]

    def full():  # as extract_tracks does it: the sweep plane fitted once per sweep, if needed
        out = []
        for sweep, boxes in cases:
            cache = []

            def fallback(s=sweep, c=cache):
                if not c:
                    c.append(ground_plane(s[:, :3]))
                return c[0]
            out += [crop_vehicle(sweep, b.pose, b.size, plane, sweep_plane=fallback)
                    for b in boxes]
        return out

    def sliced():  # the proposed change of extract_tracks: identical output
        out = []
        for sweep, boxes in cases:
            cache, index = [], _Sliced(sweep)

            def fallback(s=sweep, c=cache):
                if not c:
                    c.append(ground_plane(s[:, :3]))
                return c[0]
            out += [crop_vehicle(index.near(b, reach), b.pose, b.size, plane,
                                 sweep_plane=fallback) for b in boxes]
        return out

    def sweep_plane():
        for sweep, _ in cases:
            ground_plane(sweep[:, :3])

    times = [time_it(fn, repeats) for fn in (crop_only, ground_only, full, sliced)]
    for a, b in zip(times[2].result, times[3].result, strict=True):
        np.testing.assert_array_equal(a, b)  # the pre-sliced crop changes nothing
    ms = [t.median * 1e3 / n_boxes for t in times]
    ms.append(time_it(sweep_plane, repeats).median * 1e3 / max(len(cases), 1))
    n_fail = sum(p is None for p in times[1].result)
    return n_boxes, len(cases), n_fail, ms


def bench_dataset(label, dataset, root, names, repeats, workers, min_points):
    logs = _logs(dataset, root, names)
    n_frames = sum(len(log.frames) for log in logs)
    box_frames = [(log, f) for log in logs for f in log.frames if log.vehicle_boxes(f)]

    def read():
        for log, f in box_frames:
            log.points(f)

    def extract():
        return [t for n in (names or log_names(dataset, root))
                for t in extract_tracks(open_log(dataset, root, n), min_points=min_points)]

    t_open = time_it(lambda: _logs(dataset, root, names), repeats)
    t_read = time_it(read, repeats)
    t_extract = time_it(extract, repeats)
    tracks = t_extract.result

    def reference():
        for tr in tracks:
            try:
                accumulated_reference(tr)
            except ValueError:
                pass

    t_ref = time_it(reference, repeats)
    config = TracksConfig(dataset, str(Path(root).resolve()), VEHICLE_CLASSES,
                          min_points=min_points)
    runs = []
    for _ in range(repeats + 1):  # the first is the warm-up
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            s = extract_dataset(config, tmp, names, workers=workers)
            runs.append(time.perf_counter() - t0)
    t_cmd = sorted(runs[1:])[len(runs[1:]) // 2]
    n_tracks = len(tracks)
    n_boxes, n_sweeps, n_fail, per_box = _per_box(logs, repeats)
    what = f"{len(logs)} log(s), {n_frames} frames, {n_tracks} tracks"
    rows = [
        (label, "open logs (constructors)", f"{t_open.median:.3f}", "", "", ""),
        (label, f"read sweeps ({len(box_frames)})", f"{t_read.median:.3f}",
         f"{len(box_frames) / t_read.median:.1f}", "", ""),
        (label, f"extract_tracks ({what})", f"{t_extract.median:.3f}",
         f"{n_frames / t_extract.median:.1f}", f"{n_tracks / t_extract.median:.1f}", ""),
        (label, "accumulated reference", f"{t_ref.median:.3f}", "",
         f"{n_tracks / t_ref.median:.1f}", ""),
        (label, f"seqshape tracks --workers {workers}", f"{t_cmd:.3f}",
         f"{n_frames / t_cmd:.1f}", f"{sum(len(m['tracks']) for m in s.markers) / t_cmd:.1f}",
         ""),
        (label, f"box crop alone ({n_boxes} boxes)", "", "", "", f"{per_box[0]:.3f}"),
        (label, f"local ground fit alone (fails on {n_fail})", "", "", "", f"{per_box[1]:.3f}"),
        (label, "crop_vehicle (crop + local plane)", "", "", "", f"{per_box[2]:.3f}"),
        (label, "crop_vehicle, sweep pre-sliced by x", "", "", "", f"{per_box[3]:.3f}"),
        (label, f"sweep ground_plane (per sweep, {n_sweeps})", "", "", "",
         f"{per_box[4]:.3f}"),
    ]
    return rows


def main():
    ap = bench_parser(__doc__, repeats=3)
    ap.add_argument("--av2", metavar="ROOT", help="Argoverse 2 split folder (e.g. sensor/val)")
    ap.add_argument("--av2-sequence", action="append", help="AV2 log id(s) (default all)")
    ap.add_argument("--kitti", metavar="ROOT", help="KITTI tracking training/ folder")
    ap.add_argument("--kitti-sequence", action="append",
                    help="KITTI sequence(s) (default all; the shared copy has 0000 only)")
    ap.add_argument("--nuscenes", metavar="ROOT", help="nuScenes root (default: test fixture)")
    ap.add_argument("--nuscenes-sequence", action="append", help="scene name(s)")
    ap.add_argument("--workers", type=int, default=2, help="workers of the command (default 2)")
    ap.add_argument("--min-points", type=int, default=10,
                    help="--min-points of the extraction (default 10, as the command)")
    args = ap.parse_args()
    logging.getLogger("seqshape").setLevel(logging.ERROR)  # per-track reference warnings
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        jobs = []
        if args.av2:
            jobs.append(("av2", "av2", args.av2, args.av2_sequence))
        if args.kitti:
            jobs.append(("kitti", "kitti", args.kitti, args.kitti_sequence))
        if args.nuscenes:
            jobs.append(("nuscenes", "nuscenes", args.nuscenes, args.nuscenes_sequence))
        else:
            fixture = nuscenes_fixture(Path(tmp))
            if fixture is not None:
                jobs.append(("nuscenes (test fixture)", "nuscenes", fixture,
                             args.nuscenes_sequence))
        if not jobs:
            raise SystemExit("give at least one of --av2, --kitti, --nuscenes")
        for label, dataset, root, names in jobs:
            rows += bench_dataset(label, dataset, root, names, args.repeats, args.workers,
                                  args.min_points)
    print_table(("dataset", "stage", "median s", "frames/s", "tracks/s", "ms per box"), rows,
                align="llrrrr")


if __name__ == "__main__":
    main()
