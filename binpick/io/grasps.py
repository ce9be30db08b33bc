"""Grasp files (`grasps.json`): a part's grasps in its model frame, for a suction cup and for a
parallel-jaw gripper. The grasps stage writes one per part (generated from the CAD model, or read
from the file named by the part's `grasps` entry, which has the same format); both are expanded
by the part's symmetry. Spec: data/README.md#grasps.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.atomic import write_text

FORMAT = "binpick-grasps"
VERSION = 1
KINDS = ("suction", "jaw")


@dataclass(frozen=True)
class GraspSet:
    """Grasps of one gripper kind, best first.

    ids               : k names (unique)
    T_model_from_tool : (k, 4, 4) the tool frame at the grasp (binpick/picking/gripper.py): origin the
                        tool centre point, z the approach, x the jaws' closing axis (an oval suction
                        cup's long axis); model frame, metres
    width_m           : (k,) jaw opening at the contacts (0 for suction)
    """

    kind: str
    ids: list[str]
    T_model_from_tool: np.ndarray
    width_m: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    @classmethod
    def empty(cls, kind: str) -> GraspSet:
        return cls(kind, [], np.zeros((0, 4, 4)), np.zeros(0))


def tool_frame(origin: np.ndarray, approach: np.ndarray, closing: np.ndarray | None = None) -> np.ndarray:
    """T (4, 4) of a tool at `origin` approaching along `approach` (unit after normalising); x =
    `closing` made perpendicular to it, or (suction) a fixed axis across it."""
    z = np.asarray(approach, dtype=np.float64)
    z = z / np.linalg.norm(z)
    if closing is None:
        helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        closing = helper
    x = np.asarray(closing, dtype=np.float64) - np.dot(closing, z) * z
    x = x / np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, origin
    return T


def _entry(kind: str, grasp_id: str, T: np.ndarray, width: float, long_axis: bool) -> dict:
    r = lambda v: [round(float(x), 9) for x in v]  # noqa: E731
    if kind == "suction":
        entry = {"id": grasp_id, "point_m": r(T[:3, 3]), "approach": r(T[:3, 2])}
        return {**entry, "long_axis": r(T[:3, 0])} if long_axis else entry
    return {
        "id": grasp_id,
        "centre_m": r(T[:3, 3]),
        "approach": r(T[:3, 2]),
        "closing": r(T[:3, 0]),
        "width_m": round(float(width), 9),
    }


def save_grasps(path: str | Path, part: str, sets: dict[str, GraspSet], source: str, oval_cup: bool = False) -> None:
    """source: where the grasps came from ('generated' or the grasp file's path); oval_cup: the
    suction grasps name their cup's long axis (the tool's x)."""
    doc = {
        "format": FORMAT,
        "version": VERSION,
        "part": part,
        "unit": "m",
        "frame": "model",
        "source": source,
        **{
            kind: [
                _entry(kind, i, T, w, oval_cup) for i, T, w in zip(s.ids, s.T_model_from_tool, s.width_m, strict=True)
            ]
            for kind, s in sets.items()
        },
    }
    write_text(path, json.dumps(doc, indent=1) + "\n")


def _vector(path: Path, where: str, value: object, unit: bool) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InputError(path, f"{where}: expected three numbers, got {value!r}")
    if unit:
        n = np.linalg.norm(v)
        if n < 1e-9:
            raise InputError(path, f"{where}: a direction must not be zero")
        v = v / n
    return v


def load_grasps(path: str | Path, oval_cup: bool = False) -> dict[str, GraspSet]:
    """Every grasp set in a grasp file (kinds absent from the file are empty); oval_cup: every
    suction grasp must name its cup's long axis (`long_axis`, across the approach)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "grasp file not found")
    try:
        doc = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not a JSON grasp file ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format", FORMAT) != FORMAT:
        raise InputError(path, f'not a binpick grasp file (expected "format": "{FORMAT}")')
    if doc.get("unit", "m") != "m":
        raise InputError(
            path, f'grasps must be in metres in the part\'s model frame ("unit": "m"), not {doc.get("unit")!r}'
        )
    if not any(k in doc for k in KINDS):
        raise InputError(path, f"has no grasps (lists named {' or '.join(KINDS)})")
    out: dict[str, GraspSet] = {}
    for kind in KINDS:
        entries = doc.get(kind, [])
        if not isinstance(entries, list):
            raise InputError(path, f"{kind}: expected a list of grasps")
        ids, Ts, widths = [], [], []
        for k, e in enumerate(entries):
            where = f"{kind}[{k}]"
            if not isinstance(e, dict):
                raise InputError(path, f"{where}: expected a mapping")
            try:
                grasp_id = str(e.get("id", f"{kind[0]}{k}"))
                if kind == "suction":
                    approach = _vector(path, f"{where}.approach", e["approach"], True)
                    long_axis = None
                    if "long_axis" in e:
                        long_axis = _vector(path, f"{where}.long_axis", e["long_axis"], True)
                        if abs(float(approach @ long_axis)) > 0.02:
                            raise InputError(path, f"{where}: long_axis must be perpendicular to approach")
                    elif oval_cup:
                        raise InputError(
                            path, f"{where}: an oval cup (pick.suction.cup_half_length_m) needs the grasp's long_axis"
                        )
                    T = tool_frame(_vector(path, f"{where}.point_m", e["point_m"], False), approach, long_axis)
                    width = 0.0
                else:
                    approach = _vector(path, f"{where}.approach", e["approach"], True)
                    closing = _vector(path, f"{where}.closing", e["closing"], True)
                    if abs(float(approach @ closing)) > 0.02:
                        raise InputError(path, f"{where}: closing must be perpendicular to approach")
                    width = float(e["width_m"])
                    if not np.isfinite(width) or width <= 0:
                        raise InputError(path, f"{where}.width_m: must be a positive number of metres")
                    T = tool_frame(_vector(path, f"{where}.centre_m", e["centre_m"], False), approach, closing)
            except KeyError as exc:
                raise InputError(path, f"{where}: missing {exc.args[0]!r}") from None
            except (TypeError, ValueError) as exc:
                raise InputError(path, f"{where}: {exc}") from None
            if grasp_id in ids:
                raise InputError(path, f"{where}: id {grasp_id!r} is used twice")
            ids.append(grasp_id)
            Ts.append(T)
            widths.append(width)
        out[kind] = GraspSet(kind, ids, np.array(Ts).reshape(-1, 4, 4), np.array(widths, dtype=np.float64))
    return out
