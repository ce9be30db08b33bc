from pathlib import Path

import pytest
import yaml

from binpick.errors import InputError, ParamsError
from binpick.params import SECTIONS, deep_merge, load_params, load_raw, resolve

ROOT = Path(__file__).resolve().parents[1]


def test_project_params_load_with_quick_profile_and_part():
    raw = load_raw(ROOT / "params.yaml")
    p = load_params(ROOT / "params.yaml", "t_joint")
    assert p.profile == "quick"
    assert p.generate.n_train == raw["profiles"]["quick"]["generate"]["n_train"]
    assert p.camera.downscale == raw["profiles"]["quick"]["camera"]["downscale"]
    # Untouched by the profile: the section's own value.
    assert p.registration.angle_bins == raw["register"]["angle_bins"]
    assert p.parts["t_joint"].symmetry.order == 2


def test_every_profile_lists_every_section():
    raw = load_raw(ROOT / "params.yaml")
    for name, profile in raw["profiles"].items():
        assert set(SECTIONS) <= set(profile), name


def test_part_overrides_apply_after_profile():
    raw = {
        "profile": "q",
        "profiles": {"q": {s: {} for s in SECTIONS} | {"train": {"epochs": 3, "width": 16}}},
        "parts": {"a": {"mesh": "a.stl", "train": {"epochs": 9}}, "b": {"mesh": "b.stl"}},
    }
    a = resolve(raw, "a")
    b = resolve(raw, "b")
    assert a["train"] == {"epochs": 9, "width": 16}
    assert b["train"] == {"epochs": 3, "width": 16}


def test_a_large_part_overrides_camera_and_import_grid(tmp_path, monkeypatch):
    """A large part sets its own camera distance and voxel grid; its captures import on that grid,
    so the network sees at inference the density it was trained on."""
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    raw["parts"]["shaft"] = {
        "mesh": "shaft.stl",
        "unit": "m",
        "camera": {"distance_m": 1.4},
        "import_capture": {"voxel_size_m": 0.008},
    }
    raw["captures"]["monday"] = {"file": "monday.ply", "part": "shaft"}
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(raw))
    shaft = load_params(path, "shaft")
    assert shaft.camera.distance_m == 1.4 and shaft.import_capture.voxel_size_m == 0.008
    assert shaft.camera.width_px == load_params(path).camera.width_px  # the rest as before
    assert load_params(path, "t_joint").import_capture.voxel_size_m == 0.002
    from stages import import_capture

    seen = []
    monkeypatch.setattr(
        import_capture, "run", lambda params, *args, **kwargs: seen.append(params.import_capture.voxel_size_m)
    )
    assert (
        import_capture.main(
            ["--params", str(path), "--name", "monday", "--capture", "monday.ply", "--out", str(tmp_path / "c.npz")]
        )
        == 0
    )
    assert seen == [0.008]


def test_deep_merge_nested():
    assert deep_merge({"a": {"x": 1, "y": 2}, "b": 1}, {"a": {"y": 3}}) == {"a": {"x": 1, "y": 3}, "b": 1}


def _write(tmp_path, raw):
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def _minimal():
    """The project's sections (params.yaml is the one source of values), one part, one profile."""
    raw = {k: v for k, v in load_raw(ROOT / "params.yaml").items() if k not in ("parts", "captures", "profiles")}
    return raw | {
        "profile": "q",
        "profiles": {"q": {s: {} for s in SECTIONS}},
        "parts": {"a": {"mesh": "a.stl", "unit": "mm"}},
        "render_demo": raw["render_demo"] | {"part": "a"},
    }


def test_a_key_missing_from_the_file_fails_naming_it(tmp_path):
    """No default hides a missing setting: the code declares no values of its own."""
    raw = _minimal()
    del raw["register"]["min_score"]
    with pytest.raises(ParamsError, match=r"register\.min_score: Field required"):
        load_params(_write(tmp_path, raw))


def test_misspelt_key_fails_at_load_with_one_line(tmp_path):
    raw = deep_merge(_minimal(), {"train": {"epoch": 3}})
    with pytest.raises(ParamsError) as err:
        load_params(_write(tmp_path, raw), "a")
    msg = str(err.value)
    assert "train.epoch" in msg and "\n" not in msg


def test_bad_value_and_missing_profile_section(tmp_path):
    raw = deep_merge(_minimal(), {"train": {"eps1": 2.0, "eps2": 1.0}})
    with pytest.raises(ParamsError, match="eps1"):
        load_params(_write(tmp_path, raw), "a")
    raw = _minimal()
    del raw["profiles"]["q"]["train"]
    with pytest.raises(ParamsError, match="missing"):
        load_params(_write(tmp_path, raw))


def test_register_section_is_the_registration_attribute(tmp_path):
    raw = deep_merge(_minimal(), {"register": {"min_score": 0.7}})
    assert load_params(_write(tmp_path, raw)).registration.min_score == 0.7


def test_unknown_part_and_missing_file(tmp_path):
    with pytest.raises(ParamsError, match="not listed"):
        load_params(_write(tmp_path, _minimal()), "zzz")
    with pytest.raises(InputError, match="not found"):
        load_params(tmp_path / "nope.yaml")


def test_a_key_written_twice_fails_naming_it_and_its_line(tmp_path):
    """A part entry with `pick:` twice: YAML's safe loader would keep the second silently."""
    text = Path("params.yaml").read_text()
    entry = "    symmetry: {kind: n_fold, axis: [0.0, 1.0, 0.0], order: 2}\n"
    assert entry in text
    twice = text.replace(entry, entry + "    pick: {gripper: jaw}\n    pick: {gripper: suction}\n", 1)
    path = tmp_path / "params.yaml"
    path.write_text(twice)
    line = twice.splitlines().index("    pick: {gripper: suction}") + 1
    with pytest.raises(InputError, match=rf"the key 'pick' twice \(line {line}\)") as err:
        load_params(path)
    assert "\n" not in str(err.value)
    path.write_text(twice.replace("    pick: {gripper: jaw}\n", "", 1))
    assert load_params(path, "t_joint").pick.gripper == "suction"
