"""Parts a grip failed on: a cell does not send the arm to the same part at once again.

When the gripper holds nothing at the grasp (the suction cup found no seal, the jaws closed on air),
or loses the part on its way up (torn off against a neighbour it is hooked on), the pose it was sent
to was wrong or the grasp does not hold on that part as it lies. The next capture sees the same part
where it was, usually posed the same way, so the same pick would fail again: in the simulated cell a
T-joint posed 3 mm and 20 degrees off failed three times in a row and stopped a bin half full; a
ring screw torn off its cup against the bin wall at 180 ms after the grip was sent to the same grasp
again and lost again. The part is left alone, an obstacle like any other, until no other part can be
picked; then it is tried again (the heap around it has changed, and with it what the camera sees of
it), but not where a grip found no hold: a grasp whose contact lies within the gripper's own size of
such a failed one meets the same surface (in the simulated cell the pipe's cup failed to seal three
times on one part, each time at the same spot). A part lost on the way up had held there: its
contact stays open (the neighbour it was hooked on may be gone by its turn).

Camera frame, metres (the camera is fixed over the bin, so a spot in its frame stays put).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# A pose is the part a grip failed on when its centre lies within this share of the part's
# diameter of where that part's centre was (the same part posed again moves by millimetres; two
# parts' centres lie further apart than that unless they interpenetrate).
SAME_PART_SHARE = 0.2


@dataclass
class FailedGrips:
    """The centres (camera frame) of the parts a grip failed on since the last retry, and where
    every failed grip's tool centre point was (kept across retries)."""

    _spots: list[np.ndarray] = field(default_factory=list)
    _contacts: list[np.ndarray] = field(default_factory=list)

    @classmethod
    def at(cls, contacts_m: np.ndarray | list[list[float]]) -> FailedGrips:
        """Grips that failed with the tool centre point at contacts_m (k, 3), the parts they were on
        not known (a controller reports where it failed; no part is left alone)."""
        return cls(_contacts=list(np.array(contacts_m, dtype=np.float64).reshape(-1, 3)))

    def failed(
        self, T_cam_from_model: np.ndarray, centre_m: np.ndarray, T_cam_from_grasp: np.ndarray, held: bool = False
    ) -> None:
        """A grip failed on the part posed at T_cam_from_model (4, 4); centre_m (3,) the part's
        centre in its model frame; T_cam_from_grasp (4, 4) the tool centre point it was sent to;
        held: the grip held and the part was lost on the way up (the surface took the grip: the
        part is left alone, its contact is not ruled out)."""
        T = np.asarray(T_cam_from_model, dtype=np.float64)
        self._spots.append(T[:3, :3] @ np.asarray(centre_m, dtype=np.float64) + T[:3, 3])
        if not held:
            self._contacts.append(np.asarray(T_cam_from_grasp, dtype=np.float64)[:3, 3].copy())

    def retry(self) -> bool:
        """No other part could be picked: the parts left alone are tried again. Whether there were any."""
        had, self._spots = bool(self._spots), []
        return had

    def centres_m(self) -> np.ndarray:
        """(k, 3) the centres of the parts to leave alone now."""
        return np.array(self._spots, dtype=np.float64).reshape(-1, 3)

    def contacts_m(self) -> np.ndarray:
        """(k, 3) where the tool centre point was at each failed grip: not a grasp's place again."""
        return np.array(self._contacts, dtype=np.float64).reshape(-1, 3)


def near_failed(centres_m: np.ndarray, failed_m: np.ndarray, diameter_m: float) -> np.ndarray:
    """(p,) bool: which of the posed parts' centres (p, 3) lie within SAME_PART_SHARE of the part's
    diameter of a failed part's centre (k, 3); same frame, metres."""
    return near_contacts(centres_m, failed_m, SAME_PART_SHARE * diameter_m)


def near_contacts(tcp_m: np.ndarray, contacts_m: np.ndarray, radius_m: float) -> np.ndarray:
    """(g,) bool: which grasps' tool centre points (g, 3) lie within radius_m of a failed grip's
    (k, 3); same frame, metres."""
    tcp = np.asarray(tcp_m, dtype=np.float64).reshape(-1, 3)
    contacts = np.asarray(contacts_m, dtype=np.float64).reshape(-1, 3)
    if len(tcp) == 0 or len(contacts) == 0:
        return np.zeros(len(tcp), dtype=bool)
    distance = np.linalg.norm(tcp[:, None, :] - contacts[None, :, :], axis=2)
    return np.asarray(np.min(distance, axis=1) <= radius_m)
