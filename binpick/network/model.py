"""The FPCC network: a DGCNN (or PointNet) backbone with an embedding head and a centre-score head.

Input  x : (B, 6, N) float32 per-point features (xyz shifted by the scene minimum, metres, then
           normals or normalised xyz), plus xyz (B, N, 3) for the neighbour graph.
Output embedding (B, N, D) and centre score (B, N) in [0, 1].
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np
import torch
from pykdtree.kdtree import KDTree
from torch import nn

IN_FEATURES = 6
KNN_CHUNK = 2048  # query rows per distance block: bounds memory to chunk x N per sample


@dataclass(frozen=True)
class FPCCConfig:
    """Everything needed to rebuild the network; stored inside every checkpoint."""

    backbone: Literal["dgcnn", "pointnet"] = "dgcnn"
    k_neighbours: int = 16
    width: int = 64
    embedding_dim: int = 128
    # A third head: whether a point belongs to a part at all (trained where the training view
    # holds points of no part; checkpoints from before it have none and call every point a part's).
    foreground_head: bool = False

    def to_dict(self) -> dict:
        return asdict(self)


ALWAYS_FOREGROUND_LOGIT = 30.0  # sigmoid(30) = 1 - 1e-13


def knn_indices(xyz: torch.Tensor, k: int) -> torch.Tensor:
    """(B, N, k) int64 indices of the k nearest points of each point (itself included), nearest
    first: by k-d tree on the CPU (about 6x faster there at 4,096 points), by distance blocks on a GPU."""
    return knn_by_tree(xyz, k) if xyz.device.type == "cpu" else knn_by_distance_blocks(xyz, k)


def knn_by_tree(xyz: torch.Tensor, k: int) -> torch.Tensor:
    B, N, _ = xyz.shape
    k = min(k, N)
    clouds = xyz.detach().cpu().numpy()
    # pykdtree: half scipy's time for 4,096 points and k = 16 (a fifth of a network pass).
    idx = np.stack([KDTree(c).query(c, k=k)[1].reshape(N, k) for c in clouds])
    return torch.from_numpy(idx.astype(np.int64)).to(xyz.device)


def knn_by_distance_blocks(xyz: torch.Tensor, k: int) -> torch.Tensor:
    """Blocks of KNN_CHUNK query rows bound memory to chunk x N per sample."""
    B, N, _ = xyz.shape
    k = min(k, N)
    out = torch.empty(B, N, k, dtype=torch.long, device=xyz.device)
    for start in range(0, N, KNN_CHUNK):
        d = torch.cdist(xyz[:, start : start + KNN_CHUNK], xyz)  # (B, chunk, N)
        out[:, start : start + KNN_CHUNK] = d.topk(k, dim=-1, largest=False).indices
    return out


def gather_neighbours(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """x (B, C, N), idx (B, N, k) -> neighbour features (B, C, N, k)."""
    B, C, N = x.shape
    k = idx.shape[-1]
    flat = idx.reshape(B, 1, N * k).expand(B, C, N * k)
    return torch.gather(x, 2, flat).reshape(B, C, N, k)


def neighbour_max(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """x (B, C, N), idx (B, N, k) -> (B, C, N): per channel, the max over each point's neighbours.

    Gathers rows of a point-major table and reduces across them, which vectorises over channels
    (about 5x faster on the CPU than a max along the last axis of gather_neighbours)."""
    B, C, N = x.shape
    table = x.transpose(1, 2).reshape(B * N, C).contiguous()  # (B*N, C); reshape alone may keep a strided view
    offset = (torch.arange(B, device=x.device) * N)[:, None, None]
    rows = nn.functional.embedding(idx + offset, table)  # (B, N, k, C)
    return rows.amax(dim=2).transpose(1, 2)  # (B, C, N)


class EdgeConv(nn.Module):
    """h_i = max_j MLP([x_j - x_i, x_i]) over the k neighbours j of i (Wang et al., DGCNN).

    The MLP's first layer is linear, W [x_j - x_i, x_i] = W_a x_j + (W_b - W_a) x_i, so it is
    applied to the N points and the result gathered, not applied to the N x k edges: k times
    fewer multiplications, the same numbers. In eval mode batch norm is a per-channel affine map
    and LeakyReLU is increasing, so the max over neighbours moves before them (the min where the
    scale is negative) and the (B, C_out, N, k) activations are never formed.
    """

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Conv2d(2 * c_in, c_out, 1, bias=False), nn.BatchNorm2d(c_out), nn.LeakyReLU(0.2))

    def forward(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        conv, bn, act = self.mlp
        assert isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d)
        C = x.shape[1]
        W = conv.weight[:, :, 0, 0]  # (C_out, 2C): [neighbour offset | centre]
        u = torch.einsum("oc,bcn->bon", W[:, :C], x)  # (B, C_out, N) neighbour term
        v = torch.einsum("oc,bcn->bon", W[:, C:] - W[:, :C], x)  # (B, C_out, N) centre term
        if self.training or not bn.track_running_stats:
            edges = gather_neighbours(u, idx) + v.unsqueeze(-1)  # (B, C_out, N, k)
            return act(bn(edges)).max(dim=-1).values  # (B, c_out, N)
        assert bn.running_var is not None and bn.running_mean is not None  # tracked: checked above
        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)  # (C_out,)
        shift = bn.bias - bn.running_mean * scale
        sign = torch.where(scale < 0, -1.0, 1.0).to(u.dtype)[None, :, None]
        extreme = sign * neighbour_max(sign * u, idx)  # (B, C_out, N)
        return act(scale[None, :, None] * (extreme + v) + shift[None, :, None])


def _pointwise(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv1d(c_in, c_out, 1, bias=False), nn.BatchNorm1d(c_out), nn.LeakyReLU(0.2))


class FPCC(nn.Module):
    def __init__(self, config: FPCCConfig):
        super().__init__()
        self.config = config
        w = config.width
        if config.backbone == "dgcnn":
            self.local = nn.ModuleList([EdgeConv(IN_FEATURES, w), EdgeConv(w, w), EdgeConv(w, w)])
        elif config.backbone == "pointnet":
            self.local = nn.ModuleList([_pointwise(IN_FEATURES, w), _pointwise(w, w), _pointwise(w, w)])
        else:
            raise ValueError(f"unknown backbone {config.backbone!r}")
        self.global_mlp = _pointwise(3 * w, 8 * w)
        self.trunk = nn.Sequential(_pointwise(3 * w + 8 * w, 4 * w), _pointwise(4 * w, 2 * w))
        self.embedding_head = nn.Conv1d(2 * w, config.embedding_dim, 1)
        self.centre_head = nn.Conv1d(2 * w, 1, 1)
        self.foreground_head = nn.Conv1d(2 * w, 1, 1) if config.foreground_head else None

    def forward(self, features: torch.Tensor, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """features (B, 6, N), xyz (B, N, 3) -> embedding (B, N, D), centre score (B, N) and
        foreground logit (B, N) (a large constant without the head: every point a part's)."""
        idx = knn_indices(xyz, self.config.k_neighbours) if self.config.backbone == "dgcnn" else None
        h = features
        levels = []
        for layer in self.local:
            h = layer(h, idx) if idx is not None else layer(h)
            levels.append(h)
        local = torch.cat(levels, dim=1)  # (B, 3w, N)
        glob = self.global_mlp(local).max(dim=-1, keepdim=True).values  # (B, 8w, 1)
        h = self.trunk(torch.cat([local, glob.expand(-1, -1, local.shape[-1])], dim=1))  # (B, 2w, N)
        embedding = self.embedding_head(h).transpose(1, 2)  # (B, N, D)
        centre = torch.sigmoid(self.centre_head(h)).squeeze(1)  # (B, N)
        if self.foreground_head is None:
            return embedding, centre, torch.full_like(centre, ALWAYS_FOREGROUND_LOGIT)
        return embedding, centre, self.foreground_head(h).squeeze(1)


def input_features(points: torch.Tensor, normals: torch.Tensor, mode: str, length_scale_m: float) -> torch.Tensor:
    """(B, N, 3) points (metres) and normals -> (B, 6, N) network input.

    Channels 0-2: xyz shifted by the per-scene minimum, divided by `length_scale_m` (d_max) so that
    coordinates are in part-sized units and weigh as much as the unit normals whatever the part's
    size. Channels 3-5: normals, or ('normalised_xyz', the reference code's variant) the shifted xyz
    divided by its per-scene maximum.
    """
    shifted = (points - points.min(dim=1, keepdim=True).values) / length_scale_m
    if mode == "normals":
        extra = normals
    elif mode == "normalised_xyz":
        extra = shifted / shifted.amax(dim=1, keepdim=True).clamp_min(1e-9)
    else:
        raise ValueError(f"unknown feature mode {mode!r}")
    return torch.cat([shifted, extra], dim=-1).transpose(1, 2).contiguous()
