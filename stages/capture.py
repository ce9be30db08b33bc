"""Stage `capture`: one frame from a connected Zivid camera, saved as an organized PLY in
millimetres (what the import stage reads). Needs the optional `zivid` package."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType

from binpick.capture import capture_frame, import_zivid
from binpick.io.ply import save_ply
from binpick.params import Params, load_params
from stages.common import entry, parser, start

log = logging.getLogger("binpick.stage.capture")


def run(params: Params, out: Path, zivid: ModuleType | None = None) -> tuple[int, int]:
    frame = capture_frame(zivid or import_zivid(), params.capture)
    save_ply(out, frame)
    log.info("captured %dx%d frame -> %s", frame.shape[1], frame.shape[0], out)
    return frame.shape


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--out", required=True, type=Path, help="capture to write (.ply, millimetres)")
    args = p.parse_args(argv)
    start(args)
    run(load_params(args.params), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
