"""Bad input to any entry point: one clear error line, a non-zero exit, no traceback, no output."""

import subprocess
import sys

import pytest

from tests.conftest import ROOT


def _run(*args, cwd=ROOT):
    return subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def _assert_one_line_error(proc, *needles):
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, proc.stderr
    for needle in needles:
        assert needle in errors[0], errors[0]


def test_ingest_missing_and_wrong_files(tmp_path):
    out = tmp_path / "part.npz"
    proc = _run("-m", "stages.ingest", "--part", "t_joint", "--mesh", str(tmp_path / "missing.stl"), "--out", str(out))
    _assert_one_line_error(proc, "missing.stl", "not found")
    step = tmp_path / "part.step"
    step.write_text("ISO-10303-21;")
    proc = _run("-m", "stages.ingest", "--part", "t_joint", "--mesh", str(step), "--out", str(out))
    _assert_one_line_error(proc, "part.step", "unsupported mesh extension")
    assert not out.exists() and list(tmp_path.iterdir()) == [step]


def test_ingest_wrong_unit_is_reported(tmp_path):
    # The shipped part is in millimetres; declared as metres it would be 64 m long.
    params = (ROOT / "params.yaml").read_text().replace("    unit: mm\n    symmetry", "    unit: m\n    symmetry", 1)
    (tmp_path / "params.yaml").write_text(params)
    proc = _run(
        "-m",
        "stages.ingest",
        "--params",
        str(tmp_path / "params.yaml"),
        "--part",
        "t_joint",
        "--mesh",
        str(ROOT / "data/parts/t_joint.stl"),
        "--out",
        str(tmp_path / "p.npz"),
    )
    _assert_one_line_error(proc, "t_joint.stl", "unit")


def test_import_bad_capture(tmp_path):
    bad = tmp_path / "scan.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n\x00\x00")
    proc = _run("-m", "stages.import_capture", "--capture", str(bad), "--out", str(tmp_path / "c.npz"))
    _assert_one_line_error(proc, "scan.ply")
    proc = _run(
        "-m", "stages.import_capture", "--capture", str(tmp_path / "scan.xyz"), "--out", str(tmp_path / "c.npz")
    )
    _assert_one_line_error(proc, "scan.xyz")
    assert not (tmp_path / "c.npz").exists()


def test_broken_params_file(tmp_path):
    (tmp_path / "params.yaml").write_text("profile: [unclosed\n")
    proc = _run(
        "-m",
        "stages.segment",
        "--params",
        str(tmp_path / "params.yaml"),
        "--part",
        "t_joint",
        "--cloud",
        "c.npz",
        "--checkpoint",
        "m.pt",
        "--out",
        str(tmp_path / "s.npz"),
    )
    _assert_one_line_error(proc, "params.yaml", "YAML")


def test_binpick_review_without_results(tmp_path):
    (tmp_path / "params.yaml").write_text("profile: quick\n")
    (tmp_path / "dvc.yaml").write_text("stages: {}\n")
    proc = _run("-m", "flows.cli", "review", cwd=tmp_path)
    _assert_one_line_error(proc, "scene.rrd", "no recording yet")


@pytest.mark.parametrize("args", [["demo"]])
def test_binpick_outside_a_project(tmp_path, args):
    proc = _run("-m", "flows.cli", *args, cwd=tmp_path)
    _assert_one_line_error(proc, "not inside a binpick project")


def test_calibrate_a_damaged_checkpoint(tmp_path):
    bad = tmp_path / "model.pt"
    bad.write_bytes(b"not a checkpoint")
    proc = _run(
        "-m",
        "flows.cli",
        "calibrate",
        "--checkpoint",
        str(bad),
        "--scenes",
        str(tmp_path),
        "--out",
        str(tmp_path / "out.pt"),
    )
    _assert_one_line_error(proc, "model.pt", "not a readable checkpoint")
    assert not (tmp_path / "out.pt").exists()


def _bad_captures(tmp_path):
    """Captures that used to end in a traceback (or in a wrong diagnosis)."""
    import json

    import numpy as np
    from PIL import Image

    files = {}
    same = tmp_path / "same.ply"  # a thousand identical points
    same.write_text(
        "ply\nformat ascii 1.0\nelement vertex 1000\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        + "1 2 500\n" * 1000
    )
    files["identical points"] = ([str(same)], "distinct points")
    pcd = tmp_path / "size3.pcd"
    pcd.write_text(
        "VERSION 0.7\nFIELDS x y z\nSIZE 3 3 3\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n1 1 "
        "500\n2 1 500\n"
    )
    files["PCD SIZE 3"] = ([str(pcd)], "TYPE F with SIZE 3")
    zdf = tmp_path / "random.zdf"
    zdf.write_bytes(np.random.default_rng(0).bytes(4096))
    files["random bytes as .zdf"] = ([str(zdf)], "not a Zivid SDK 1.x frame")
    ok_intrinsics = tmp_path / "k.json"
    ok_intrinsics.write_text(json.dumps({"fx": 100.0, "fy": 100.0, "cx": 80.0, "cy": 60.0}))
    grey = tmp_path / "grey.png"
    Image.fromarray((np.arange(160 * 120) % 256).astype(np.uint8).reshape(120, 160)).save(grey)
    files["8-bit PNG as depth"] = ([str(grey), "--intrinsics", str(ok_intrinsics)], "8-bit image")
    depth = tmp_path / "depth.png"
    Image.fromarray(np.full((120, 160), 500, np.uint16)).save(depth)
    wrong = tmp_path / "k_full_res.json"
    wrong.write_text(json.dumps({"fx": 2660.0, "fy": 2660.0, "cx": 960.0, "cy": 600.0}))
    files["intrinsics of another resolution"] = (
        [str(depth), "--intrinsics", str(wrong)],
        "outside the 160 x 120 image",
    )
    return files


CAPTURE_CASES = [
    "identical points",
    "PCD SIZE 3",
    "random bytes as .zdf",
    "8-bit PNG as depth",
    "intrinsics of another resolution",
]


@pytest.mark.parametrize("case", CAPTURE_CASES)
def test_bad_captures_get_one_line(tmp_path, case):
    args, needle = _bad_captures(tmp_path)[case]
    out = tmp_path / "cloud.npz"
    proc = _run("-m", "stages.import_capture", "--capture", *args, "--out", str(out))
    _assert_one_line_error(proc, needle)
    assert not out.exists()


def test_an_output_path_that_cannot_be_written(tmp_path):
    blocker = tmp_path / "results"
    blocker.write_text("a file where a folder should be")
    proc = _run(
        "-m",
        "stages.ingest",
        "--part",
        "t_joint",
        "--mesh",
        str(ROOT / "data/parts/t_joint.stl"),
        "--out",
        str(blocker / "part.npz"),
    )
    _assert_one_line_error(proc, "results", "cannot read or write")


def _labels(path, rows):
    path.write_text("".join(" ".join(str(v) for v in row) + "\n" for row in rows))
    return path


@pytest.mark.parametrize("case", ["nan coordinates", "huge labels", "iou above 1", "iou 0", "negative distance"])
def test_eval_labels_refuses_bad_input(tmp_path, case):
    gt = _labels(tmp_path / "gt.txt", [(i * 0.001, 0.1, 0.5, i % 3) for i in range(50)])
    pred, extra, needle = gt, [], ""
    if case == "nan coordinates":
        pred, needle = (
            _labels(tmp_path / "p.txt", [("nan" if i == 4 else i * 0.001, 0.1, 0.5, i % 3) for i in range(50)]),
            "non-finite coordinates",
        )
    elif case == "huge labels":
        pred, needle = (
            _labels(tmp_path / "p.txt", [(i * 0.001, 0.1, 0.5, 10**12 + i) for i in range(50)]),
            "small integers",
        )
    elif case == "iou above 1":
        extra, needle = ["--iou", "1.5"], "(0, 1]"
    elif case == "iou 0":
        extra, needle = ["--iou", "0"], "(0, 1]"
    else:
        extra, needle = ["--match-distance-m", "-0.001"], "must not be negative"
    proc = _run("-m", "flows.cli", "eval-labels", "--pred", str(pred), "--gt", str(gt), *extra)
    _assert_one_line_error(proc, needle)


def test_serve_names_a_foreign_program_on_the_prefect_port(tmp_path):
    """Another program answering 200 to everything is not mistaken for a Prefect server."""
    import http.server
    import os
    import threading

    class Yes(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 - the http.server API
            self.send_response(200)
            self.end_headers()
            self.wfile.write(b"<html>ok</html>")

        def log_message(self, *args):
            pass

    server = http.server.HTTPServer(("127.0.0.1", 0), Yes)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
        proc = subprocess.run(
            [sys.executable, "-m", "flows.cli", "serve", "--port", str(server.server_port)],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
            env=env,
        )
    finally:
        server.shutdown()
    _assert_one_line_error(proc, f"port {server.server_port}", "not a Prefect server")


def test_a_crashed_stage_and_a_held_lock_are_reported_by_their_cause(tmp_path):
    import json

    from flows.dvc_tasks import failure_reason

    crashed = (
        "Running stage 'segment@x':\n> python -m stages.segment\nTraceback (most recent call last):\n"
        '  File "x.py", line 3, in f\nZeroDivisionError: division by zero\n'
        "ERROR: failed to reproduce 'segment@x': failed to run: python -m stages.segment, exited with 1\n"
    )
    assert failure_reason(tmp_path, crashed, "").startswith("the stage crashed: ZeroDivisionError: division by zero")
    own = "error: data/x.ply: holds no points\nERROR: failed to reproduce 'import_capture@x'\n"
    assert failure_reason(tmp_path, "", own) == "data/x.ply: holds no points"
    (tmp_path / ".dvc" / "tmp").mkdir(parents=True)
    (tmp_path / ".dvc" / "tmp" / "rwlock").write_text(
        json.dumps({"write": {"data/x": {"pid": 4242, "cmd": "dvc repro train@t_joint"}}})
    )
    locked = failure_reason(tmp_path, "", "ERROR: Unable to acquire lock. Most likely another DVC process is running")
    assert (
        "another run holds the repository lock (pid 4242: dvc repro train@t_joint)" in locked and "delete" not in locked
    )


def _bad_meshes(tmp_path):
    import numpy as np
    import trimesh

    cases = {}
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(np.random.default_rng(1).bytes(3000))
    cases["random bytes"] = (garbage, "garbage.stl")
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    cases["no triangles"] = (empty, "empty.obj")
    flat = tmp_path / "flat.obj"
    flat.write_text("v 0 0 0\nv 1 1 1\nv 2 2 2\nf 1 2 3\n")
    cases["degenerate faces only"] = (flat, "flat.obj")
    speck = tmp_path / "speck.stl"
    trimesh.creation.box(extents=[0.05, 0.05, 0.05]).export(speck)  # 50 um in mm: fits no unit
    cases["a speck"] = (speck, "too small")
    pair = tmp_path / "pair.stl"
    b = trimesh.creation.box(extents=[20.0, 20.0, 20.0])
    trimesh.util.concatenate([b, b.copy().apply_translation([60.0, 0.0, 0.0])]).export(pair)
    cases["two bodies"] = (pair, "an assembly")
    return cases


@pytest.mark.parametrize("case", ["random bytes", "no triangles", "degenerate faces only", "a speck", "two bodies"])
def test_bad_meshes_get_one_line_and_no_model(tmp_path, case):
    path, needle = _bad_meshes(tmp_path)[case]
    out = tmp_path / "models" / "part.npz"
    proc = _run(
        "-m",
        "stages.ingest",
        "--part",
        "t_joint",
        "--mesh",
        str(path),
        "--out",
        str(out),
        "--metrics",
        str(tmp_path / "m.json"),
    )
    _assert_one_line_error(proc, needle)
    assert not out.exists() and not (tmp_path / "m.json").exists()


def test_label_stage_refuses_poses_of_another_part(tmp_path):
    import json

    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps({"part": "other", "unit": "m", "frame": "camera", "poses": []}))
    cloud = tmp_path / "cloud.npz"
    proc = _run(
        "-m",
        "stages.label",
        "--part",
        "t_joint",
        "--cloud",
        str(cloud),
        "--poses",
        str(poses),
        "--ppf",
        str(tmp_path / "ppf.npz"),
        "--out",
        str(tmp_path / "l.npz"),
    )
    _assert_one_line_error(proc, "cloud.npz", "not found")
    assert not (tmp_path / "l.npz").exists()


def test_learn_commands_name_what_is_missing():
    proc = _run("-m", "flows.cli", "learn", "review", "--part", "no_such_part")
    _assert_one_line_error(proc, "no_such_part", "no labelled captures")
    proc = _run("-m", "flows.cli", "learn", "review", "--part", "t_joint", "--reject", "x")
    _assert_one_line_error(proc, "--reject goes with --approve")


def test_a_flows_stage_runs_at_lower_cpu_priority_than_its_caller(tmp_path):
    """A stage a flow runs yields the CPU to the pick service and the Prefect server: it runs at
    STAGE_NICENESS above the caller's own niceness (never below it)."""
    import os

    import yaml

    from flows.dvc_tasks import STAGE_NICENESS, dvc_env, repro

    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run([sys.executable, "-m", "dvc", "init", "-q"], cwd=tmp_path, check=True, env=dvc_env())
    stage = {"cmd": "python -c \"import os; open('nice.txt', 'w').write(str(os.nice(0)))\"", "outs": ["nice.txt"]}
    (tmp_path / "dvc.yaml").write_text(yaml.safe_dump({"stages": {"probe": stage}}))
    repro("probe", tmp_path)
    assert int((tmp_path / "nice.txt").read_text()) == max(os.nice(0), STAGE_NICENESS)
