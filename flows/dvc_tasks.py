"""Prefect tasks that run DVC, so that DVC's cache skips every stage that is up to date."""

import contextlib
import os
import subprocess
import sys
from pathlib import Path

from prefect import task
from prefect.logging import get_run_logger


class StageFailed(RuntimeError):
    """A DVC stage failed; `reason` is the stage's own error line (or DVC's)."""

    def __init__(self, target: str, reason: str):
        self.target = target
        self.reason = reason
        super().__init__(f"{target}: {reason}")


def dvc_env() -> dict[str, str]:
    """The environment for DVC: this interpreter's folder first on PATH, so that the `python` of
    the stage commands is the project's own."""
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


def prefect_run_env() -> dict[str, str]:
    """The current Prefect flow and task run, for the stages' MLflow tags (review/tracking.py)."""
    from prefect.runtime import flow_run, task_run

    values = {
        "BINPICK_PREFECT_FLOW_RUN_ID": flow_run.id,
        "BINPICK_PREFECT_FLOW_RUN_NAME": flow_run.name,
        "BINPICK_PREFECT_FLOW_NAME": flow_run.flow_name,
        "BINPICK_PREFECT_TASK_RUN_ID": task_run.id,
    }
    return {k: str(v) for k, v in values.items() if v}


# Stages (training, scene generation) take every core for minutes. On a cell's PC the pick service
# and the Prefect server that schedules retraining share those cores; at normal priority a served
# watcher's API calls timed out while its own training ran (the server answered nothing for
# minutes on 2 cores). Niceness only matters when something else wants the CPU.
STAGE_NICENESS = 10


def repro(target: str, root: Path, extra_env: dict[str, str] | None = None) -> str:
    """`dvc repro <target>` in `root` at lower CPU priority (STAGE_NICENESS, inherited by the stage
    and its workers); returns DVC's output, raises StageFailed with the error."""
    import psutil

    proc = subprocess.Popen(
        [sys.executable, "-m", "dvc", "repro", target],
        cwd=root,
        env={**dvc_env(), **(extra_env or {})},
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    # Set from here rather than in a preexec_fn, which is unsafe in Prefect's threaded task runs.
    # DVC starts the stage's own process later, so it inherits the priority.
    with contextlib.suppress(psutil.Error):
        stage = psutil.Process(proc.pid)
        stage.nice(max(stage.nice(), STAGE_NICENESS))  # never raised above the caller's
    stdout, stderr = proc.communicate()
    if proc.returncode != 0:
        raise StageFailed(target, failure_reason(root, stdout, stderr))
    return stdout


_EXCEPTION_LINE = __import__("re").compile(r"^[A-Za-z_][\w.]*(Error|Exception|Interrupt|Exit)\b.*")


def failure_reason(root: Path, stdout: str, stderr: str) -> str:
    """The one line that says why `dvc repro` failed: the stage's own `error:` line when a stage
    failed; who holds the lock when another run does; else DVC's last error line."""
    lines = (stderr + "\n" + stdout).splitlines()
    own = [line.removeprefix("error: ") for line in lines if line.startswith("error: ")]
    if own:
        return own[-1]
    if any("Unable to acquire lock" in line for line in lines):
        return lock_holder(root)
    # A stage that crashed (a bug, not bad input): the exception line of its traceback.
    crashed = [line for line in lines if _EXCEPTION_LINE.match(line)]
    if crashed and any(line.startswith("Traceback") for line in lines):
        return f"the stage crashed: {crashed[-1].strip()} (run it with --verbose, or see `dvc repro -v`)"
    errors = [line.removeprefix("ERROR: ") for line in lines if line.startswith("ERROR: ")]
    return (errors or [line for line in lines if line.strip()] or ["unknown error"])[-1].strip()


def lock_holder(root: Path) -> str:
    """'another run holds the repository lock (pid N: command)' from DVC's lock files; the lock
    is live, so it is never suggested to delete it."""
    import json

    holder = ""
    try:
        info = json.loads((root / ".dvc" / "tmp" / "rwlock").read_text() or "{}")
        for kind in ("write", "read"):
            for entry in (info.get(kind) or {}).values():
                entries = entry if isinstance(entry, list) else [entry]
                for e in entries:
                    holder = f"pid {e.get('pid')}: {e.get('cmd')}"
                    break
    except (OSError, ValueError, AttributeError):
        pass
    if not holder:
        try:
            holder = f"pid {(root / '.dvc' / 'tmp' / 'lock').read_text().strip()}"
        except OSError:
            holder = "another DVC process"
    return f"another run holds the repository lock ({holder}); wait for it to finish, or stop that process"


@task(
    name="dvc-repro",
    task_run_name="{target}",
    retries=1,
    retry_delay_seconds=2,
    retry_condition_fn=lambda task, run, state: "lock" in str(state.message or "").lower(),
)
def repro_stage(target: str, root: Path) -> str:
    """One DVC stage; retried once only when another DVC process held the repository lock."""
    import logging
    import time

    progress = logging.getLogger("binpick.flows")
    progress.info("%s ...", target)
    t0 = time.perf_counter()
    out = repro(target, root, prefect_run_env())
    logger = get_run_logger()
    # `dvc repro <target>` also reports the upstream stages it skipped: only a line that starts
    # the target itself says it ran.
    skipped = f"Running stage '{target}'" not in out
    logger.info("%s: %s", target, "up to date" if skipped else "ran")
    progress.info("%s: %s (%.0f s)", target, "up to date" if skipped else "done", time.perf_counter() - t0)
    return out
