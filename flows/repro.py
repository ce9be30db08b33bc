"""`binpick repro`: the whole DVC pipeline, where one failing part or capture blocks nothing else.

`dvc repro --keep-going` runs every stage that does not depend on a failed one; each part or
capture with a failed stage is then set aside (until its files or entry change) with the stage's
own error line as the reason.
"""

import logging
import re
import subprocess
import sys
from pathlib import Path

from binpick.project import set_aside
from flows.dvc_tasks import dvc_env, failure_reason
from flows.pipeline import PART_STAGES, SCENE_STAGES, Outcome

log = logging.getLogger("binpick.repro")
_RUNNING = re.compile(r"Running stage '([^']+)'")
_FAILED = re.compile(r"failed to reproduce '([^']+)'")


def failed_stages(output: str) -> dict[str, str]:
    """Stage -> its error line, from the interleaved output of `dvc repro --keep-going`."""
    current, failed = None, {}
    for line in output.splitlines():
        if m := _RUNNING.search(line):
            current = m.group(1)
        elif line.startswith("error: ") and current and current not in failed:
            failed[current] = line.removeprefix("error: ")
        elif m := _FAILED.search(line):
            failed.setdefault(m.group(1), "the stage failed (see above)")
    return failed


def repro_all(root: Path) -> Outcome:
    """Run `dvc repro --keep-going`, showing DVC's progress lines; set aside what failed."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "dvc", "repro", "--keep-going"],
        cwd=root,
        env=dvc_env(),
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        bufsize=1,
    )
    lines = []
    assert proc.stdout is not None
    for line in proc.stdout:
        lines.append(line)
        if _RUNNING.search(line):
            log.info("%s", line.strip())
    proc.wait()
    output = "".join(lines)
    outcome = Outcome(ran=[m.group(1) for m in _RUNNING.finditer(output)])
    failed = failed_stages(output)
    if proc.returncode != 0 and not failed:
        raise_reason = failure_reason(root, output, "")
        from binpick.errors import BinpickError

        raise BinpickError(f"dvc repro failed: {raise_reason}")
    for stage, reason in failed.items():
        kind_stage, _, name = stage.partition("@")
        kind = "parts" if kind_stage in PART_STAGES else "captures" if kind_stage in SCENE_STAGES else None
        outcome.failed[stage] = reason
        if kind and name:
            set_aside(root, kind, name, f"{stage}: {reason}")
    return outcome
