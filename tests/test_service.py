"""The pick service answers over HTTP and the TCP line protocol with the poses and picks of a
rendered bin (known poses), refuses bad requests with a clear answer and keeps running, keeps
each request for review within its retention limit, and a kept request joins the batch pipeline."""

from __future__ import annotations

import base64
import hashlib
import json
import socket
import threading
import time

import numpy as np
import pytest
from conftest import ROOT, copy_project

from binpick.generation.scene import generate_scene
from binpick.geometry.symmetry import symmetry_transforms
from binpick.io.grasps import save_grasps
from binpick.io.part_model import save_part_model
from binpick.io.ppf_model import save_ppf_model
from binpick.io.zdf import save_zdf_v1
from binpick.metrics.pose import scene_pose_metrics
from binpick.params import load_params
from binpick.picking.grasps import REVOLUTION_GRASP_STEPS, expand_by_symmetry, generate_grasps
from binpick.registration.model import train_ppf
from binpick.view import ViewParams
from flows.bench import free_port

httpx = pytest.importorskip("httpx")


@pytest.fixture(scope="module")
def project(tmp_path_factory, t_joint):
    """A project with the built-in part's models built (no network) and a rendered capture."""
    root = copy_project(tmp_path_factory.mktemp("service"))
    text = (root / "params.yaml").read_text().replace("keep_requests: 500", "keep_requests: 3")
    (root / "params.yaml").write_text(text)
    p = load_params(root / "params.yaml", "t_joint")
    folder = root / "data" / "models" / "t_joint"
    folder.mkdir(parents=True)
    save_part_model(folder / "part.npz", t_joint)
    save_ppf_model(
        folder / "ppf.npz",
        train_ppf(
            t_joint.points_m, t_joint.normals, t_joint.diameter_m, symmetry_transforms(t_joint.symmetry), p.registration
        ),
    )
    grasps = {
        k: expand_by_symmetry(g, symmetry_transforms(t_joint.symmetry, REVOLUTION_GRASP_STEPS))
        for k, g in generate_grasps(t_joint, p.pick).items()
    }
    save_grasps(folder / "grasps.json", "t_joint", grasps, "generated")
    generate = p.generate.model_copy(update={"clutter": p.generate.clutter.off()})
    scene = generate_scene(
        t_joint,
        generate,
        p.camera.model_copy(update={"downscale": 2}),
        ViewParams.of_import(p.import_capture),
        5,
        n_objects=4,
    )
    H, W = scene.labels.shape
    capture = root / "data" / "captures" / "bin.zdf"
    capture.parent.mkdir(parents=True)
    save_zdf_v1(capture, scene.xyz_m.reshape(H, W, 3) * 1000.0)
    return root, scene, capture


@pytest.fixture(scope="module")
def server(project):
    """The service on free loopback ports, in this process; stopped after the module."""
    import uvicorn

    from flows.service import PickService
    from flows.service_http import http_app

    root, _, _ = project
    service = PickService(root, root / "params.yaml", keep_mlflow=False)
    service.settings = service.settings.model_copy(update={"http_port": free_port(), "tcp_port": free_port()})
    config = uvicorn.Config(http_app(service), host="127.0.0.1", port=service.settings.http_port, log_level="warning")
    web = uvicorn.Server(config)
    thread = threading.Thread(target=web.run, daemon=True)
    thread.start()
    for _ in range(200):
        if web.started:
            break
        time.sleep(0.05)
    yield service, f"http://127.0.0.1:{service.settings.http_port}"
    web.should_exit = True
    thread.join(timeout=10)
    service.close()


def _check_poses(answer: dict, scene, t_joint) -> None:
    T = np.array([p["T_cam_from_model"] for p in answer["poses"]]).reshape(-1, 4, 4)
    summary, _ = scene_pose_metrics(
        T,
        scene.T_cam_from_model,
        scene.visible_fraction,
        t_joint.points_m,
        symmetry_transforms(t_joint.symmetry),
        t_joint.diameter_m,
    )
    assert summary["pose_precision"] == 1.0 and summary["pose_recall"] >= 0.75, summary


def test_http_answers_picks_for_an_upload_and_a_named_file(server, project, t_joint):
    service, url = server
    root, scene, capture = project
    assert httpx.get(f"{url}/health").json()["parts"] == ["t_joint"]
    upload = httpx.post(
        f"{url}/picks",
        params={"part": "t_joint", "format": "zdf"},
        content=capture.read_bytes(),
        headers={"content-type": "application/octet-stream"},
        timeout=120,
    )
    assert upload.status_code == 200, upload.text
    answer = upload.json()
    assert answer["format"] == "binpick-picks" and answer["picks"], answer.get("unpicked")
    _check_poses(answer, scene, t_joint)
    for step in ("read_s", "clean_s", "register_s", "pick_s", "pipeline_s"):
        assert answer["timings_s"][step] >= 0
    # The first pick's grasp lies on the pose it names (the grasp applied to that pose).
    first = answer["picks"][0]
    T_base_from_cam = np.asarray(answer["T_base_from_cam"])
    assert np.allclose(T_base_from_cam @ np.asarray(first["camera"]["grasp"]), first["base"]["grasp"])
    # The arm was checked: its joints put the tool at the grasp (forward kinematics).
    from binpick.robot.arm import load_arm

    flange = load_arm("ur5e").flange_pose(first["arm"]["joints_rad"]["grasp"])
    T_flange_from_tcp = np.asarray(load_params(ROOT / "params.yaml").cell.T_flange_from_tcp)
    assert np.allclose(flange @ T_flange_from_tcp, first["base"]["grasp"], atol=1e-6)
    named = httpx.post(
        f"{url}/picks", json={"part": "t_joint", "path": str(capture.relative_to(root))}, timeout=120
    ).json()
    # The same capture, the same answer.
    assert [(p["pose_index"], p["grasp_id"]) for p in named["picks"]] == [
        (p["pose_index"], p["grasp_id"]) for p in answer["picks"]
    ]
    assert np.allclose(
        [p["T_cam_from_model"] for p in named["poses"]], [p["T_cam_from_model"] for p in answer["poses"]], atol=1e-6
    )
    # The controller reports that the first pick's grip failed: no pick goes there again.
    failed_at = np.asarray(first["camera"]["grasp"])[:3, 3]
    again = httpx.post(
        f"{url}/picks",
        json={"part": "t_joint", "path": str(capture.relative_to(root)), "failed_grasps": [failed_at.tolist()]},
        timeout=120,
    ).json()
    assert again["picks"], again.get("unpicked")
    lip_m = 2.0 * load_params(ROOT / "params.yaml").pick.suction.cup_radius_m
    grasps = np.array([np.asarray(p["camera"]["grasp"])[:3, 3] for p in again["picks"]])
    assert np.min(np.linalg.norm(grasps - failed_at, axis=1)) > lip_m
    assert (again["picks"][0]["pose_index"], again["picks"][0]["grasp_id"]) != (first["pose_index"], first["grasp_id"])


def test_bad_requests_get_clear_errors_and_the_service_goes_on(server, project):
    service, url = server
    root, _, capture = project
    cases = [
        (httpx.post(f"{url}/picks", json={"part": "gizmo", "path": "x.ply"}), 404, "unknown part 'gizmo'"),
        (
            httpx.post(f"{url}/picks", json={"part": "t_joint", "path": "x.ply", "unit": "furlong"}),
            400,
            "unit 'furlong'",
        ),
        (httpx.post(f"{url}/picks", json={"part": "t_joint", "path": "/etc/passwd"}), 400, "outside the project"),
        (httpx.post(f"{url}/picks", json={"part": "t_joint", "path": "data/none.ply"}), 400, "not found"),
        (httpx.post(f"{url}/picks", json={"part": "t_joint"}), 400, "names a capture"),
        (httpx.post(f"{url}/picks", params={"part": "t_joint"}, content=b"x" * 100), 400, "needs its format"),
        (
            httpx.post(f"{url}/picks", params={"part": "t_joint", "format": "ply"}, content=b"ply\nformat nonsense\n"),
            400,
            "capture",
        ),
        (
            httpx.post(f"{url}/picks", content=b"{not json", headers={"content-type": "application/json"}),
            400,
            "not JSON",
        ),
    ]
    cases.append(
        (httpx.post(f"{url}/picks", json={"part": "t_joint", "path": "x.ply", "pose_format": "staubli"}), 400, "ur")
    )
    for failed in ([[0.1, 0.2]], "0.1,0.2,0.3;0.4,x,0.6"):
        cases.append(
            (
                httpx.post(f"{url}/picks", json={"part": "t_joint", "path": "x.ply", "failed_grasps": failed}),
                400,
                "failed_grasps",
            )
        )
    for response, status, words in cases:
        assert response.status_code == status, response.text
        assert words in response.json()["error"]
        # An answer names the client's own words, never where the service's project lies.
        assert str(root) not in response.text and str(root.resolve()) not in response.text
    # Messages from deeper down (a reload refused names params.yaml) are made relative to the project.
    assert service.public(f"no part of {root / 'params.yaml'} can be served") == "no part of params.yaml can be served"
    limits = service.settings
    service.settings = limits.model_copy(update={"max_request_mb": 0.001})
    try:
        big = httpx.post(
            f"{url}/picks", params={"part": "t_joint", "format": "zdf"}, content=capture.read_bytes()[:10000]
        )
        assert big.status_code == 413 and "max_request_mb" in big.json()["error"]
    finally:
        service.settings = limits
    assert httpx.get(f"{url}/health").json()["status"] == "ok"


def test_the_line_protocol_answers_one_json_line_per_request(server, project, t_joint):
    service, _ = server
    root, scene, capture = project
    with socket.create_connection(("127.0.0.1", service.settings.tcp_port), timeout=120) as s:
        stream = s.makefile("rwb")

        def ask(obj) -> dict:
            stream.write((obj if isinstance(obj, bytes) else json.dumps(obj).encode()) + b"\n")
            stream.flush()
            return json.loads(stream.readline())

        assert ask({"health": True})["parts"] == ["t_joint"]
        assert "not JSON" in ask(b"{oops")["error"]
        answer = ask({"part": "t_joint", "data_b64": base64.b64encode(capture.read_bytes()).decode(), "format": "zdf"})
        assert answer["picks"], answer
        _check_poses(answer, scene, t_joint)
        named = ask({"part": "t_joint", "path": str(capture), "pose_format": "ur"})
        assert named["picks"][0]["grasp_id"] == answer["picks"][0]["grasp_id"]
        # The UR's p[x, y, z, rx, ry, rz] of each pose is the base-frame matrix's.
        assert named["pose_format"] == "ur" and named["pose_fields"][3] == "rx_rad"
        from binpick.robot.pose_formats import from_robot

        for pick in named["picks"]:
            for waypoint in ("pregrasp", "grasp", "postgrasp"):
                assert np.allclose(from_robot(pick["robot"][waypoint], "ur"), pick["base"][waypoint], atol=1e-6)
            assert np.allclose(from_robot(pick["robot"]["place"], "ur"), pick["arm"]["place_tcp_base"], atol=1e-6)
        assert "robot" not in answer["picks"][0] and answer["pose_format"] == "matrix"


def test_a_robot_controller_asks_in_words_and_reads_numbers(server, project):
    """The text command the UR script (clients/ur/binpick_pick.script) sends, answered in the
    "(n1,...,n25)" form URScript's socket_read_ascii_float reads."""
    from binpick.robot.pose_formats import from_robot

    service, url = server
    root, _, capture = project
    relative = str(capture.relative_to(root))
    with socket.create_connection(("127.0.0.1", service.settings.tcp_port), timeout=120) as s:
        stream = s.makefile("rwb")

        def ask(line: str) -> list[float]:
            stream.write(line.encode() + b"\n")
            stream.flush()
            text = stream.readline().decode().strip()
            assert text.startswith("(") and text.endswith(")"), text
            return [float(x) for x in text[1:-1].split(",")]

        ur = ask(f"PICK t_joint ur {relative}")
        kuka = ask(f"pick t_joint kuka {relative}")
        assert len(ur) == 25 and ur[0] == 1.0
        assert ask(f"PICK gizmo {relative}")[0] == -404.0
        assert ask("HELLO")[0] == -400.0
        service.token = "s3cret"
        try:
            assert ask(f"PICK t_joint {relative}")[0] == -401.0
            assert ask("TOKEN s3cret") == [1.0]
            assert ask(f"PICK t_joint {relative}")[:7] == ur[:7]  # ur is the default
        finally:
            service.token = None
    json_answer = httpx.post(f"{url}/picks", json={"part": "t_joint", "path": relative}, timeout=120).json()
    first = json_answer["picks"][0]
    for k, waypoint in enumerate(("pregrasp", "grasp", "postgrasp")):
        assert np.allclose(from_robot(ur[1 + 6 * k : 7 + 6 * k], "ur"), first["base"][waypoint], atol=1e-5)
        assert np.allclose(from_robot(kuka[1 + 6 * k : 7 + 6 * k], "kuka"), first["base"][waypoint], atol=1e-5)
    assert np.allclose(from_robot(ur[19:25], "ur"), first["arm"]["place_tcp_base"], atol=1e-5)


def test_the_ur_script_speaks_the_service_and_cell_settings():
    """The URScript client's settings are the project's defaults and it reads what the service sends."""
    import re

    script = (ROOT / "clients" / "ur" / "binpick_pick.script").read_text()
    p = load_params(ROOT / "params.yaml")
    assert f"BINPICK_PORT = {p.service.tcp_port}" in script
    tcp = [float(x) for x in re.search(r"TCP = p\[([^\]]*)\]", script).group(1).split(",")]
    assert np.allclose(tcp[:3], np.asarray(p.cell.T_flange_from_tcp)[:3, 3]) and np.allclose(tcp[3:], 0)
    assert np.allclose(np.asarray(p.cell.T_flange_from_tcp)[:3, :3], np.eye(3))
    home = [float(x) for x in re.search(r"HOME = \[([^\]]*)\]", script).group(1).split(",")]
    assert np.allclose(home, p.cell.home_q_rad)
    assert "socket_read_ascii_float(25" in script and '" ur"' in script
    assert max(int(i) for i in re.findall(r"r\[(\d+)\]", script)) == 25


def test_the_python_client_gets_picks_and_reads_refusals(server, project):
    from binpick.client import PickClient, PickServiceError
    from binpick.robot.pose_formats import from_robot

    service, url = server
    root, _, capture = project
    client = PickClient(url)
    assert client.health()["parts"] == ["t_joint"]
    answer = client.picks_from_file("t_joint", capture, pose_format="fanuc")
    assert answer["pose_fields"][3:] == ["W_deg", "P_deg", "R_deg"]
    first = answer["picks"][0]
    assert np.allclose(from_robot(first["robot"]["grasp"], "fanuc"), first["base"]["grasp"], atol=1e-5)
    assert client.picks_at("t_joint", str(capture.relative_to(root)))["picks"][0]["grasp_id"] == first["grasp_id"]
    with pytest.raises(PickServiceError) as refused:
        client.picks_at("t_joint", "data/none.ply")
    assert refused.value.status == 400 and "not found" in refused.value.message


def _browser():
    """Headless Chromium driven by its own chromedriver (Debian's chromium and chromium-driver)."""
    import shutil

    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (make setup)")
    chromium = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    driver = shutil.which("chromedriver")
    if chromium is None or driver is None:
        pytest.skip("no Chromium with chromedriver on this machine (Debian: apt-get install chromium chromium-driver)")
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    flags = ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1280,1600")
    for flag in flags:
        options.add_argument(flag)
    return webdriver.Chrome(options=options, service=webdriver.ChromeService(executable_path=driver))


def _gone(element):
    """A wait condition: the element no longer belongs to the page. Chromium answers a look at a
    node taken away mid-reload either as stale or as an inspector error ("Node with given id does
    not belong to the document"); selenium's staleness_of knows only the first."""
    from selenium.common.exceptions import StaleElementReferenceException, WebDriverException

    def check(_driver) -> bool:
        try:
            element.is_enabled()
        except StaleElementReferenceException:
            return True
        except WebDriverException as exc:
            if "does not belong to the document" in str(exc):
                return True
            raise
        return False

    return check


def test_the_operator_page_shows_the_latest_capture_and_the_requests_in_a_browser(server, project):
    service, url = server
    root, _, capture = project
    relative = str(capture.relative_to(root))
    assert httpx.post(f"{url}/picks", json={"part": "t_joint", "path": relative}, timeout=120).status_code == 200
    assert httpx.post(f"{url}/picks", json={"part": "gizmo", "path": relative}, timeout=120).status_code == 404
    deadline = time.time() + 60
    while service._keeper._jobs.unfinished_tasks and time.time() < deadline:  # the image is drawn after the answer
        time.sleep(0.1)
    browser = _browser()
    try:
        from selenium.webdriver.common.by import By

        browser.get(url + "/?refresh=0")  # held still: a reload between two looks would stale the elements
        image = browser.find_element(By.ID, "latest")
        for _ in range(100):
            if browser.execute_script("return arguments[0].complete && arguments[0].naturalWidth", image):
                break
            time.sleep(0.1)
        assert browser.execute_script("return arguments[0].naturalWidth", image) > 100
        rows = browser.find_elements(By.CSS_SELECTOR, "#requests tbody tr")
        assert rows and "refused" in rows[0].text and "pick" in rows[1].text
        assert browser.find_element(By.ID, "parts").text == "t_joint"
        assert "404 unknown part" in browser.page_source
        recordings = browser.find_elements(By.LINK_TEXT, "scene.rrd")
        assert recordings
        assert httpx.get(recordings[0].get_attribute("href")).content[:4] == b"RRF2"
        # Read-only without the token once the service has one.
        assert browser.find_elements(By.TAG_NAME, "button")  # no token: the reload is offered
        service.token = "s3cret"
        try:
            browser.get(url + "/?refresh=0")
            assert not browser.find_elements(By.TAG_NAME, "button")
            browser.get(url + "/?token=s3cret&refresh=0")
            button = browser.find_element(By.TAG_NAME, "button")
            button.click()
            # The form posts, the service reloads the parts and sends the browser back to the page.
            from selenium.webdriver.support import expected_conditions
            from selenium.webdriver.support.wait import WebDriverWait

            WebDriverWait(browser, 60).until(_gone(button))
            parts = WebDriverWait(browser, 60).until(expected_conditions.presence_of_element_located((By.ID, "parts")))
            assert parts.text == "t_joint"
        finally:
            service.token = None
        page = browser.page_source
    finally:
        browser.quit()
    assert str(root) not in page and str(root.resolve()) not in page
    state = httpx.get(f"{url}/operator/state").json()
    assert state["refusals"]["404 unknown part"] >= 1 and state["picks_per_hour"] > 0
    assert httpx.get(f"{url}/requests/..%2F..%2Fparams.yaml/picks.json").status_code == 404
    kept = state["requests"][1]["request_id"]
    assert httpx.get(f"{url}/requests/{kept}/request.json").status_code == 404  # it names this machine's paths


def test_the_operator_figures_count_the_last_hour():
    from flows.operator import Outcome, summarise

    now = 10_000.0
    items = [
        Outcome(now - 1800, "a", "p", 200, 3, 1, 0.5),
        Outcome(now - 1200, "b", "p", 200, 2, 0, 0.7, "too far tilted", ("too far tilted",)),
        Outcome(now - 600, None, "p", 503, why="busy"),
        Outcome(now - 60, "c", "p", 200, 4, 1, 0.6, "", ("arm hits the bin wall",)),
    ]
    figures = summarise(items, now)
    assert figures["picks_per_hour"] == 4.0  # 2 picks over the 30 minutes since the first request
    assert figures["failure_rate"] == 0.5 and figures["total_s_median"] == 0.6
    assert figures["refusals"] == {"503 busy": 1}
    assert figures["unpicked"] == {"too far tilted": 1, "arm hits the bin wall": 1}


def test_a_token_is_required_once_set(server):
    service, url = server
    service.token = "s3cret"
    try:
        assert httpx.get(f"{url}/health").status_code == 401
        assert httpx.get(f"{url}/health", headers={"authorization": "Bearer s3cret"}).status_code == 200
    finally:
        service.token = None


def test_requests_are_kept_within_the_limit_and_one_joins_the_pipeline(server, project):
    import subprocess
    import sys

    from flows.service_keeper import list_requests

    service, url = server
    root, _, capture = project
    for _ in range(2):
        assert (
            httpx.post(f"{url}/picks", json={"part": "t_joint", "path": str(capture)}, timeout=120).status_code == 200
        )
    deadline = time.time() + 60
    while service._keeper._jobs.unfinished_tasks and time.time() < deadline:  # the keeper works after the answer
        time.sleep(0.1)
    time.sleep(0.5)
    kept = list_requests(root / "data" / "service" / "requests")
    assert len(kept) == 3  # service.keep_requests
    newest = kept[0]
    for name in ("capture.zdf", "picks.json", "poses.json", "request.json", "scene.rrd"):
        assert (newest / name).is_file(), name
    proc = subprocess.run(
        [sys.executable, "-m", "flows.cli", "requests", "--add", "latest"],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    entry = next(c for n, c in load_params(root / "params.yaml").captures.items() if n != "demo")
    assert entry.part == "t_joint" and (root / entry.file).read_bytes() == capture.read_bytes()
    listing = subprocess.run(
        [sys.executable, "-m", "flows.cli", "requests"], cwd=root, capture_output=True, text=True, timeout=120
    )
    assert listing.returncode == 0 and newest.name in listing.stdout


def test_the_command_refuses_a_port_in_use_and_an_open_bind_without_token(project):
    import subprocess
    import sys

    root, _, _ = project
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        proc = subprocess.run(
            [sys.executable, "-m", "flows.cli", "service", "--http-port", str(port)],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert proc.returncode == 2 and "cannot listen" in proc.stderr and "Traceback" not in proc.stderr
    env = {k: v for k, v in __import__("os").environ.items() if k != "BINPICK_TOKEN"}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "flows.cli",
            "service",
            "--host",
            "0.0.0.0",
            "--http-port",
            str(free_port()),
            "--tcp-port",
            "0",
        ],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert proc.returncode == 2 and "needs a token" in proc.stderr


def test_the_schema_describes_requests_and_answers(server):
    _, url = server
    schema = httpx.get(f"{url}/openapi.json").json()
    body = schema["paths"]["/picks"]["post"]["requestBody"]["content"]
    assert {"application/json", "application/octet-stream"} <= set(body)
    assert {"part", "path", "camera", "unit"} <= set(body["application/json"]["schema"]["properties"])
    answer = schema["components"]["schemas"]["PicksAnswer"]["properties"]
    assert {"picks", "poses", "request_id", "T_base_from_cam"} <= set(answer)
    assert "/reload" in schema["paths"]


def test_a_part_trained_later_is_served_after_a_reload_and_a_refused_network_is_not(server, project):
    """The project gains a part while the service runs: /reload serves it without a restart, while
    a request in progress is answered; a part whose network evaluate refused is not served, and
    /health says why."""
    import shutil

    import yaml

    service, url = server
    root, _, capture = project
    raw = yaml.safe_load((root / "params.yaml").read_text())
    raw["parts"]["t_joint_b"] = dict(raw["parts"]["t_joint"])
    raw["pick"]["part_priority"] = ["t_joint_b"]  # a mixed bin's picks: t_joint_b's first
    (root / "params.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))
    shutil.copytree(root / "data" / "models" / "t_joint", root / "data" / "models" / "t_joint_b")
    assert httpx.get(f"{url}/health").json()["parts"] == ["t_joint"]

    answers: list[int] = []
    during = threading.Thread(
        target=lambda: answers.append(
            httpx.post(f"{url}/picks", json={"part": "t_joint", "path": str(capture)}, timeout=120).status_code
        )
    )
    during.start()
    time.sleep(0.2)
    reloaded = httpx.post(f"{url}/reload", timeout=120)
    during.join()
    assert answers == [200] and reloaded.status_code == 200, reloaded.text
    assert reloaded.json()["parts"] == ["t_joint", "t_joint_b"]
    assert httpx.post(f"{url}/picks", json={"part": "t_joint_b", "path": str(capture)}, timeout=120).json()["picks"]

    network = root / "data" / "fpcc" / "t_joint_b" / "model.pt"
    network.parent.mkdir(parents=True)
    network.write_bytes(b"a network the evaluate stage judged")
    metrics = root / "data" / "metrics" / "t_joint_b" / "evaluate.json"
    metrics.parent.mkdir(parents=True)
    metrics.write_text(json.dumps({"accepted": 0.0, "precision": 0.41, "recall": 0.3}))
    health = httpx.post(f"{url}/reload", timeout=120).json()
    assert health["parts"] == ["t_joint"] and "not accepted" in health["not_served"]["t_joint_b"]
    assert httpx.post(f"{url}/picks", json={"part": "t_joint_b", "path": str(capture)}, timeout=120).status_code == 404
    # Accepted, but for another file than the one now there: retrained since, not served.
    metrics.write_text(
        json.dumps({"accepted": 1.0, "checkpoint_sha256": hashlib.sha256(b"an older network").hexdigest()})
    )
    health = httpx.post(f"{url}/reload", timeout=120).json()
    assert health["parts"] == ["t_joint"] and "not been evaluated since" in health["not_served"]["t_joint_b"]
    network.unlink()
    assert httpx.post(f"{url}/reload", timeout=120).json()["parts"] == ["t_joint", "t_joint_b"]

    # A mixed request: two parts of the same shape claim every instance; each region goes to one.
    single = httpx.post(f"{url}/picks", json={"part": "t_joint", "path": str(capture)}, timeout=120).json()
    mixed = httpx.post(
        f"{url}/picks",
        params={"parts": "t_joint,t_joint_b", "format": "zdf", "pose_format": "ur"},
        content=capture.read_bytes(),
        headers={"content-type": "application/octet-stream"},
        timeout=120,
    )
    assert mixed.status_code == 200, mixed.text
    answer = mixed.json()
    assert answer["parts"] == ["t_joint", "t_joint_b"] and "part" not in answer
    # Each instance posed once. The second part's whole-scene pass votes from none of the points
    # the first part's poses claim, so only its segments' poses meet the first's in a conflict.
    assert len(answer["poses"]) == len(single["poses"]) and 1 <= len(answer["conflicts"]) <= len(single["poses"])
    assert {p["part"] for p in answer["poses"]} <= {"t_joint", "t_joint_b"}
    named = [p["part"] for p in answer["picks"]]
    assert named == sorted(named, key=lambda n: n != "t_joint_b")  # pick.part_priority's part first
    for pick in answer["picks"]:
        assert answer["poses"][pick["pose_index"]]["part"] == pick["part"] and len(pick["robot"]["grasp"]) == 6
    refused = [
        httpx.post(f"{url}/picks", json={"parts": ["t_joint", "gizmo"], "path": str(capture)}),
        httpx.post(f"{url}/picks", json={"part": "t_joint", "parts": ["t_joint"], "path": str(capture)}),
    ]
    assert [r.status_code for r in refused] == [404, 400] and "not both" in refused[1].json()["error"]
    # What the kit still needs: one t_joint, no t_joint_b; the other picks are left, with the reason.
    kit = httpx.post(
        f"{url}/picks",
        params={"parts": "t_joint,t_joint_b", "format": "zdf", "quota": "t_joint:1,t_joint_b:0"},
        content=capture.read_bytes(),
        headers={"content-type": "application/octet-stream"},
        timeout=120,
    ).json()
    assert [p["part"] for p in kit["picks"]] == ["t_joint"]
    assert len(kit["unpicked"]) >= len(answer["picks"]) - 1 and any("quota" in u["reason"] for u in kit["unpicked"])
    bad = httpx.post(f"{url}/picks", params={"parts": "t_joint,t_joint_b", "quota": "t_joint:many"}, content=b"x")
    assert bad.status_code == 400 and "part:count" in bad.json()["error"]


def test_a_network_is_served_only_when_evaluate_judged_these_bytes(tmp_path):
    from binpick.layout import Layout
    from flows.service import _not_accepted

    layout = Layout(tmp_path)
    assert _not_accepted(layout, "p") is None  # no network: registration only
    layout.checkpoint("p").parent.mkdir(parents=True)
    layout.checkpoint("p").write_bytes(b"weights")
    assert "not been evaluated" in _not_accepted(layout, "p")
    metrics = layout.part_metrics("p", "evaluate")
    metrics.parent.mkdir(parents=True)
    metrics.write_text(json.dumps({"accepted": 1.0, "checkpoint_sha256": hashlib.sha256(b"weights").hexdigest()}))
    assert _not_accepted(layout, "p") is None
    layout.checkpoint("p").write_bytes(b"weights, retrained")
    assert "since it was trained" in _not_accepted(layout, "p")
