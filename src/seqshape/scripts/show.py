"""``seqshape show``: a PNG overview and an offline interactive HTML 3D view of one track.

The files are named after the track id stored in the dataset, made file-name safe
(:func:`seqshape._io.safe_stem`: ``../x`` becomes ``_x``) and checked to stay inside ``--out``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from seqshape._io import contained_path, safe_stem
from seqshape.data import TrackDataset
from seqshape.errors import ConfigError
from seqshape.viz import plot_track_png, track_html

HELP = "plot one track (PNG) and an interactive 3D view (HTML)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DIR", help="track dataset folder (with manifest.json)")
    parser.add_argument("--track", required=True, metavar="ID",
                        help="track id (see manifest.json), or its index in the dataset")
    parser.add_argument("--out", required=True, metavar="DIR2", help="folder for the outputs")
    parser.add_argument("--no-html", action="store_true", help="write the PNG only")


def run(args: argparse.Namespace) -> int:
    ds = TrackDataset(args.dataset)
    try:
        track = ds.get(args.track)
    except KeyError:
        if not args.track.lstrip("-").isdigit() or not -len(ds) <= int(args.track) < len(ds):
            some = ", ".join(ds.track_ids[:5])
            raise ConfigError(f"{args.dataset}: no track {args.track!r} among {len(ds)} tracks "
                              f"(ids look like: {some}, ...)") from None
        track = ds[int(args.track)]
    out = Path(args.out)
    stem = safe_stem(track.track_id)
    png = plot_track_png(track, contained_path(out, f"{stem}.png"))
    print(f"wrote {png}")
    if not args.no_html:
        html = track_html(track, contained_path(out, f"{stem}.html"))
        print(f"wrote {html} (offline, open in a browser)")
    return 0
