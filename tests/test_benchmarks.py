"""The benchmark code on tiny settings: it must produce right answers; its timings are not
asserted (speed targets live in the benchmarks' JSON, not in tests)."""

import numpy as np
import pytest

from binpick.geometry.transforms import make_T
from flows.bench.generation import bench_generate, max_penetration_mm, rejection_baseline
from flows.bench.ppf import bench_ppf

from settings import PARAMS, ROOT, changed


def test_penetration_measure_knows_overlap_from_none(t_joint):
    rng = np.random.default_rng(0)
    T = make_T(np.eye(3), np.zeros(3))
    shifted = make_T(np.eye(3), np.array([0.0, 0.0, 0.005]))  # 5 mm into a 24 mm thick part
    far = make_T(np.eye(3), np.array([0.2, 0.0, 0.0]))
    assert max_penetration_mm(t_joint, np.stack([T, far]), rng) == 0.0
    assert max_penetration_mm(t_joint, np.stack([T, shifted]), rng) > 1.0


def test_rejection_baseline_places_every_object(t_joint):
    poses = rejection_baseline(t_joint, 4, PARAMS.generate.bin, np.random.default_rng(0))
    assert poses.shape == (4, 4, 4)


def test_generate_bench_reports_both_methods(t_joint):
    result = bench_generate(PARAMS, ["t_joint"], scenes=1, baseline_scenes=1, counts=(3,))
    ours, base = result["binpick"]["3"], result["rejection_baseline"]["3"]
    assert ours["objects_placed_mean"] == 3 and ours["max_penetration_mm"] <= 1.0
    assert base["objects_placed_mean"] == 3 and "speedup_at_3" in result
    physics = result["binpick_physics"]["3"]
    assert physics["objects_placed_mean"] >= 2 and physics["max_penetration_mm"] <= 1.0


def test_ppf_bench_recovers_poses():
    result = bench_ppf(PARAMS, ["t_joint"], trials=3, methods=["binpick_ppf"])
    ours = result["binpick_ppf"]
    assert ours["add_success_rate"] == 1.0 and ours["rot_err_deg_median"] < 1.0
    assert set(result["per_part"]) == {"t_joint"}


def test_clutter_bench_reports_both_scorings():
    from flows.bench.clutter import bench_clutter

    result = bench_clutter(PARAMS, ["t_joint"], n_scenes=1, checkpoints={})
    part = result["parts"]["t_joint"]
    for key in ("pose_precision", "pose_recall", "pose_recall_measured", "false_poses_outside_bin", "n_scenes"):
        assert key in part and f"baseline_{key}" in part and key in result and f"baseline_{key}" in result
    assert part["n_scenes"] == 1 and part["pose_recall"] >= 0.5 and part["false_poses_outside_bin"] == 0
    # The one scene is counted in the band of tilt its camera was drawn in (0 to 45 degrees).
    ((band, figures),) = result["by_tilt"].items()
    assert 0 <= int(band.split("-")[0]) < 45 and figures["n_scenes"] == 1


def test_a_part_the_capture_did_not_measure_is_visible_but_not_measured(t_joint):
    """measured_fractions reads the captured label image: a part whose pixels the sensor lost
    (its label blanked, as a projector's shadow does) is measured 0, the others as visible."""
    from dataclasses import replace

    from binpick.generation.scene import generate_scene
    from binpick.view import ViewParams
    from flows.bench.clutter import measured_fractions

    plain = PARAMS.generate.model_copy(update={"clutter": PARAMS.generate.clutter.off()})
    scene = generate_scene(
        t_joint, plain, changed(PARAMS.camera, downscale=2), ViewParams.of_import(PARAMS.import_capture), 5, n_objects=4
    )
    measured = measured_fractions(scene, t_joint)
    np.testing.assert_allclose(measured, scene.visible_fraction, atol=0.05)
    lost = int(np.argmax(scene.visible_fraction))
    blanked = replace(scene, labels=np.where(scene.labels == lost, -1, scene.labels).astype(scene.labels.dtype))
    after = measured_fractions(blanked, t_joint)
    assert scene.visible_fraction[lost] > 0.5 and after[lost] == 0.0
    np.testing.assert_array_equal(np.delete(after, lost), np.delete(measured, lost))


def test_a_tilted_bench_camera_looks_at_the_bin_centre_at_its_tilt():
    from binpick.generation.scene import tilted_camera
    from binpick.geometry.transforms import invert_T, transform_points
    from flows.bench.clutter import camera_tilt_deg, tilt_band

    for tilt_deg, heading in ((0.0, 0.3), (30.0, 1.0), (45.0, 4.0)):
        T_bin_from_camera = tilted_camera(0.8, np.radians(tilt_deg), heading)
        assert camera_tilt_deg(T_bin_from_camera) == pytest.approx(tilt_deg, abs=1e-9)
        # The bin floor centre lies on the camera's axis, 0.8 m away.
        centre_cam = transform_points(invert_T(T_bin_from_camera), np.zeros((1, 3)))[0]
        np.testing.assert_allclose(centre_cam, [0.0, 0.0, 0.8], atol=1e-12)
    assert [tilt_band(t) for t in (0.0, 14.9, 15.0, 44.0)] == ["0-15", "0-15", "15-30", "30-45"]


def test_the_sensor_bench_judges_no_pick_only_where_a_part_was_there_to_pick():
    from flows.bench.sensors import judges_the_pick

    assert judges_the_pick(sent=True, n_pickable=0) and judges_the_pick(sent=True, n_pickable=3)
    assert judges_the_pick(sent=False, n_pickable=1)  # a visible part, no pick: a failure
    assert not judges_the_pick(sent=False, n_pickable=0)  # nothing to see, nothing sent: right


def test_picking_bench_clears_a_small_bin_and_reports_its_keys():
    from flows.bench.picking import bench_picking

    # The part's own entry (here a bellows cup of 4 mm travel) is what the bench picks with.
    own = changed(PARAMS, pick=changed(PARAMS.pick, suction=changed(PARAMS.pick.suction, stroke_m=0.004)))
    result = bench_picking(
        PARAMS, ["t_joint"], n_bins=1, parts_per_bin=(3, 3), checkpoints={}, part_settings={"t_joint": own}
    )
    part = result["parts"]["t_joint"]
    assert part["contact_touch_m"] == pytest.approx(0.004)
    for key in (
        "pick_success_rate",
        "clearance_rate",
        "wrong_part_picks",
        "collisions",
        "cycle_s_median",
        "n_bins",
        "n_attempts",
    ):
        assert key in part and key in result
    # Every attempt is accounted for: good, wrong part, collision or no pick.
    assert part["n_attempts"] >= part["parts_settled"] * part["clearance_rate"]
    assert part["clearance_rate"] >= 2 / 3 and part["wrong_part_picks"] + part["collisions"] <= 1
    ((band, figures),) = result["by_tilt"].items()
    assert result["tilt_deg_max"] == 45.0 and figures["n_attempts"] == part["n_attempts"]


def test_mixed_picking_bench_clears_a_small_bin_and_names_each_pick_s_part(shared_data):
    """A bin of T-joints and three-way pipes (4 parts, no networks) emptied through the mixed
    scene path: every attempt is counted once, under the part its pick named or as no pick, and
    the parts settled per kind add up to the bin."""
    from flows.bench.mix_picking import bench_picking_mix

    names = ["t_joint", "zju_three_way_pipe"]
    result = bench_picking_mix(PARAMS, names, n_bins=1, parts_per_bin=(4, 4), checkpoints={})
    parts = result["parts"]
    assert set(parts) == set(names)
    assert sum(parts[n]["parts_settled"] for n in names) == result["parts_settled"] >= 3
    assert sum(parts[n]["n_attempts"] for n in names) + result["attempts_without_a_pick"] == result["n_attempts"]
    for key in ("pick_success_rate", "clearance_rate", "wrong_part_picks", "collisions", "cycle_s_median"):
        assert key in result
    assert result["clearance_rate"] >= 2 / 3 and result["wrong_part_picks"] == 0


def test_the_benchmarks_take_a_listed_parts_own_entry(tmp_path):
    """A part's entry in params.yaml (its own gripper) reaches the benchmarks that run it."""
    from flows.cli.bench import part_settings

    text = (ROOT / "params.yaml").read_text()
    entry = "    symmetry: {kind: n_fold, axis: [0.0, 1.0, 0.0], order: 2}\n"
    assert entry in text
    path = tmp_path / "params.yaml"
    path.write_text(text.replace(entry, entry + "    pick: {suction: {cup_radius_m: 0.008, stroke_m: 0.006}}\n", 1))
    resolved = part_settings(path, ["t_joint", "not_listed"])
    assert list(resolved) == ["t_joint"]
    assert resolved["t_joint"].pick.suction.cup_radius_m == 0.008 and resolved["t_joint"].pick.suction.stroke_m == 0.006


def test_a_pick_off_the_part_or_through_a_neighbour_is_caught(t_joint):
    """The benchmark's own judge: a grasp placed on a true part passes, one 5 mm above it or
    whose tool passes through a neighbour fails (or 5 mm into it), unless a bellows cup's travel
    covers the 5 mm."""

    from binpick.geometry.transforms import make_T
    from binpick.io.grasps import tool_frame
    from binpick.picking.plan import Pick
    from flows.bench.picking import TrueSurface, _nearest_surface, _path_hits, _true_touch, touch_m

    T_obj = make_T(np.eye(3), np.array([0.0, 0.0, 0.5]))
    # The camera looks along +z, so the part's top is its model -z side: a contact on the run's
    # outer surface there (radius 12 mm, 20 mm from the branch), approaching along +z.
    truth = TrueSurface(t_joint, PARAMS.pick.suction.cup_radius_m)
    contact = np.array([0.02, 0.0, -0.012])
    T_grasp = T_obj @ tool_frame(contact, np.array([0.0, 0.0, 1.0]))

    def pick(T):
        return Pick(0, "s", 0, 0.0, T, T, T, 1.0, 0.01, 0.0)

    assert _true_touch(pick(T_grasp), "suction", T_obj[None], truth) == 0
    lifted = T_grasp.copy()
    lifted[2, 3] -= 0.005
    assert _true_touch(pick(lifted), "suction", T_obj[None], truth) is None
    distance, angle = _nearest_surface(lifted, T_obj[None], truth)  # what the failed pick missed by
    assert distance == pytest.approx(0.005, abs=1e-4) and angle < 10.0  # the approach the unlifted grasp passed with
    neighbour = make_T(np.eye(3), np.array([0.0, 0.0, 0.44]))  # a second part in the tool's way
    assert not _path_hits(pick(T_grasp), "suction", PARAMS, 0, T_obj[None], t_joint.points_m, np.zeros((0, 3)))
    assert _path_hits(
        pick(T_grasp), "suction", PARAMS, 0, np.stack([T_obj, neighbour]), t_joint.points_m, np.zeros((0, 3))
    )
    # A bellows cup of 12 mm travel, its lip half pressed at the contact, reaches the surface 5 mm
    # beyond it, and gives when the surface lies 5 mm nearer (the tool 5 mm into its target).
    bellows = changed(PARAMS, pick=changed(PARAMS.pick, suction=changed(PARAMS.pick.suction, stroke_m=0.012)))
    assert touch_m(bellows.pick, "suction") == pytest.approx(0.008)
    assert _true_touch(pick(lifted), "suction", T_obj[None], TrueSurface(t_joint, 0.005, 0.008)) == 0
    pressed = T_grasp.copy()
    pressed[2, 3] += 0.005
    assert _path_hits(pick(pressed), "suction", PARAMS, 0, T_obj[None], t_joint.points_m, np.zeros((0, 3)))
    assert not _path_hits(pick(pressed), "suction", bellows, 0, T_obj[None], t_joint.points_m, np.zeros((0, 3)))


def test_the_judge_reads_the_surface_under_the_cup_not_one_facet():
    """A cylinder of 12 facets (30 degrees each): a cup on the fold between two facets,
    approaching along the cylinder's own normal there, is 15 degrees off either facet and sits
    square on the surface under it: it passes; one tilted 20 degrees from that normal fails."""
    import trimesh

    from binpick.geometry.transforms import axis_angle_to_R, make_T
    from binpick.io.grasps import tool_frame
    from binpick.params import SymmetryParams
    from binpick.part.model import make_part_model
    from binpick.picking.plan import Pick
    from flows.bench.picking import TrueSurface, _true_touch

    cylinder = trimesh.creation.cylinder(radius=0.02, height=0.1, sections=12)
    part = make_part_model("rod", cylinder, SymmetryParams(kind="revolution"), 20000, np.random.default_rng(0), "m")
    truth = TrueSurface(part, PARAMS.pick.suction.cup_radius_m)
    T_obj = make_T(np.eye(3), np.array([0.0, 0.0, 0.5]))
    fold = np.array([0.02, 0.0, 0.0])  # a vertex of the 12-gon: where two facets meet
    assert truth.query.on_surface(fold[None])[1][0] < 1e-9

    def pick(approach):
        T = T_obj @ tool_frame(fold, approach)
        return Pick(0, "s", 0, 0.0, T, T, T, 1.0, 0.01, 0.0)

    assert _true_touch(pick(np.array([-1.0, 0.0, 0.0])), "suction", T_obj[None], truth) == 0
    tilted = axis_angle_to_R(np.array([0.0, 0.0, 1.0]), np.radians(20.0)) @ np.array([-1.0, 0.0, 0.0])
    assert _true_touch(pick(tilted), "suction", T_obj[None], truth) is None


def test_scene_bench_bins_hold_twenty_long_parts(t_joint):
    """Bins of a long part dropped as the training scenes are stop filling before 20; the scene
    benchmark's hold the 20 it asks for, of a long part and of the built-in one."""
    import trimesh

    from binpick.generation.placement import place_objects
    from binpick.params import SymmetryParams
    from binpick.part.model import make_part_model
    from flows.bench.picking import picking_settings
    from flows.bench.scene import scene_generate_settings

    # The gear shaft's proportions: a 0.44 m body of 60 mm girth with a 100 mm gear on it.
    body, gear = (
        trimesh.creation.cylinder(radius=0.03, height=0.44),
        trimesh.creation.cylinder(radius=0.05, height=0.06),
    )
    gear.apply_translation([0.0, 0.0, 0.1])
    shaft = make_part_model(
        "shaft",
        trimesh.util.concatenate([body, gear]),
        SymmetryParams(kind="revolution", axis=(0, 0, 1)),
        20000,
        np.random.default_rng(0),
        "m",
    )

    def held(part, g, seeds=(0, 1, 2)):
        return [
            len(place_objects(part.points_m, 20, g.bin, g.placement, np.random.default_rng(k)).T_bin_from_model)
            for k in seeds
        ]

    p = picking_settings(PARAMS, shaft)
    # The premise: the training scenes' 8 drops a part leave room in such a bin unfound.
    eight = p.generate.model_copy(
        update={"placement": p.generate.placement.model_copy(update={"mode": "drop", "candidates_per_object": 8})}
    )
    assert min(held(shaft, eight)) < 20
    assert held(shaft, scene_generate_settings(shaft, p)) == [20, 20, 20]
    assert held(t_joint, scene_generate_settings(t_joint, picking_settings(PARAMS, t_joint))) == [20, 20, 20]


def test_the_report_plots_the_figures_of_a_folder_of_benchmark_files(tmp_path):
    import json
    import subprocess
    import sys

    from flows.bench.report import ALL_PARTS, collect, report

    machine = {"cpu_model": "Test CPU", "cores_usable": 2, "cuda": None}
    (tmp_path / "scene.json").write_text(
        json.dumps(
            {
                "machine": machine,
                "pose_precision": 0.9,
                "parts": {
                    "t_joint": {"pose_precision": 1.0, "pose_recall": 0.75, "register_s_median": 0.4, "ok": True},
                    "nut": {"pose_precision": 0.5, "pose_recall": 0.25, "register_s_median": 0.2},
                },
            }
        )
    )
    (tmp_path / "cell.json").write_text(
        json.dumps(
            {
                "machine": machine,
                "parts": {
                    "t_joint": {"cycle_s": [1.0, 2.0, 3.0], "picks_per_hour": 480.0, "baseline_picks_per_hour": 0}
                },
            }
        )
    )
    figures, machines = collect(tmp_path)
    got = {(f.bench, f.part, f.key): f.value for f in figures}
    assert got[("scene", "nut", "pose_recall")] == 0.25
    assert got[("scene", ALL_PARTS, "pose_precision")] == 0.9
    assert got[("cell", "t_joint", "cycle_s")] == [1.0, 2.0, 3.0]
    assert ("scene", "t_joint", "ok") not in got  # a flag is not a figure
    assert set(machines) == {"scene", "cell"}
    written = report(tmp_path, tmp_path / "report")
    names = {p.name for p in written}
    assert names == {"precision_recall.png", "cycle_times.png", "step_timings.png", "picks_per_hour.png"}
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in written)
    page = (tmp_path / "report" / "index.html").read_text()
    assert all(f'src="{n}"' in page for n in names) and "Test CPU" in page
    assert all(f"({n})" in (tmp_path / "report" / "plots.md").read_text() for n in names)
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = subprocess.run(
        [sys.executable, "-m", "flows.cli", "bench", "report", str(empty)], capture_output=True, text=True
    )
    assert proc.returncode == 2 and proc.stderr.strip().endswith(
        "has no benchmark JSON files (binpick bench ... --out writes them)"
    )
    assert "Traceback" not in proc.stderr
