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
    proc = _run("-m", "stages.ingest", "--params", str(tmp_path / "params.yaml"), "--part", "t_joint",
                "--mesh", str(ROOT / "data/parts/t_joint.stl"), "--out", str(tmp_path / "p.npz"))
    _assert_one_line_error(proc, "t_joint.stl", "unit")


def test_import_bad_capture(tmp_path):
    bad = tmp_path / "scan.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n\x00\x00")
    proc = _run("-m", "stages.import_capture", "--capture", str(bad), "--out", str(tmp_path / "c.npz"))
    _assert_one_line_error(proc, "scan.ply")
    proc = _run("-m", "stages.import_capture", "--capture", str(tmp_path / "scan.xyz"), "--out", str(tmp_path / "c.npz"))
    _assert_one_line_error(proc, "scan.xyz")
    assert not (tmp_path / "c.npz").exists()


def test_broken_params_file(tmp_path):
    (tmp_path / "params.yaml").write_text("profile: [unclosed\n")
    proc = _run("-m", "stages.segment", "--params", str(tmp_path / "params.yaml"), "--part", "t_joint",
                "--cloud", "c.npz", "--checkpoint", "m.pt", "--out", str(tmp_path / "s.npz"))
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
    proc = _run("-m", "flows.cli", "calibrate", "--checkpoint", str(bad), "--scenes", str(tmp_path), "--out", str(tmp_path / "out.pt"))
    _assert_one_line_error(proc, "model.pt", "not a readable checkpoint")
    assert not (tmp_path / "out.pt").exists()
