"""Sensor-gap benchmark: what training on one camera model costs on another, and what the
randomised sensor models and fine-tuning on the cell's own captures win back.

Per part, networks are trained on synthetic bins (in memory, the project's train section, at the
sizes given), cluttered as the test bins are, rendered with:
- `today`: the camera section's camera and generate.noise (what the project trained on before
  the sensor models);
- `randomised`: a preset drawn per scene from every sensor model in generate.sensor.models,
  its baseline scaled and its projector turned about the optical axis at random
  (RANDOMISED_BASELINE_SCALE);
- `without_<preset>`: every preset but that one (leave-one-out).
Each is tested on cluttered bins (bench clutter's distractors and camera tilts up to 45 degrees)
rendered with every preset and with today's camera, through the real scene path. Keys per
`<train>@<test>` pair: pose_precision, pose_recall, pose_recall_measured, false_poses_outside_bin
(as bench clutter),
pick_success_rate (the first pick of each capture judged as bench picking judges it: the right
part touched, the gripper's path free of the other parts and the bin; a capture without a pick
counts as a failure unless it shows no part at least half visible, n_pick_captures the captures
judged), seg_precision, seg_recall (the network's instances on the scene's view).

Fine-tuning (`finetune`): the `today` network segments captures of sensor B (bench clutter bins
rendered with that preset), its poses verified with margin label them (binpick.learning), it is
fine-tuned on its synthetic scenes plus those captures (binpick learn's recipe) and tested again on
the B test bins and today's; `gap_closed_<key>` is the share of the gap between today@B and
randomised@B (a network that saw B) that fine-tuning closed; `served` (1 or 0) whether the cell's
gate (flows.learn.no_worse, learn.max_drop) would serve it: its segmentation no worse on the B
test bins and on today's, judged here on their true labels (the cell judges held-back captures
by their own labels).

All figures are on our renderer with our sensor models: the effects those models leave out
(docs/guide/captures.md, "Training for your sensor") are not measured here.
"""

from __future__ import annotations

import logging
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from binpick.cell.bin_box import BinBox
from binpick.errors import BinpickError
from binpick.generation.bin import bin_meshes
from binpick.generation.scene import generate_scene
from binpick.geometry.transforms import transform_points
from binpick.io.part_model import PartModel
from binpick.io.scene import SyntheticScene
from binpick.learning import label_capture
from binpick.metrics.segmentation import SegmentationCounts
from binpick.network.calibrate import recalibrate
from binpick.network.checkpoint import read_checkpoint, write_finetuned
from binpick.network.evaluate import segment_and_count
from binpick.network.train import BEST, Views, finetune_fpcc, train_fpcc
from binpick.params import ImportCaptureParams, Params
from binpick.scene.process import PartModels, chosen_verification, process
from binpick.scene.register import with_verification
from binpick.seeding import SceneSeeds, derive_int, derive_seed
from binpick.view import ViewParams
from flows.bench import machine
from flows.bench.clutter import CLUTTER, TILT_DEG_MAX, _score, _summary, drawn_bin, scaled_settings
from flows.bench.picking import TrueSurface, _nearest_surface, _path_hits, _true_touch, bench_models, touch_m
from flows.learn import no_worse

log = logging.getLogger(__name__)

TODAY = "today"
RANDOMISED = "randomised"
BIN_SAMPLE_SPACING_M = 0.004
# The randomised networks' training scenes also draw each preset's baseline and the projector's
# side: a sensor the network never saw differs in both. Structured-light and stereo sensors for
# bins put their projector or second camera 0.05-0.55 m from the camera (Kinect v1 0.075 m,
# PhoXi M 0.35 m, PhoXi L 0.55 m), and a cell may mount one turned about its axis. Scaling the
# presets' 0.075-0.15 m by 0.5-3 spans 0.04-0.45 m: it reaches PhoXi M's baseline, so the
# leave-one-out figure for it measures a sensor inside these ranges, not beyond them.
RANDOMISED_BASELINE_SCALE = (0.5, 3.0)
RANDOMISED_PROJECTOR_ANGLE_DEG = (0.0, 360.0)


def _generate(p: Params, presets: list[str], clutter: bool, randomise_mount: bool = False):
    """generate params for these presets ([] = today's camera), cluttered or not; randomise_mount:
    draw the baseline and the projector's side as the randomised networks' training does."""
    g = p.generate
    mount = (
        {"baseline_scale": RANDOMISED_BASELINE_SCALE, "projector_angle_deg": RANDOMISED_PROJECTOR_ANGLE_DEG}
        if randomise_mount
        else {}
    )
    return g.model_copy(
        update={
            "sensor": g.sensor.model_copy(update={"presets": list(presets), **mount}),
            "clutter": g.clutter.model_copy(update={**CLUTTER, "camera_tilt_deg_max": TILT_DEG_MAX})
            if clutter
            else g.clutter.off(),
        }
    )


def _scene_seed(seed: int, part: str, tag: str, index: int) -> np.random.SeedSequence:
    return derive_seed(seed, "bench-sensors", part, tag, index)


def _render(
    part: PartModel,
    p: Params,
    presets: list[str],
    clutter: bool,
    tag: str,
    n: int,
    seed: int,
    randomise_mount: bool = False,
) -> list[tuple[SyntheticScene, np.random.SeedSequence]]:
    g = _generate(p, presets, clutter, randomise_mount)
    view = ViewParams.of_import(p.import_capture)
    out = []
    for i in range(n):
        s = _scene_seed(seed, part.name, tag, i)
        out.append((generate_scene(part, g, p.camera, view, s), s))
    return out


def _views(scenes: list[tuple[SyntheticScene, np.random.SeedSequence]]) -> Views:
    seen = [s for s, _ in scenes if len(s.view_points_m)]
    return Views(
        [s.view_points_m for s in seen], [s.view_normals for s in seen], [s.view_labels.astype(np.int64) for s in seen]
    )


def _train(
    part: PartModel, p: Params, presets: list[str], n_train: int, n_val: int, seed: int, work: Path, tag: str
) -> tuple[Path, Views, Views]:
    """A network trained on n_train scenes of these presets ([] = today's camera; presets draw
    the mount too: RANDOMISED_BASELINE_SCALE), clustering calibrated on n_val: its checkpoint,
    its training views and its validation views. The scenes are cluttered as the test bins are
    (distractors, bin sizes, camera tilts), as a project's training scenes are (generate.clutter):
    the sensor is then the one thing a network has not seen. Trained on plain bins, a network
    had never seen a distractor: the ring screw's randomised network, on 12 PhoXi-class bins, kept
    3 wrong poses of 35 (two on distractors); trained on cluttered bins, none of 33."""
    mount = bool(presets)
    train = _views(_render(part, p, presets, True, f"{tag}-train", n_train, seed, mount))
    val = _views(_render(part, p, presets, True, f"{tag}-val", n_val, seed, mount))
    folder = work / tag
    d_max = p.train.d_max_m if p.train.d_max_m is not None else part.diameter_m / 2.0
    log.info("%s: training %s on %d scenes", part.name, tag, len(train))
    train_fpcc(
        train,
        val,
        p.train,
        d_max,
        derive_int(seed, "bench-sensors-train", part.name, tag),
        folder,
        part.name,
        part.diameter_m,
        progress=False,
    )
    out = folder / "model.pt"
    recalibrate(
        folder / BEST,
        out,
        val,
        p.segment,
        p.evaluate.iou_threshold,
        np.random.default_rng(derive_int(seed, "calibrate", part.name, tag)),
    )
    return out, train, val


def _with_network(models: PartModels, p: Params, checkpoint: Path) -> PartModels:
    """The part's models (PPF model and grasps built once) with this network segmenting."""
    from binpick.network.infer import load_segmenter

    segmenter = load_segmenter(checkpoint, p.segment)
    return replace(
        models,
        segmenter=segmenter,
        register_params=with_verification(p.registration, chosen_verification(None, segmenter)),
    )


def _test(
    part: PartModel,
    p: Params,
    base: PartModels,
    checkpoint: Path,
    scenes: list[tuple[SyntheticScene, np.random.SeedSequence]],
    truth: TrueSurface,
    seed: int,
    bin_box: str = "none",
    pair: str = "",
) -> dict[str, float]:
    """The keys of one train/test pair over its test scenes; bin_box: the box each capture is
    cropped to (BIN_BOXES); pair: its name in the log (`train@test`)."""
    models = _with_network(base, p, checkpoint)
    assert models.segmenter is not None
    ppf = models.ppf
    rows: list[dict[str, float]] = []
    seg = SegmentationCounts()
    good = judged = boxed = 0
    for k, (scene, s) in enumerate(scenes):
        # The bin generate_scene drew (sensor presets draw from a stream of their own).
        drawn, _ = drawn_bin(p.model_copy(update={"generate": _generate(p, [], True)}), part, s)
        H, W = scene.labels.shape
        box = _cell_box(bin_box, scene, drawn, p, part, seed)
        boxed += int(box is not None)
        try:
            result = process(
                scene.xyz_m.reshape(-1, 3),
                None,
                (H, W),
                _cropped(models, box),
                SceneSeeds.of(seed, f"sensors-{part.name}-{k}"),
            )
            poses, plan = result.registration.poses, result.picks
        except BinpickError as exc:
            log.warning("%s %s test scene %d: %s", part.name, pair, k, exc)
            poses, plan = [], None
        rows.append(_score(poses, scene, ppf, part, drawn.inner_x_m, drawn.inner_y_m))
        seg = seg.add(segment_and_count(models.segmenter, scene, p.segment, p.evaluate.iou_threshold, seed, k)[1])
        sent = plan is not None and bool(plan.picks)
        judged += int(judges_the_pick(sent, rows[-1]["n_pickable"]))
        if not sent and rows[-1]["n_pickable"] > 0:
            log.info(
                "%s %s test scene %d: no pick sent, %d parts at least half in view (%d posed; refused: %s)",
                part.name,
                pair,
                k,
                rows[-1]["n_pickable"],
                len(poses),
                "; ".join(sorted({reason for _, reason in plan.unpicked})) if plan is not None else "no plan",
            )
        if plan is not None and plan.picks:
            first = plan.picks[0]
            target = _true_touch(first, p.pick.gripper, scene.T_cam_from_model, truth)
            bins = np.concatenate([_surface(m) for m in bin_meshes(drawn)])
            if target is None:
                distance_m, angle_deg = _nearest_surface(first.T_cam_from_grasp, scene.T_cam_from_model, truth)
                log.info(
                    "%s %s test scene %d: the first pick touches no part as a grasp should (%.1f mm from the nearest "
                    "true surface, %.0f degrees off its normal)",
                    part.name,
                    pair,
                    k,
                    1000 * distance_m,
                    angle_deg,
                )
            elif _path_hits(
                first,
                p.pick.gripper,
                p,
                target,
                scene.T_cam_from_model,
                part.points_m,
                transform_points(scene.T_cam_from_bin, bins),
            ):
                log.info("%s %s test scene %d: the first pick's path hits another part or the bin", part.name, pair, k)
            else:
                good += 1
    summary = seg.summary()
    return {
        **_summary(rows),
        "pick_success_rate": good / judged if judged else 0.0,
        "n_pick_captures": float(judged),
        "n_bin_boxes": float(boxed),
        "seg_precision": summary["precision"],
        "seg_recall": summary["recall"],
    }


# The bin box a test capture is cropped to: none (the cleaning alone finds the bin), the one
# `binpick fit-bin` fits from the capture (where it would not refuse it), or the bin as drawn (a
# cell whose box was set and checked by hand).
BIN_BOXES = ("none", "fitted", "given")


def _cell_box(mode: str, scene: SyntheticScene, drawn, p: Params, part: PartModel, seed: int) -> BinBox | None:
    """The bin box of a test capture under `mode` (BIN_BOXES), camera frame; None: no box."""
    if mode == "fitted":
        return fit_bin_box_of(scene.xyz_m.reshape(-1, 3), p.import_capture, part.diameter_m, seed)
    if mode == "given":
        # Parts heaped over the rim are still the bin's: the crop reaches a part's size above it.
        return BinBox.of_generated(drawn, scene.T_cam_from_bin, headroom_m=part.diameter_m)
    return None


def _cropped(models: PartModels, box: BinBox | None) -> PartModels:
    """The models with their import cropping to the box (unchanged without one)."""
    if box is None:
        return models
    return replace(models, import_params=models.import_params.model_copy(update=box.as_import_settings()))


def fit_bin_box_of(
    xyz_m: np.ndarray, settings: ImportCaptureParams, part_diameter_m: float, seed: int
) -> BinBox | None:
    """The bin box `binpick fit-bin` fits from a capture (n, 3; NaN: no return), as a cell keeps
    it once it is set up (README, "Your own part and camera", step 3), or None where fit-bin would
    refuse it (no plane, nothing on it, implausible for the part)."""
    from binpick.cell.bin_fit import fit_capture_bin, implausible, valid_points

    points = xyz_m[valid_points(xyz_m, settings.min_range_m)]
    try:
        box = fit_capture_bin(points, settings, seed)
    except ValueError as exc:
        log.warning("no bin box fitted: %s", exc)
        return None
    problems = implausible(box, part_diameter_m, points)
    if problems:
        log.warning("the fitted bin box is refused: %s", "; ".join(problems))
        return None
    return box


def _gate_scores(real: dict[str, float], synthetic: dict[str, float]) -> dict[str, float]:
    """A pair's segmentation figures under the names the serving gate (flows.learn.no_worse) reads."""
    return {
        "real_precision": real["seg_precision"],
        "real_recall": real["seg_recall"],
        "synthetic_precision": synthetic["seg_precision"],
        "synthetic_recall": synthetic["seg_recall"],
    }


def judges_the_pick(sent: bool, n_pickable: float) -> bool:
    """Whether a capture counts for pick_success_rate: a pick was sent (judged right or wrong), or
    none was where the capture shows a part at least half visible (a failure). A bin whose parts
    the camera does not see (a lone part under a distractor, or in a projector's shadow) has
    nothing to pick: sending no pick there is right, not a failure."""
    return sent or n_pickable > 0


def _surface(mesh) -> np.ndarray:
    import trimesh

    return trimesh.sample.sample_surface_even(mesh, max(100, int(mesh.area / BIN_SAMPLE_SPACING_M**2)), seed=0)[0]


def _finetuned(
    part: PartModel,
    p: Params,
    built: PartModels,
    base: Path,
    synthetic_train: Views,
    synthetic_val: Views,
    captures: list[tuple[SyntheticScene, np.random.SeedSequence]],
    seed: int,
    work: Path,
    bin_box: str = "none",
) -> tuple[Path, dict[str, float]]:
    """The base network fine-tuned on its synthetic training views plus the captures it labelled
    itself, kept at its best on the validation views and recalibrated on them (binpick learn's
    recipe); bin_box: the box each capture is processed cropped to (BIN_BOXES)."""
    models = _with_network(built, p, base)
    labelled = []
    n_trusted = 0
    for k, (scene, s) in enumerate(captures):
        H, W = scene.labels.shape
        # The cell knows its bin: the box generate_scene drew.
        drawn, _ = drawn_bin(p.model_copy(update={"generate": _generate(p, [], True)}), part, s)
        box = BinBox.of_generated(drawn, scene.T_cam_from_bin)
        try:
            result = process(
                scene.xyz_m.reshape(-1, 3),
                None,
                (H, W),
                _cropped(models, _cell_box(bin_box, scene, drawn, p, part, seed)),
                SceneSeeds.of(seed, f"sensors-capture-{part.name}-{k}"),
            )
        except BinpickError as exc:
            log.warning("%s capture %d: %s", part.name, k, exc)
            continue
        c = label_capture(
            result.cloud,
            result.registration.poses,
            models.ppf.dense_points_m,
            part.diameter_m,
            p.registration.min_score,
            p.learn.trust_margin,
            p.import_capture.voxel_size_m,
            box,
        )
        if len(c.T_cam_from_model):
            labelled.append(c)
            n_trusted += len(c.T_cam_from_model)
    state = read_checkpoint(base)
    folder = work / "finetune"
    best = finetune_fpcc(
        state,
        synthetic_train + Views.of_captures(labelled),
        synthetic_val,
        p.train,
        p.learn.finetune_epochs,
        p.learn.finetune_learning_rate,
        derive_int(seed, "bench-sensors-finetune", part.name),
        folder,
        progress=False,
    )
    out = folder / "model.pt"
    write_finetuned(best, out, state, state["sha256"], [f"capture-{k}" for k in range(len(labelled))], [])
    recalibrate(
        out,
        out,
        synthetic_val,
        p.segment,
        p.evaluate.iou_threshold,
        np.random.default_rng(derive_int(seed, "calibrate-finetuned", part.name)),
    )
    return out, {
        "n_captures": float(len(captures)),
        "n_labelled_captures": float(len(labelled)),
        "n_trusted_poses": float(n_trusted),
    }


def bench_sensors(
    settings: Params,
    names: list[str],
    n_train: int,
    n_val: int,
    n_test: int,
    n_captures: int,
    finetune_sensor: str,
    leave_one_out: bool = True,
    seed: int = 0,
    trust_margin: float | None = None,
    bin_box: str = "none",
    part_settings: dict[str, Params] | None = None,
) -> dict[str, object]:
    """settings: the project's params (its train section sizes the networks, its bin and camera
    are scaled to each part as bench clutter scales them); n_train, n_val: synthetic scenes per
    network; n_test: cluttered test bins per test sensor; n_captures: captures of
    finetune_sensor the cell labels itself; trust_margin: instead of learn.trust_margin; bin_box:
    the box every capture is cropped to (BIN_BOXES); part_settings: the params resolved for a part
    the project lists (its entry's overrides: its gripper), used for that part."""
    from flows.bench.parts import bench_parts

    if bin_box not in BIN_BOXES:
        raise ValueError(f"--bin-box {bin_box!r} is not one of {', '.join(BIN_BOXES)}")

    def with_margin(p: Params) -> Params:
        if trust_margin is None:
            return p
        return p.model_copy(update={"learn": p.learn.model_copy(update={"trust_margin": trust_margin})})

    settings = with_margin(settings)

    out: dict[str, object] = {
        "machine": machine(),
        "n_train": n_train,
        "n_val": n_val,
        "n_test": n_test,
        "n_captures": n_captures,
        "tilt_deg_max": TILT_DEG_MAX,
        "renderer_only": True,
        "trust_margin": settings.learn.trust_margin,
        "bin_box": bin_box,
        "parts": {},
    }
    presets = sorted(settings.generate.sensor.models)
    if finetune_sensor not in presets:
        raise ValueError(f"--finetune-sensor {finetune_sensor!r} is not a sensor model (have: {', '.join(presets)})")
    for part in bench_parts(names, n_points=settings.ingest.n_surface_points):
        name = part.name
        p = scaled_settings(with_margin((part_settings or {}).get(name, settings)), part, TILT_DEG_MAX)
        truth = TrueSurface(part, p.pick.suction.cup_radius_m, touch_m(p.pick, p.pick.gripper))
        built = bench_models(part, p, None)
        tests = {
            TODAY: _render(part, p, [], True, "test-today", n_test, seed),
            **{q: _render(part, p, [q], True, f"test-{q}", n_test, seed) for q in presets},
        }
        pairs: dict[str, dict[str, float]] = {}
        with tempfile.TemporaryDirectory(prefix="binpick-sensors-") as tmp:
            work = Path(tmp)
            today, today_train, today_val = _train(part, p, [], n_train, n_val, seed, work, TODAY)
            randomised, _, _ = _train(part, p, presets, n_train, n_val, seed, work, RANDOMISED)
            for train_name, checkpoint in ((TODAY, today), (RANDOMISED, randomised)):
                for test_name, scenes in tests.items():
                    pairs[f"{train_name}@{test_name}"] = _test(
                        part, p, built, checkpoint, scenes, truth, seed, bin_box, f"{train_name}@{test_name}"
                    )
                    log.info(
                        "%s %s@%s: %s",
                        name,
                        train_name,
                        test_name,
                        {k: round(v, 3) for k, v in pairs[f"{train_name}@{test_name}"].items()},
                    )
            if leave_one_out:
                for q in presets:
                    without, _, _ = _train(
                        part, p, [x for x in presets if x != q], n_train, n_val, seed, work, f"without_{q}"
                    )
                    pairs[f"without_{q}@{q}"] = _test(
                        part, p, built, without, tests[q], truth, seed, bin_box, f"without_{q}@{q}"
                    )
                    log.info(
                        "%s without_%s@%s: %s",
                        name,
                        q,
                        q,
                        {k: round(v, 3) for k, v in pairs[f"without_{q}@{q}"].items()},
                    )
            captures = _render(part, p, [finetune_sensor], True, f"captures-{finetune_sensor}", n_captures, seed)
            tuned, labelling = _finetuned(part, p, built, today, today_train, today_val, captures, seed, work, bin_box)
            finetune: dict[str, object] = {
                "base": TODAY,
                "sensor": finetune_sensor,
                **labelling,
                "after@" + finetune_sensor: _test(
                    part, p, built, tuned, tests[finetune_sensor], truth, seed, bin_box, f"finetuned@{finetune_sensor}"
                ),
                "after@" + TODAY: _test(
                    part, p, built, tuned, tests[TODAY], truth, seed, bin_box, f"finetuned@{TODAY}"
                ),
            }
        before, after, reference = (
            pairs[f"{TODAY}@{finetune_sensor}"],
            finetune["after@" + finetune_sensor],
            pairs[f"{RANDOMISED}@{finetune_sensor}"],
        )
        synthetic_before, synthetic_after = pairs[f"{TODAY}@{TODAY}"], finetune["after@" + TODAY]
        assert isinstance(after, dict) and isinstance(synthetic_after, dict)
        for key in ("pose_precision", "pose_recall", "pick_success_rate", "seg_precision", "seg_recall"):
            gap = reference[key] - before[key]
            finetune[f"gap_closed_{key}"] = (after[key] - before[key]) / gap if gap > 0 else None
            finetune[f"synthetic_change_{key}"] = synthetic_after[key] - synthetic_before[key]
        finetune["served"] = float(
            no_worse(_gate_scores(before, synthetic_before), _gate_scores(after, synthetic_after), p.learn.max_drop)
        )
        loo = {q: pairs[f"without_{q}@{q}"] for q in presets if f"without_{q}@{q}" in pairs}
        out["parts"][name] = {  # type: ignore[index]
            "pairs": pairs,
            "finetune": finetune,
            "presets": presets,
            # The target: a preset never seen against the same preset seen in training.
            "leave_one_out_gap": {
                q: {
                    k: pairs[f"{RANDOMISED}@{q}"][k] - v[k]
                    for k in ("pose_precision", "pose_recall", "pick_success_rate")
                }
                for q, v in loo.items()
            },
        }
    return out
