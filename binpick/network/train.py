"""The FPCC training loop: setup, data, model, optimiser, epochs with validation, checkpoints,
early stopping, resume after interruption. Reads top to bottom; no tracking calls inside
(the caller receives each epoch's metrics and the network, in eval mode, through `on_epoch`)."""

from __future__ import annotations

import hashlib
import logging
import math
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from binpick.errors import InputError
from binpick.io.scene import list_scenes, load_scene
from binpick.network.blocks import crop
from binpick.network.checkpoint import InferenceSettings, read_checkpoint, save_checkpoint
from binpick.network.infer import default_device
from binpick.network.loss import fpcc_loss
from binpick.network.model import FPCC, FPCCConfig, input_features
from binpick.params import TrainParams

log = logging.getLogger(__name__)

LAST = "last.pt"
BEST = "best.pt"


@contextmanager
def deterministic_kernels(device: torch.device) -> Iterator[None]:
    """On CUDA, run only deterministic kernels while inside, so that a training run, and a run
    resumed from its `last.pt`, ends with the same weights every time (on an H200 the default
    kernels' atomic adds moved weights by 1e-4 within three epochs). The CPU kernels are
    deterministic already."""
    if device.type != "cuda":
        yield
        return
    # cuBLAS needs a fixed workspace to be deterministic; torch reads this when it makes one.
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    before = torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.benchmark
    torch.use_deterministic_algorithms(True, warn_only=True)  # an op without one warns, never fails
    torch.backends.cudnn.benchmark = False
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(before[0])
        torch.backends.cudnn.benchmark = before[1]


@dataclass(frozen=True)
class Views:
    """Training views of S scenes, each of its own size N_s: points (N_s, 3) float32 metres,
    normals (N_s, 3) float32, labels (N_s,) int64."""

    points: list[np.ndarray]
    normals: list[np.ndarray]
    labels: list[np.ndarray]

    def __len__(self) -> int:
        return len(self.points)

    def scenes(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(points, normals, labels) of each scene."""
        return list(zip(self.points, self.normals, self.labels, strict=False))

    @classmethod
    def of_captures(cls, captures: list) -> Views:
        """The views of labelled captures (binpick.io.labelled_capture): their cleaned points,
        as the network sees a capture, with their labels (ignored points: negative)."""
        return cls(
            [c.points_m for c in captures], [c.normals for c in captures], [c.labels.astype(np.int64) for c in captures]
        )

    def __add__(self, other: Views) -> Views:
        return Views(self.points + other.points, self.normals + other.normals, self.labels + other.labels)

    def fingerprint(self) -> str:
        """A hash of the content: a checkpoint resumes only on the data it was trained on."""
        h = hashlib.sha256()
        for arrays in (self.points, self.normals, self.labels):
            for a in arrays:
                h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()


def load_views(folder: Path) -> Views:
    """The network's views of every scene in a split folder of the generate stage."""
    scenes = [load_scene(p) for p in list_scenes(folder)]
    if not scenes:
        raise InputError(folder, "holds no scene_*.npz files (run the generate stage first)")
    # A scene where no part is seen (none could be placed, or none is in view) has nothing to learn from.
    seen = [s for s in scenes if len(s.view_points_m)]
    if not seen:
        raise InputError(
            folder,
            "no scene shows the part (does it fit the bin, generate.bin, and the camera's view, camera.distance_m?)",
        )
    if len(seen) < len(scenes):
        log.warning("%s: %d of %d scenes show no part and are left out", folder, len(scenes) - len(seen), len(scenes))
    scenes = seen
    return Views(
        points=[s.view_points_m for s in scenes],
        normals=[s.view_normals for s in scenes],
        labels=[s.view_labels.astype(np.int64) for s in scenes],
    )


def _batch(
    views: Views, idx: np.ndarray, n_points: int, rng: np.random.Generator, augment: bool, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A crop of n_points from each view, rotated about the camera axis at random (augment), as tensors."""
    P, Nn, L = [], [], []
    for s in idx:
        pick = crop(views.points[s], n_points, rng)
        p, n = views.points[s][pick].astype(np.float64), views.normals[s][pick].astype(np.float64)
        if augment:
            a = rng.uniform(0, 2 * np.pi)
            R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
            c = p.mean(axis=0)
            p, n = (p - c) @ R.T + c, n @ R.T
        P.append(p)
        Nn.append(n)
        L.append(views.labels[s][pick])
    as_t = lambda a, dt: torch.as_tensor(np.stack(a), dtype=dt, device=device)  # noqa: E731
    return as_t(P, torch.float32), as_t(Nn, torch.float32), as_t(L, torch.int64)


def _loss(model: FPCC, points, normals, labels, params: TrainParams, d_max_m: float, gen: torch.Generator):
    emb, ctr, fg = model(input_features(points, normals, params.features, d_max_m), points)
    return fpcc_loss(
        emb,
        ctr,
        points,
        labels,
        d_max_m,
        params.eps1,
        params.eps2,
        params.centre_loss_weight,
        params.centre_score_form,
        params.loss_anchors,
        gen,
        fg,
    )


def train_fpcc(
    train: Views,
    val: Views,
    params: TrainParams,
    d_max_m: float,
    seed: int,
    checkpoint_dir: str | Path,
    part: str,
    part_diameter_m: float,
    on_epoch: Callable[[int, dict[str, float], FPCC], None] | None = None,
    device: torch.device | None = None,
    progress: bool = True,
    init_state: dict | None = None,
) -> tuple[FPCC, dict[str, float]]:
    """Train, keeping `last.pt` (resume point) and `best.pt` (lowest validation loss) in checkpoint_dir.

    Returns the best network and its metrics. A `last.pt` written with the same config, settings,
    seed and data resumes. The checkpoints hold the inference settings of the part (no calibrated
    clustering yet). init_state: a checkpoint's entries (read_checkpoint) to fine-tune: its
    network and weights are the start instead of fresh ones.
    """
    device = device or default_device()
    checkpoint_dir = Path(checkpoint_dir)
    checkpoint_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    if init_state is None:
        config = FPCCConfig(
            backbone=params.backbone,
            k_neighbours=params.k_neighbours,
            width=params.width,
            embedding_dim=params.embedding_dim,
            foreground_head=True,
        )
    else:
        config = FPCCConfig(**init_state["config"])
    model = FPCC(config).to(device)
    if init_state is not None:
        model.load_state_dict(init_state["model"])
    optimiser = torch.optim.Adam(model.parameters(), lr=params.learning_rate, weight_decay=params.weight_decay)
    settings = InferenceSettings(
        part=part, part_diameter_m=part_diameter_m, features=params.features, d_max_m=d_max_m, train=params
    )
    extra = {
        **settings.to_extra(),
        "seed": seed,
        "data_fingerprint": train.fingerprint() + val.fingerprint(),
        **({"finetuned_from": init_state.get("sha256", "")} if init_state is not None else {}),
    }

    start_epoch, best_val, best_epoch = 0, math.inf, -1
    last = checkpoint_dir / LAST
    state = None
    if last.is_file():
        try:
            state = read_checkpoint(last, device)
        except InputError as exc:
            # A damaged resume point must not block training: start again, and say why.
            log.warning("%s; starting this training from scratch", exc)
            last.unlink()
    if state is not None:
        same_run = all(
            state["extra"].get(k) == extra.get(k)
            for k in ("train_params", "seed", "data_fingerprint", "d_max_m", "finetuned_from")
        )
        if state["config"] == config.to_dict() and same_run:
            model.load_state_dict(state["model"])
            optimiser.load_state_dict(state["optimiser"])
            start_epoch = state["epoch"] + 1
            best_val, best_epoch = state["metrics"]["best_val_loss"], state["metrics"]["best_epoch"]
            log.info("resuming from %s at epoch %d", last, start_epoch)
        else:
            log.info("ignoring %s: it was written with other settings or data", last)

    steps = max(1, len(train) // params.batch_size)
    metrics: dict[str, float] = {}
    epochs_run = start_epoch
    bar = tqdm(
        range(start_epoch, params.epochs),
        desc="train",
        unit="epoch",
        disable=not progress,
        initial=start_epoch,
        total=params.epochs,
    )
    with deterministic_kernels(device):
        for epoch in bar:
            # Every epoch draws from its own seed, so a resumed run sees the same batches.
            rng = np.random.default_rng([seed, epoch])
            gen = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
            model.train()
            order = rng.permutation(len(train))
            sums: dict[str, float] = {}
            for step in range(steps):
                batch = _batch(
                    train,
                    order[step * params.batch_size : (step + 1) * params.batch_size],
                    params.n_points,
                    rng,
                    True,
                    device,
                )
                loss, parts = _loss(model, *batch, params, d_max_m, gen)
                optimiser.zero_grad()
                loss.backward()
                optimiser.step()
                for k, v in parts.items():
                    sums[k] = sums.get(k, 0.0) + v / steps

            model.eval()
            val_sums: dict[str, float] = {}
            with torch.no_grad():
                val_rng = np.random.default_rng([seed, 10**9])  # the same validation draw every epoch
                for start in range(0, len(val), params.batch_size):
                    idx = np.arange(start, min(start + params.batch_size, len(val)))
                    _, parts = _loss(
                        model,
                        *_batch(val, idx, params.n_points, val_rng, False, device),
                        params,
                        d_max_m,
                        torch.Generator().manual_seed(seed),
                    )
                    for k, v in parts.items():
                        val_sums[k] = val_sums.get(k, 0.0) + v * len(idx) / len(val)

            epochs_run = epoch + 1
            val_loss = val_sums["loss"]
            if val_loss < best_val:
                best_val, best_epoch = val_loss, epoch
            metrics = {
                **{f"train_{k}": v for k, v in sums.items()},
                **{f"val_{k}": v for k, v in val_sums.items()},
                "best_val_loss": best_val,
                "best_epoch": best_epoch,
            }
            if best_epoch == epoch:
                save_checkpoint(checkpoint_dir / BEST, model, None, epoch, metrics, extra)
            save_checkpoint(last, model, optimiser, epoch, metrics, extra)
            bar.set_postfix(loss=f"{sums['loss']:.3f}", val=f"{val_loss:.3f}")
            if on_epoch is not None:
                on_epoch(epoch, metrics, model)
            if epoch - best_epoch >= params.patience_epochs:
                log.info(
                    "early stop at epoch %d: no validation improvement for %d epochs", epoch, params.patience_epochs
                )
                break

    best_state = read_checkpoint(checkpoint_dir / BEST, device)
    model.load_state_dict(best_state["model"])
    model.eval()
    return model, {**best_state["metrics"], "epochs_run": float(epochs_run)}


def finetune_fpcc(
    init_state: dict,
    train: Views,
    val: Views,
    params: TrainParams,
    epochs: int,
    learning_rate: float,
    seed: int,
    checkpoint_dir: str | Path,
    device: torch.device | None = None,
    progress: bool = True,
) -> Path:
    """Fine-tune the network of a checkpoint's entries (read_checkpoint) for `epochs` at
    `learning_rate` on train (synthetic views plus labelled captures, whose ignored points add
    nothing to the loss), keeping the lowest validation loss on val. Returns the path of that
    best checkpoint in checkpoint_dir (its clustering not yet calibrated: write_finetuned)."""
    extra = init_state["extra"]
    tuned = params.model_copy(update={"epochs": epochs, "learning_rate": learning_rate, "patience_epochs": epochs})
    train_fpcc(
        train,
        val,
        tuned,
        float(extra["d_max_m"]),
        seed,
        checkpoint_dir,
        str(extra["part"]),
        float(extra["part_diameter_m"]),
        device=device,
        progress=progress,
        init_state=init_state,
    )
    return Path(checkpoint_dir) / BEST
