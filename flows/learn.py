"""`binpick learn`: the cell teaches its own networks.

The `label` stage turns every capture's trusted poses into a labelled capture
(data/real/<part>/<capture>.npz, DVC-versioned like the synthetic scenes). Before any of them is
learnt from, a person looks at it (`binpick learn review`: a rerun recording of the labels and
the poses they came from) and approves or rejects it; the verdicts live in
data/real/<part>/reviewed.json (in git), tied to the labelled file's SHA-256, so that a capture
labelled again is reviewed again.

`binpick learn finetune` (and the scheduled retraining, once learn.min_new_scenes reviewed
captures are new) fine-tunes the served network on the part's synthetic training scenes plus the
approved captures, holding back learn.heldout_share of the captures. It then scores the served
and the new network on the held-back captures (on their labelled points) and on the synthetic
test scenes; only when the new one loses at most learn.max_drop of precision and recall on both
does it become data/fpcc/<part>/served.pt, registered in MLflow as fpcc-<part> with the alias
learn.serve_alias. The service serves served.pt while it was fine-tuned from the part's current
model.pt; a retrained model.pt (the `train` stage) supersedes it. The batch stages keep using
model.pt, so that `dvc repro` stays reproducible.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from binpick.errors import BinpickError, InputError
from binpick.io.atomic import atomic_path
from binpick.io.digest import file_sha256
from binpick.io.labelled_capture import LabelledCapture, list_labelled_captures, load_labelled_capture
from binpick.io.review_record import load_review_record, save_review_record
from binpick.labels import IGNORE
from binpick.layout import Layout
from binpick.params import Params

log = logging.getLogger(__name__)

REVIEWED = "reviewed.json"
REVIEW_RECORDING = "review.rrd"


def load_reviewed(folder: Path) -> dict[str, dict]:
    """capture -> {"sha256": of the labelled file reviewed, "approved": bool}."""
    return load_review_record(folder / REVIEWED)


def approved_captures(folder: Path) -> list[Path]:
    """The labelled captures a person approved as they are now (same SHA-256), sorted by name."""
    reviewed = load_reviewed(folder)
    return [
        p
        for p in list_labelled_captures(folder)
        if reviewed.get(p.stem, {}).get("approved") and reviewed[p.stem]["sha256"] == file_sha256(p)
    ]


def pending_captures(folder: Path) -> list[Path]:
    """Labelled captures nobody has reviewed as they are now."""
    reviewed = load_reviewed(folder)
    return [p for p in list_labelled_captures(folder) if reviewed.get(p.stem, {}).get("sha256") != file_sha256(p)]


@dataclass
class Review:
    recording: Path | None = None
    pending: list[str] = field(default_factory=list)
    approved: list[str] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)


def review(root: Path, part: str, approve: bool = False, reject: list[str] | None = None) -> Review:
    """Without approve: write a rerun recording of the pending labelled captures of `part` to
    data/work/<part>/review.rrd. With approve: record every pending capture as approved, except
    those named in reject (recorded as rejected)."""
    folder = Layout(root).real(part)
    if not folder.is_dir():
        raise BinpickError(
            f"part {part!r} has no labelled captures: run the pipeline on its captures first (`binpick repro`)"
        )
    pending = pending_captures(folder)
    names = [p.stem for p in pending]
    unknown = sorted(set(reject or []) - set(names))
    if unknown:
        raise BinpickError(
            f"--reject {unknown[0]!r}: no pending labelled capture of {part} has that name (pending: "
            f"{', '.join(names) or 'none'})"
        )
    if not approve:
        if not pending:
            return Review()
        out = Layout(root).work(part) / REVIEW_RECORDING
        write_review_recording(
            out, part, _part_model(root, part), [(p.stem, load_labelled_capture(p)) for p in pending]
        )
        return Review(recording=out, pending=names)
    reviewed = load_reviewed(folder)
    result = Review()
    for p in pending:
        ok = p.stem not in (reject or [])
        reviewed[p.stem] = {"sha256": file_sha256(p), "approved": ok}
        (result.approved if ok else result.rejected).append(p.stem)
    save_review_record(folder / REVIEWED, reviewed)
    return result


def _part_model(root: Path, part: str):
    from binpick.io.part_model import load_part_model

    return load_part_model(Layout(root).part_model(part))


def write_review_recording(path: Path, part: str, part_model, captures: list[tuple[str, LabelledCapture]]) -> None:
    """A rerun recording (to a file, never a viewer): one time step per capture, its points
    coloured by the instance they were labelled with (ignored points grey) and the part's mesh
    at each trusted pose, in the camera frame."""
    import rerun as rr

    from binpick.palette import instance_colours, instance_rgb

    path.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("binpick", recording_id=f"review-{part}")
    with atomic_path(path) as tmp:
        rec.save(str(tmp))
        rec.log("camera", rr.ViewCoordinates.RDF, static=True)
        for step, (name, c) in enumerate(captures):
            rec.set_time("capture", sequence=step)
            n = len(c.T_cam_from_model)
            palette = instance_colours(max(n, 1))
            rec.log(
                "camera/labels",
                rr.Points3D(
                    c.points_m, colors=instance_rgb(c.labels), radii=0.001, class_ids=c.labels.astype(np.int32)
                ),
            )
            rec.log("camera/parts", rr.Clear(recursive=True))
            for k, T in enumerate(c.T_cam_from_model):
                vertices = part_model.mesh_vertices_m @ T[:3, :3].T + T[:3, 3]
                rec.log(
                    f"camera/parts/{k}",
                    rr.Mesh3D(
                        vertex_positions=vertices,
                        triangle_indices=part_model.mesh_faces,
                        albedo_factor=np.append(palette[k % len(palette)], 90).astype(np.uint8),
                    ),
                )
            labelled = float(np.mean(c.labels != IGNORE)) if len(c.labels) else 0.0
            rec.log(
                "capture",
                rr.TextDocument(
                    f"{name}: {n} trusted poses (scores {', '.join(f'{s:.2f}' for s in c.scores)}), "
                    f"{100 * labelled:.0f}% of {len(c.labels)} points labelled within "
                    f"{1000 * float(c.near_m):.1f} mm, the rest ignored (grey)"
                ),
            )
        rec.flush()
        rec.disconnect()


def served_checkpoint(root: Path, part: str) -> Path | None:
    """The network the service serves for `part`: data/fpcc/<part>/served.pt when it was
    fine-tuned from the current model.pt, else model.pt; None when the part has no network."""
    from binpick.network.checkpoint import read_checkpoint

    base, served = Layout(root).checkpoint(part), Layout(root).served_checkpoint(part)
    if not base.is_file():
        return None
    if served.is_file():
        try:
            if read_checkpoint(served)["extra"].get("finetuned_from") == read_checkpoint(base).get("sha256"):
                return served
        except InputError as exc:
            log.warning("%s; serving %s", exc, base)
            return base
        log.info("%s was fine-tuned from an earlier %s: serving the newer %s", served, base.name, base)
    return base


def heldout(name: str, share: float) -> bool:
    """Whether a capture is held back from fine-tuning: by a hash of its name, so that it stays
    on the same side as captures are added."""
    return int(hashlib.sha256(name.encode()).hexdigest()[:8], 16) / 0xFFFFFFFF < share


def no_worse(before: dict[str, float], after: dict[str, float], max_drop: float) -> bool:
    """Whether the new network (after) loses at most max_drop of precision and of recall against
    the served one (before) on the held-back captures and on the synthetic test scenes."""
    return all(
        after[f"{s}_{m}"] >= before[f"{s}_{m}"] - max_drop
        for s in ("real", "synthetic")
        for m in ("precision", "recall")
    )


def finetune(root: Path, params: Params, part: str, force: bool = False, progress: bool = True) -> dict[str, object]:
    """Fine-tune the part's served network when enough approved captures are new (or force);
    serve the result only when it is no worse. params: resolved for the part. Returns what was
    measured and decided."""
    from binpick.network.calibrate import recalibrate
    from binpick.network.checkpoint import read_checkpoint, write_finetuned
    from binpick.network.infer import default_device
    from binpick.network.train import BEST, Views, finetune_fpcc, load_views
    from binpick.seeding import derive_int

    lp = params.learn
    current = served_checkpoint(root, part)
    if current is None:
        raise BinpickError(f"part {part!r} has no trained network to fine-tune (run `binpick repro` first)")
    state = read_checkpoint(current)
    # Captures the served network learnt from or was judged by are not new.
    learnt = set(state["extra"].get("real_scenes", []))
    seen = learnt | set(state["extra"].get("real_heldout", []))
    approved = approved_captures(Layout(root).real(part))
    new = [p.stem for p in approved if p.stem not in seen]
    outcome: dict[str, object] = {
        "part": part,
        "served_before": current.name,
        "approved": len(approved),
        "new": len(new),
    }
    if len(new) < lp.min_new_scenes and not force:
        log.info(
            "%s: %d approved captures are new, fine-tuning waits for %d (learn.min_new_scenes)",
            part,
            len(new),
            lp.min_new_scenes,
        )
        return {**outcome, "finetuned": False, "served": False}
    test = [p for p in approved if heldout(p.stem, lp.heldout_share)]
    train = [p for p in approved if not heldout(p.stem, lp.heldout_share)]
    if not test or not train:
        raise BinpickError(
            f"{part}: {len(approved)} approved captures give {len(train)} to learn from and {len(test)} to judge by; "
            "both need at least one (approve more captures)"
        )
    layout = Layout(root)
    scenes = layout.scenes(part)
    synthetic_train, synthetic_val = load_views(scenes / "train"), load_views(scenes / "val")
    real = Views.of_captures([load_labelled_capture(p) for p in train])
    work = layout.work(part) / "finetune"
    log.info(
        "%s: fine-tuning %s on %d synthetic + %d real scenes, judging on %d held-back captures",
        part,
        current.name,
        len(synthetic_train),
        len(real),
        len(test),
    )
    best = finetune_fpcc(
        state,
        synthetic_train + real,
        synthetic_val,
        params.train,
        lp.finetune_epochs,
        lp.finetune_learning_rate,
        derive_int(params.seed, "finetune", part),
        work,
        default_device(),
        progress,
    )
    candidate = work / "candidate.pt"
    # The model.pt this line descends from: the served one's base (served_checkpoint checked it), or itself.
    base_sha = state["extra"]["finetuned_from"] if current == layout.served_checkpoint(part) else state["sha256"]
    write_finetuned(
        best,
        candidate,
        state,
        base_sha,
        sorted(learnt | {p.stem for p in train}),
        sorted((seen - learnt) | {p.stem for p in test}),
    )
    # The clustering's cuts are chosen for the network they cut: the fine-tuned one's, again.
    recalibrate(
        candidate,
        candidate,
        synthetic_val,
        params.segment,
        params.evaluate.iou_threshold,
        np.random.default_rng(derive_int(params.seed, "calibrate-finetuned", part)),
    )
    before = score(current, params, scenes / "test", test)
    after = score(candidate, params, scenes / "test", test)
    serve = no_worse(before, after, lp.max_drop)
    outcome.update(
        {
            "finetuned": True,
            "served": serve,
            "n_train_real": len(real),
            "n_heldout_real": len(test),
            **{f"before_{k}": v for k, v in before.items()},
            **{f"after_{k}": v for k, v in after.items()},
        }
    )
    if serve:
        served = layout.served_checkpoint(part)
        with atomic_path(served) as tmp:
            shutil.copyfile(candidate, tmp)
        outcome["version"] = _register(params, part, served, outcome)
    for name in ("last.pt", BEST):
        (work / name).unlink(missing_ok=True)
    return outcome


def score(checkpoint: Path, params: Params, synthetic_test: Path, real_test: list[Path]) -> dict[str, float]:
    """Precision and recall of the network on the held-back captures (their labelled points
    alone: ignored points count for neither side) and on the synthetic test scenes."""
    from binpick.io.scene import list_scenes, load_scene
    from binpick.metrics.segmentation import SegmentationCounts
    from binpick.network.evaluate import capture_counts, scene_seed, segment_and_count
    from binpick.network.infer import load_segmenter

    segmenter = load_segmenter(checkpoint, params.segment)
    iou = params.evaluate.iou_threshold
    real = SegmentationCounts()
    for i, path in enumerate(real_test):
        rng = np.random.default_rng(scene_seed(params.seed, f"real-{path.stem}", i))
        real = real.add(capture_counts(segmenter, load_labelled_capture(path), params.segment, iou, rng))
    synthetic = SegmentationCounts()
    for i, path in enumerate(list_scenes(synthetic_test)):
        _, counts = segment_and_count(segmenter, load_scene(path), params.segment, iou, params.seed, i)
        synthetic = synthetic.add(counts)
    r, s = real.summary(), synthetic.summary()
    return {
        "real_precision": r["precision"],
        "real_recall": r["recall"],
        "synthetic_precision": s["precision"],
        "synthetic_recall": s["recall"],
    }


def _register(params: Params, part: str, served: Path, outcome: dict[str, object]) -> str:
    """An MLflow run of the fine-tuning, its network registered as a version of fpcc-<part> with
    the serve alias."""
    from review.tracking import accept_checkpoint, add_model_version, mlflow_run

    with mlflow_run(
        f"part-{part}", f"finetune-{part}", params.tracking.mlflow_uri, {"binpick.step": "finetune"}
    ) as run:
        import mlflow

        mlflow.log_metrics(
            {k: float(v) for k, v in outcome.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        )
        mlflow.log_artifact(str(served), artifact_path="model")
        add_model_version(part, served, run, f"finetune@{part}")
        version = accept_checkpoint(part, served, params.learn.serve_alias)
    log.info(
        "%s: the fine-tuned network is served (fpcc-%s version %s, alias %r)",
        part,
        part,
        version,
        params.learn.serve_alias,
    )
    return str(version)
