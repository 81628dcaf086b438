"""The amodal-labelling step of ``seqshape demo``: the whole chain on a kitti-tiny scene.

:func:`amodal_demo_step` generates a small scene (``seqshape scenes --preset kitti-tiny``, with
the 2D instance masks degraded as that command does by default: what sc-seg segments the LiDAR
with is a segmenter's imperfect output, not the exact visible masks) unless one is there,
labels it with gt-accumulation and, when estimator weights load, sc-gt and sc-seg, scores each
against the exact amodal ground truth and draws overlays of a few frames. It returns a
:class:`DemoStepResult` the demo report embeds (markdown, the mask table, image paths); the
report says which 2D masks sc-seg used.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from seqshape.amodal.evaluate import evaluate_files, markdown_table, summarise
from seqshape.amodal.labeler import LabelConfig, label_log, write_labels, write_overlays
from seqshape.data.kitti import KittiTrackingSequence
from seqshape.demo.report import Section
from seqshape.errors import SeqshapeError
from seqshape.model.estimator import Estimator
from seqshape.sim.degrade import DegradeConfig
from seqshape.sim.scene_writer import generate_scenes, scene_config

log = logging.getLogger(__name__)

TITLE = "Automatic amodal mask labels"


@dataclass
class DemoStepResult:
    """What the demo report shows: a title, markdown, overlay PNGs and the metrics; ``table``
    is the mask table alone (markdown), for the terminal."""

    title: str
    markdown: str
    images: list[Path] = field(default_factory=list)
    metrics: dict = field(default_factory=dict)
    table: str = ""


def masks_note(degrade: DegradeConfig) -> str:
    """One sentence naming the 2D masks sc-seg segmented the LiDAR with.

    >>> masks_note(DegradeConfig()).startswith("sc-seg used degraded 2D instance masks")
    True
    """
    if degrade.is_identity:
        return ("sc-seg used the exact visible 2D masks (no degradation): an upper bound, not "
                "what a real segmenter gives.")
    lo, hi = degrade.jitter_px
    parts = [f"outlines moved by {lo:g}-{hi:g} px"] if hi > 0 else []
    if degrade.dilate_px:
        parts.append(f"{'dilated' if degrade.dilate_px > 0 else 'eroded'} by "
                     f"{abs(degrade.dilate_px)} px")
    parts += [f"{100 * rate:g} % of {what} instances missed" for rate, what in
              ((degrade.miss_rate_small, "small"), (degrade.miss_rate, "larger")) if rate > 0]
    if degrade.false_rate > 0:
        parts.append(f"{degrade.false_rate:g} false instances per true one")
    return (f"sc-seg used degraded 2D instance masks (`instances_2d/`, as `seqshape scenes` "
            f"writes them by default: {', '.join(parts)}), as a decent instance segmenter "
            f"would give them; gt-accumulation and sc-gt use the 3D boxes, not 2D masks.")


def amodal_demo_step(work_dir, checkpoint: str | None = "pretrained", seed: int = 0,
                     overlay_frames: int = 3, estimator=None,
                     degrade: DegradeConfig | None = None,
                     frames: int | None = None) -> DemoStepResult:
    """Run the labelling chain in ``work_dir`` (created); see the module doc.

    ``estimator``: an already loaded Estimator (else ``checkpoint`` is loaded; when that
    fails the sc-* modes are skipped and the report says why). ``degrade``: the 2D mask
    degradation of the scene (None: ``DegradeConfig()``, the default of ``seqshape scenes``;
    :data:`seqshape.sim.degrade.NO_DEGRADE` for the exact masks). ``frames``: frames of the
    scene (None: the preset's 20).
    """
    work = Path(work_dir)
    scenes = work / "scenes"
    degrade = DegradeConfig() if degrade is None else degrade
    generate_scenes(scenes, scene_config("kitti-tiny", frames=None if frames is None
                                         else (frames, frames)),
                    seed=seed, workers=1, degrade=degrade)
    sequence = KittiTrackingSequence.sequences(scenes)[0]
    seq = KittiTrackingSequence(scenes, sequence)
    note = ""
    if estimator is None:
        try:
            estimator = Estimator.load("pretrained" if checkpoint is None else checkpoint,
                                       backend="auto-float")
        except SeqshapeError as exc:
            note = f"sc-gt and sc-seg skipped: no estimator weights ({exc})."
            log.warning("%s", note)
    modes = ["gt-accumulation"] + (["sc-gt", "sc-seg"] if estimator is not None else [])
    rows, images = {}, []
    shown = seq.frames[:: max(1, len(seq.frames) // overlay_frames)][:overlay_frames]
    for mode in modes:
        result = label_log(seq, LabelConfig(mode=mode), estimator=estimator)
        path = work / "labels" / f"{mode}_{sequence}.json"
        write_labels(path, result)
        rows[mode] = summarise(*evaluate_files([(path, scenes / "amodal" / f"{sequence}.json")]))
        rows[mode]["frames_per_s"] = result.timings["frames"] / max(result.timings["total"], 1e-9)
        images += write_overlays(seq, result, work / "overlays" / mode, frames=shown)
    table = markdown_table(rows, title="Amodal mask labels vs exact ground truth")
    md = (f"Scene: kitti-tiny, sequence {sequence}, {len(seq.frames)} frames, labelled with "
          f"{', '.join(modes)} and scored against the exact amodal ground truth.\n\n" + table
          + ("\n" + masks_note(degrade) + "\n" if "sc-seg" in modes else "")
          + ("\n" + note + "\n" if note else ""))
    return DemoStepResult(TITLE, md, images, rows, table)


def step_amodal(ctx) -> None:
    """``seqshape demo`` step: :func:`amodal_demo_step` in ``DIR/amodal``, added as a Section.

    Uses the demo's loaded sequential estimator (``ctx.estimators["sequential"]``) when there
    is one.
    """
    work = ctx.out / "amodal"
    res = amodal_demo_step(work, checkpoint=getattr(ctx.args, "checkpoint", "pretrained"),
                           seed=getattr(ctx.args, "seed", 0),
                           estimator=ctx.estimators.get("sequential"))
    ctx.state["amodal"] = res.metrics
    ctx.state["amodal_table"] = res.table
    images = [(f"{p.parent.name}: frame {p.stem.split('_')[-1]}",
               str(p.relative_to(ctx.out))) for p in res.images]
    ctx.sections.append(Section(res.title, res.markdown, images=images))
