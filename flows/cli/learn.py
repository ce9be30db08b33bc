"""`binpick learn ...` (labelled captures reviewed, networks fine-tuned on them) and the network
tools `calibrate` and `eval-labels`."""

from __future__ import annotations

from pathlib import Path

import typer

from binpick.env import project_root
from binpick.errors import BinpickError
from flows.cli.common import PARAMS, app, fail, learn_app, log, trained_part_paths


@learn_app.command("review")
def learn_review_cmd(
    part: str = typer.Option(..., help="the part whose labelled captures to review"),
    approve: bool = typer.Option(
        False, "--approve", help="approve every pending labelled capture (except --reject ones)"
    ),
    reject: list[str] = typer.Option(None, help="a pending capture whose labels are wrong (with --approve)"),
) -> None:
    """Show the labelled captures nobody has reviewed (a rerun recording), then approve them,
    rejecting wrong ones: only approved captures are learnt from."""
    import sys

    from flows.learn import review

    if reject and not approve:
        fail("--reject goes with --approve (look first: run without either)")
    root = project_root()
    result = review(root, part, approve, list(reject or []))
    if approve:
        typer.echo(
            f"{part}: approved {len(result.approved)}, rejected {len(result.rejected)}"
            + (f" ({', '.join(result.rejected)})" if result.rejected else "")
            + "; recorded in data/real/"
            + f"{part}/reviewed.json"
        )
    elif result.recording is None:
        typer.echo(f"{part}: no labelled capture is waiting for review")
    else:
        typer.echo(
            f"{part}: {len(result.pending)} labelled captures to review ({', '.join(result.pending)}). Look at them "
            "with\n"
            f"  {Path(sys.executable).parent / 'rerun'} {result.recording.relative_to(root)}\n"
            f"then `binpick learn review --part {part} --approve [--reject CAPTURE ...]`"
        )


@learn_app.command("finetune")
def learn_finetune_cmd(
    part: str = typer.Option(..., help="the part whose network to fine-tune"),
    force: bool = typer.Option(
        False, "--force", help="fine-tune even if fewer than learn.min_new_scenes approved captures are new"
    ),
    params: Path = PARAMS,
) -> None:
    """Fine-tune the part's served network on its synthetic scenes plus the approved captures;
    serve the result (MLflow alias learn.serve_alias) only when it is no worse on held-back
    captures and on the synthetic test scenes."""
    from binpick.params import load_params
    from flows.learn import finetune

    root = project_root()
    result = finetune(root, load_params(params, part), part, force)
    if not result["finetuned"]:
        typer.echo(
            f"{part}: {result['new']} of {result['approved']} approved captures are new; not fine-tuned (see "
            "learn.min_new_scenes, or --force)"
        )
        return
    figures = ", ".join(
        f"{k}: {result[f'before_{k}']:.2f} -> {result[f'after_{k}']:.2f}"
        for k in ("real_precision", "real_recall", "synthetic_precision", "synthetic_recall")
    )
    typer.echo(
        f"{part}: fine-tuned on {result['n_train_real']} captures, judged on {result['n_heldout_real']}: {figures}; "
        + (f"served (version {result['version']})" if result["served"] else "worse, not served")
    )


@app.command()
def calibrate(
    out: Path = typer.Option(..., help="checkpoint to write (.pt)"),
    part: str = typer.Option("t_joint", help="the part (its params entry, checkpoint and scenes)"),
    checkpoint: Path = typer.Option(None, help="trained checkpoint; default: data/fpcc/<part>/model.pt"),
    scenes: Path = typer.Option(None, help="data set folder with a val/ split; default: data/scenes/<part>"),
    params: Path = PARAMS,
) -> None:
    """Choose a trained network's clustering settings again on the validation scenes, as the train
    stage does (for a network trained elsewhere, or after a change of segment settings); writes a
    copy of the checkpoint that holds them."""
    import numpy as np

    from binpick.network.calibrate import recalibrate
    from binpick.network.checkpoint import read_checkpoint
    from binpick.network.train import load_views
    from binpick.params import load_params
    from binpick.seeding import derive_seed

    checkpoint, scenes = trained_part_paths(part, checkpoint, scenes)
    try:
        p = load_params(params, part)
        read_checkpoint(checkpoint)  # a damaged checkpoint is named before the scenes are read
        views = load_views(scenes / "val")
        chosen = recalibrate(
            checkpoint,
            out,
            views,
            p.segment,
            p.evaluate.iou_threshold,
            np.random.default_rng(derive_seed(p.seed, "calibrate", part)),
        )
    except (BinpickError, ValueError, OSError) as exc:
        fail(str(exc))
    log.info(
        "%s: %s on %d validation scenes -> %s",
        part,
        ", ".join(f"{k} {v:.3g}" for k, v in chosen.items()),
        len(views),
        out,
    )


@app.command("eval-labels")
def eval_labels(
    pred: Path = typer.Option(..., help="labelled scene to evaluate (text)"),
    gt: Path = typer.Option(..., help="ground-truth labelled scene (text)"),
    pred_columns: str = typer.Option("x,y,z,label", help="e.g. x,y,z,label or x,y,z,score,label"),
    gt_columns: str = typer.Option("x,y,z,label"),
    unit: str = typer.Option("m", help="unit of both files' coordinates"),
    match_distance_m: float = typer.Option(0.001, help="a predicted point labels the ground-truth point this close"),
    iou: float = typer.Option(0.5, help="IoU threshold of a match"),
) -> None:
    """Evaluate a foreign tool's labelled scene against ground truth with this project's metrics."""
    import json

    from binpick.io.labelled import load_labelled, transfer_labels
    from binpick.metrics.segmentation import scene_counts

    if not 0.0 < iou <= 1.0:
        fail(f"--iou {iou:g} must lie in (0, 1]")
    if not match_distance_m >= 0.0:
        fail(f"--match-distance-m {match_distance_m:g} must not be negative")
    p = load_labelled(pred, tuple(c.strip() for c in pred_columns.split(",")), unit)
    g = load_labelled(gt, tuple(c.strip() for c in gt_columns.split(",")), unit)
    labels = transfer_labels(p.points_m, p.labels, g.points_m, match_distance_m)
    typer.echo(json.dumps(scene_counts(labels, g.labels, iou).summary(), indent=1, sort_keys=True))
