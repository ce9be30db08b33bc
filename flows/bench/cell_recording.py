"""A rerun recording of one bin emptied by the simulated cell (`binpick bench cell`): in the bin
frame (z up, metres), the bin's boxes, the parts at their true poses at every capture, and for
every executed pick the arm's sampled surface at each waypoint of its path, the tool's path and the
outcome; timeline `attempt`."""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path

import numpy as np

from binpick.geometry.transforms import transform_points
from binpick.io.atomic import atomic_path
from binpick.io.part_model import PartModel
from binpick.picking.arm import ArmMotion
from binpick.robot.arm import ArmModel

ARM_COLOUR = np.array([230, 140, 40], np.uint8)
PART_COLOUR = np.array([120, 160, 220], np.uint8)
BIN_COLOUR = np.array([150, 150, 150, 120], np.uint8)


class CellRecording:
    def __init__(
        self,
        path: Path,
        name: str,
        arm: ArmModel,
        T_bin_from_base: np.ndarray,
        T_flange_from_tcp: np.ndarray,
        bin_boxes: list[tuple[np.ndarray, np.ndarray]],
    ) -> None:
        import rerun as rr

        self.rr, self.arm = rr, arm
        self.T_bin_from_base, self.T_flange_from_tcp = T_bin_from_base, T_flange_from_tcp
        self._files = ExitStack()
        tmp = self._files.enter_context(atomic_path(path))
        self.rec = rr.RecordingStream("binpick", recording_id=f"cell-{name}")
        self.rec.save(str(tmp))  # to a file, never a viewer
        self.rec.log("bin", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        lo = np.array([b[0] for b in bin_boxes])
        hi = np.array([b[1] for b in bin_boxes])
        self.rec.log("bin/boxes", rr.Boxes3D(mins=lo, sizes=hi - lo, colors=BIN_COLOUR), static=True)

    def attempt(
        self, k: int, part: PartModel, T_bin_from_parts: np.ndarray, motion: ArmMotion | None, outcome: str
    ) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("attempt", sequence=k)
        sample = part.points_m[:: max(1, len(part.points_m) // 1500)]
        points = [transform_points(T, sample) for T in T_bin_from_parts]
        rec.log(
            "bin/parts",
            rr.Points3D(np.concatenate(points) if points else np.zeros((0, 3)), colors=PART_COLOUR, radii=0.001),
        )
        if motion is None:
            rec.log("bin/outcome", rr.TextDocument(outcome))
            return
        q = np.array([motion.q[name] for name in motion.path])
        surface, _ = self.arm.surface_points(q)
        T = self.T_bin_from_base
        for name, pts in zip(motion.path, surface, strict=True):
            rec.log(f"bin/arm/{name}", rr.Points3D(pts @ T[:3, :3].T + T[:3, 3], colors=ARM_COLOUR, radii=0.004))
        tcp = (T @ self.arm.flange_poses(q) @ self.T_flange_from_tcp)[:, :3, 3]
        rec.log("bin/tool_path", rr.LineStrips3D([tcp], colors=[ARM_COLOUR]))
        rec.log("bin/outcome", rr.TextDocument(outcome))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
        self._files.close()  # the file takes its name only now
