"""Site maps over HTTP, against a real server: create, add scans, read, follow the events, delete; one
writer per map (409 with Retry-After); unknown ids 404; a scan's upload limits and errors are
/correspond's.  The client and ``shadowcorr-client map`` talk to the same server."""

from __future__ import annotations

import json
import threading
import time

import httpx
import numpy as np
import pytest

from shadowcorr_client import ShadowCorrClient
from shadowcorr_client.cli import main as client_main
from shadowcorr_client.errors import ResponseError
from shadowcorr.io import write_bundle

from .harness import ServerProcess, zipped_bundle
from .scenes import sphere_scene

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

CENTRES = np.array([[0, 0, 45], [140, 20, 40], [-100, 110, 42], [40, -150, 38]], float)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    srv = ServerProcess(["--workers", "1", "--max-views", "4", "--maps-dir", str(tmp_path_factory.mktemp("maps")),
                         "--retry-after-s", "3"])
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def ring():
    return sphere_scene(CENTRES, CENTRES[:, 2], cameras=6, width=240, height_px=135)


def views(bundle, *indices):
    import dataclasses

    return dataclasses.replace(bundle, views=[bundle.views[i] for i in indices])


def test_a_map_grows_scan_by_scan_over_http(server, ring) -> None:
    with ShadowCorrClient(server.url, timeout=120.0) as client:
        map_id = client.create_map()
        first = client.add_scan(map_id, views(ring, 0, 1), name="first")
        assert first["scan"] == 1 and first["name"] == "first"
        assert {e["kind"] for e in first["events"]} == {"created"}
        second = client.add_scan(map_id, views(ring, 3, 4))
        assert {e["kind"] for e in second["events"]} == {"observed"}
        assert len(second["linked_views"]) == 2 and "network" in second["timings_ms"]
        # Each sphere is one object, and every segment of the second scan got its sphere's id from the first.
        ids = {(s["view"], s["instance"]): s["object"] for s in first["segments"] + second["segments"]}
        for instance in range(1, len(CENTRES) + 1):
            assert len({o for (_, i), o in ids.items() if i == instance}) == 1
        state = client.get_map(map_id)
        assert [s["scan"] for s in state["scans"]] == [1, 2] and len(state["objects"]) == len(CENTRES)
        assert len(state["segments"]) == len(first["segments"]) + len(second["segments"])
        last_of_first = max(e["event"] for e in first["events"])
        assert [e["event"] for e in client.map_events(map_id, since=last_of_first)] == [
            e["event"] for e in second["events"]]
        client.delete_map(map_id)
        with pytest.raises(ResponseError) as gone:
            client.get_map(map_id)
        assert gone.value.status == 404 and gone.value.error == "map_not_found"


def test_unknown_ids_and_bad_queries(server) -> None:
    with httpx.Client(base_url=server.url, timeout=30.0) as http:
        for path in ("/maps/0123", "/maps/../../etc/passwd", "/maps/" + "a" * 32, "/maps/" + "A" * 32 + "/events"):
            r = http.get(path)
            assert r.status_code == 404 and r.json()["error"] in ("map_not_found", "not_found"), path
        assert http.delete("/maps/" + "f" * 32).status_code == 404
        assert http.post("/maps/" + "f" * 32 + "/scans", files={"bundle": ("b.zip", b"x")}).status_code == 404
        map_id = http.post("/maps").json()["map"]
        r = http.get(f"/maps/{map_id}/events", params={"since": "-1"})
        assert r.status_code == 422 and r.json()["error"] == "invalid_options"
        assert http.get(f"/maps/{map_id}").json()["scans"] == []


def test_a_scans_upload_gets_the_limits_and_errors_of_correspond(server, ring) -> None:
    too_many, _, _ = zipped_bundle(views(ring, 0, 1, 2, 3, 4))  # the server takes 4 views
    with httpx.Client(base_url=server.url, timeout=60.0) as http:
        map_id = http.post("/maps").json()["map"]
        for body in ({"bundle": ("b.zip", too_many)}, {"bundle": ("b.zip", b"not a zip")}):
            scan, correspond = (http.post(path, files=body) for path in (f"/maps/{map_id}/scans", "/correspond"))
            assert scan.status_code == correspond.status_code == 422
            assert scan.json()["error"] == correspond.json()["error"] == "invalid_bundle"
            assert scan.json()["problems"] == correspond.json()["problems"]
        r = http.post(f"/maps/{map_id}/scans", content=b"{}", headers={"Content-Type": "application/json"})
        assert r.status_code == 415 and r.json()["error"] == "unsupported_media_type"
        assert http.get(f"/maps/{map_id}").json()["scans"] == []  # nothing of the refused scans was kept


def test_one_writer_per_map(server, ring) -> None:
    zipped, _, _ = zipped_bundle(views(ring, 0, 1))
    request = httpx.Request("POST", f"{server.url}/maps/x/scans", files={"bundle": ("b.zip", zipped)})
    body, content_type = request.read(), request.headers["Content-Type"]

    def slowly():  # the first scan holds its map while its body arrives
        yield body[:1024]
        time.sleep(2.0)
        yield body[1024:]

    with httpx.Client(base_url=server.url, timeout=120.0) as http:
        map_id = http.post("/maps").json()["map"]
        first: dict = {}
        sender = threading.Thread(target=lambda: first.update(r=http.post(
            f"/maps/{map_id}/scans", content=slowly(), headers={"Content-Type": content_type})))
        sender.start()
        time.sleep(0.8)
        with httpx.Client(base_url=server.url, timeout=60.0) as other:
            second = other.post(f"/maps/{map_id}/scans", files={"bundle": ("b.zip", zipped)})
            deleting = other.delete(f"/maps/{map_id}")
            reading = other.get(f"/maps/{map_id}")
            elsewhere = other.post(f"/maps/{other.post('/maps').json()['map']}/scans", files={"bundle": ("b.zip", zipped)})
        sender.join(120)
        assert second.status_code == 409 and second.json()["error"] == "map_busy"
        assert second.headers["Retry-After"] == "3"
        assert deleting.status_code == 409
        assert reading.status_code == 200  # readers are never blocked by the writer
        assert elsewhere.status_code == 200  # other maps are not held
        assert first["r"].status_code == 200 and first["r"].json()["scan"] == 1
        again = http.post(f"/maps/{map_id}/scans", files={"bundle": ("b.zip", zipped)})
        assert again.status_code == 200 and again.json()["scan"] == 2


def test_shadowcorr_client_map_commands(server, ring, tmp_path, capsys) -> None:
    base = ["--server", server.url, "--timeout", "120"]
    assert client_main(["map", "create", *base]) == 0
    map_id = json.loads(capsys.readouterr().out)["map"]
    first = write_bundle(views(ring, 0, 2), tmp_path / "first")
    second = write_bundle(views(ring, 4, 5), tmp_path / "second")
    out = tmp_path / "updates.jsonl"
    assert client_main(["map", "add", map_id, str(first), str(second), "--out", str(out), *base]) == 0
    assert [json.loads(line)["scan"] for line in out.read_text().splitlines()] == [1, 2]
    capsys.readouterr()
    assert client_main(["map", "events", map_id, "--since", "2", *base]) == 0
    events = json.loads(capsys.readouterr().out)
    assert events and all(e["event"] > 2 for e in events)
    assert client_main(["map", "show", map_id, "--out", str(tmp_path / "map.json"), *base]) == 0
    assert len(json.loads((tmp_path / "map.json").read_text())["scans"]) == 2
    assert client_main(["map", "delete", map_id, *base]) == 0
    capsys.readouterr()
    assert client_main(["map", "show", map_id, *base]) == 1
    assert "map_not_found" in capsys.readouterr().err
