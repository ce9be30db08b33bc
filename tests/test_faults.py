"""Faults a running cell meets: outputs committed together or not at all, temporaries of killed
writers swept, runs of killed stages ended, stages that die with the run that started them."""

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from binpick.io.atomic import atomic_dir, atomic_path, atomic_paths
from tests.conftest import ROOT


def test_outputs_of_one_stage_are_committed_together_or_not_at_all(tmp_path):
    poses, rrd, metrics = tmp_path / "poses.json", tmp_path / "scene.rrd", tmp_path / "m.json"
    for p in (poses, rrd, metrics):
        p.write_text("old")
    with pytest.raises(PermissionError), atomic_paths(poses, rrd, metrics) as (a, b, c):
        a.write_text("new")
        b.write_text("new")
        raise PermissionError("metrics folder is read-only")  # the last write fails
    assert [p.read_text() for p in (poses, rrd, metrics)] == ["old"] * 3
    with atomic_paths(poses, None, metrics) as (a, none, c):
        assert none is None
        a.write_text("new")
        c.write_text("new")
    assert [p.read_text() for p in (poses, rrd, metrics)] == ["new", "old", "new"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "poses.json", "scene.rrd"]


def _dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


def test_temporaries_of_a_killed_writer_are_swept_by_the_next(tmp_path):
    dead = _dead_pid()
    stale_dir = tmp_path / f".scenes.{dead}.abc123.tmp"
    (stale_dir / "train").mkdir(parents=True)
    stale_file = tmp_path / f".model.{dead}.xyz.tmp.pt"
    stale_file.write_bytes(b"half")
    live_file = tmp_path / f".model.{os.getpid()}.live.tmp.pt"  # a writer still at work
    live_file.write_bytes(b"busy")
    with atomic_dir(tmp_path / "scenes") as out:
        (out / "a").write_text("x")
    with atomic_path(tmp_path / "model.pt") as out:
        out.write_bytes(b"ok")
    assert not stale_dir.exists() and not stale_file.exists() and live_file.exists()
    assert (tmp_path / "scenes" / "a").is_file() and (tmp_path / "model.pt").read_bytes() == b"ok"


def test_runs_of_killed_stages_are_ended(tmp_path):
    import mlflow

    from review.tracking import end_dead_runs

    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    try:
        experiment = mlflow.create_experiment("part-x", artifact_location=(tmp_path / "art").as_uri())
        client = mlflow.MlflowClient()
        import socket

        dead = client.create_run(
            experiment, tags={"binpick.pid": str(_dead_pid()), "binpick.host": socket.gethostname()}, run_name="train-x"
        )
        alive = client.create_run(
            experiment, tags={"binpick.pid": str(os.getpid()), "binpick.host": socket.gethostname()}, run_name="train-x"
        )
        assert end_dead_runs("part-x") == [dead.info.run_id]
        assert client.get_run(dead.info.run_id).info.status == "KILLED"
        assert client.get_run(alive.info.run_id).info.status == "RUNNING"
    finally:
        os.environ.pop("MLFLOW_TRACKING_URI", None)


def _wait_gone(pid: int, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        with open(f"/proc/{pid}/stat") as fh:
            if fh.read().rsplit(")", 1)[1].split()[0] == "Z":  # exited, waiting to be reaped
                return True
        time.sleep(0.1)
    return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG and /proc are Linux's")
def test_a_stage_dies_with_the_dvc_run_that_started_it(tmp_path):
    """dvc -> shell -> stage: after kill -9 of the `dvc` process the stage stops (the shell between
    them lives on, so the parent-death signal alone would not do)."""
    stage = tmp_path / "stage.py"
    stage.write_text(
        textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(ROOT)!r})
        from binpick.lifetime import die_with_parent, find_ancestor, watch_ancestor
        die_with_parent()
        watch_ancestor(find_ancestor("dvc"), interval_s=0.2)
        open({str(tmp_path / "started")!r}, "w").close()
        time.sleep(60)
        open({str(tmp_path / "outputs")!r}, "w").close()
    """)
    )
    fake_dvc = tmp_path / "dvc"  # a process whose program is `dvc`, running the stage through a shell
    fake_dvc.write_text(
        f"#!{sys.executable}\nimport subprocess, sys\nsubprocess.run(['/bin/sh', '-c', '{sys.executable} {stage}; "
        "echo done'])\n"
    )
    fake_dvc.chmod(0o755)
    dvc = subprocess.Popen([str(fake_dvc), "repro"])
    deadline = time.monotonic() + 30
    while not (tmp_path / "started").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert (tmp_path / "started").exists()
    stage_pid = int(subprocess.run(["pgrep", "-f", str(stage)], capture_output=True, text=True).stdout.split()[-1])
    dvc.send_signal(signal.SIGKILL)
    dvc.wait()
    assert _wait_gone(stage_pid), "the stage outlived the killed dvc process"
    assert not (tmp_path / "outputs").exists()
