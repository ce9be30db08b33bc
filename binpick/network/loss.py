"""FPCC losses: attention-weighted hinge embedding loss and smooth-L1 centre-score loss.

Pairs are formed between a random subset of anchor points and all points, which keeps the cost
at anchors x N instead of N x N while every point still gets gradient as a pair member.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from binpick.labels import NOT_A_PART

# The foreground term's weight beside the embedding term (both are about 1 at the start).
FOREGROUND_LOSS_WEIGHT = 1.0


def centre_score_targets(points: torch.Tensor, labels: torch.Tensor, d_max_m: float, form: str) -> torch.Tensor:
    """Ground-truth centre score of each point, (N,) in [0, 1].

    points (N, 3) metres; labels (N,) int64 instance indices (>= 0; a negative label, not a
    part or a point the loss ignores, gets 0). The centre of an instance is the mean of its
    points. linear: 1 - r / d_max; squared (reference code): 1 - (r / d_max)^2.
    """
    known = labels >= 0
    own = labels.clamp_min(0)
    n_inst = int(labels.max()) + 1 if bool(known.any()) else 1
    sums = torch.zeros(n_inst, 3, dtype=points.dtype, device=points.device).index_add_(0, own[known], points[known])
    counts = torch.bincount(own[known], minlength=n_inst).clamp_min(1).to(points.dtype)
    centres = sums / counts[:, None]
    ratio = (points - centres[own]).norm(dim=1) / d_max_m
    if form == "squared":
        ratio = ratio**2
    elif form != "linear":
        raise ValueError(f"unknown centre score form {form!r}")
    return torch.where(known, (1.0 - ratio).clamp(0.0, 1.0), torch.zeros_like(ratio))


def fpcc_loss(
    embedding: torch.Tensor,
    centre: torch.Tensor,
    points: torch.Tensor,
    labels: torch.Tensor,
    d_max_m: float,
    eps1: float,
    eps2: float,
    centre_weight: float,
    form: str,
    n_anchors: int,
    generator: torch.Generator | None = None,
    foreground_logit: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Loss of one batch.

    embedding (B, N, D), centre (B, N) predicted; points (B, N, 3) metres; labels (B, N) int64:
    an instance (>= 0), NOT_A_PART (a rendered distractor or rim the cleaning left: its centre
    score is taught 0 and its embedding is pushed from the parts' near it) or below (a point the
    loss ignores, a captured scene's unexplained points: input, not target). Pairs farther apart
    than 2 * d_max (a true, not a squared, distance) are ignored. foreground_logit (B, N), when
    given: the foreground head's output, taught part (>= 0) against NOT_A_PART with the two
    classes weighted alike (points of no part are a few per cent of a training view); a view with
    ignored points teaches it only when it holds points of both classes.
    """
    B, N, _ = embedding.shape
    emb_terms, ctr_terms, fg_terms = [], [], []
    for b in range(B):
        target = centre_score_targets(points[b], labels[b], d_max_m, form)
        known = labels[b] >= NOT_A_PART
        index = torch.nonzero(known).squeeze(1)  # every point of a synthetic scene
        if not len(index):  # nothing to learn from in this crop: no gradient, no term
            ctr_terms.append(centre[b].sum() * 0.0)
            emb_terms.append(embedding[b].sum() * 0.0)
            continue
        ctr_terms.append(F.smooth_l1_loss(centre[b, index], target[index]))
        is_part = labels[b, index] >= 0
        # A view with ignored points (a captured scene) may know only its parts: a term of one
        # class there would teach "everything is a part". It teaches the head when it knows both.
        partial = bool((labels[b] < NOT_A_PART).any()) and (bool(is_part.all()) or not bool(is_part.any()))
        if foreground_logit is not None and not partial:
            bce = F.binary_cross_entropy_with_logits(
                foreground_logit[b, index], is_part.to(foreground_logit.dtype), reduction="none"
            )
            fg_terms.append(torch.stack([bce[m].mean() for m in (is_part, ~is_part) if bool(m.any())]).mean())
        anchors = index[
            torch.randperm(len(index), generator=generator, device="cpu")[: min(n_anchors, len(index))].to(index.device)
        ]
        valid = (torch.cdist(points[b, anchors], points[b]) <= 2.0 * d_max_m) & known[None, :]  # (m, N)
        attention = (target[anchors, None] + target[None, :]).clamp(max=1.0)  # (m, N)
        same = labels[b, anchors, None] == labels[b][None, :]
        d_f = torch.cdist(embedding[b, anchors], embedding[b])  # (m, N)
        hinge = torch.where(same, F.relu(d_f - eps1), F.relu(eps2 - d_f))
        w = valid.to(hinge.dtype) * attention
        emb_terms.append((w * hinge).sum() / w.sum().clamp_min(1.0))
    emb = torch.stack(emb_terms).mean()
    ctr = torch.stack(ctr_terms).mean()
    total = emb + centre_weight * ctr
    parts = {"embedding_loss": emb.item(), "centre_loss": ctr.item()}
    if fg_terms:
        fg = torch.stack(fg_terms).mean()
        total = total + FOREGROUND_LOSS_WEIGHT * fg
        parts["foreground_loss"] = fg.item()
    return total, {"loss": total.item(), **parts}
