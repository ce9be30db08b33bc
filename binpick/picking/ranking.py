"""The order to take picks in: trusted poses first, then pick.order (height, score, clearance)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from binpick.params import PickParams

if TYPE_CHECKING:
    from binpick.picking.plan import Pick


def rank_key(pick: Pick, params: PickParams) -> tuple[float, ...]:
    """A pick's place in the order to take them (smaller first): trusted first, then pick.order."""
    return (*order_keys(pick.trusted, pick.height_m, pick.score, pick.clearance_m, params), pick.pose_index)


def order_keys(
    trusted: bool, height_m: float, score: float, clearance_m: float, params: PickParams
) -> tuple[float, ...]:
    keys = [0.0 if trusted else 1.0]
    for k in params.order:
        if k == "height":
            keys.append(-np.floor(height_m / params.height_tolerance_m) if params.height_tolerance_m > 0 else -height_m)
        elif k == "score":
            keys.append(-score)
        else:
            keys.append(-clearance_m)
    return tuple(keys)


def known_keys(trusted: bool, height_m: float, score: float, params: PickParams) -> tuple[float, ...]:
    """The ranking's keys known before a part's grasps are checked: up to its clearance."""
    keys = order_keys(trusted, height_m, score, 0.0, params)
    return keys[: 1 + params.order.index("clearance")] if "clearance" in params.order else keys
