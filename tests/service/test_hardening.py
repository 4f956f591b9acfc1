"""Safe next to a real hand: what a web page, a bad client or a typo could do to a live
``sdh2svc serve --sim`` without a token, and what the service answers instead."""

from __future__ import annotations

import contextlib
import json
import re
import socket
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import httpx
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from sdh2svc.client import ApiError, InvalidRequest, NotFound, Unavailable, run_state
from tests.live_service import LiveService, start_run, start_service

EVIL = "http://evil.example"
ALLOWED_ORIGIN = "http://dash.example:9000"
MAX_BODY_KB = 512
JSON = {"content-type": "application/json"}
BUSY_TIMEOUT_S = 0.5  # how long the service's writes wait for another program's lock


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveService]:
    s = start_service(tmp_path_factory.mktemp("hardening"), viewer=False, extra=[
        "--set", 'service.allowed_hosts=["lab-pc.local"]',
        "--set", f'service.allowed_origins=["{ALLOWED_ORIGIN}"]',
        "--set", f"service.max_body_kb={MAX_BODY_KB}",
        "--set", f"storage.busy_timeout_s={BUSY_TIMEOUT_S}",
    ])  # fmt: skip
    try:
        yield s
    finally:
        assert s.stop() == 0, "".join(s.log)


def plain(svc: LiveService) -> httpx.AsyncClient:
    """Raw HTTP, for what sdh2svc.client never sends: a browser's 'simple' request (no JSON
    content type), foreign Origins and Hosts, hostile bodies."""
    return httpx.AsyncClient(base_url=svc.url, timeout=30.0)


async def test_other_web_pages_cannot_drive_the_hand(svc: LiveService) -> None:
    async with plain(svc) as c:
        text = {"Content-Type": "text/plain"}
        # a page elsewhere: fetch(…/api/runs, {method: "POST", mode: "no-cors"})
        r = await c.post("/api/runs", headers={**text, "Origin": EVIL})
        assert r.status_code == 403 and r.json()["error"].startswith("cross-origin")
        r = await c.post("/api/runs", headers=text)  # and without the Origin: still no JSON
        assert r.status_code == 415 and "application/json" in r.json()["error"]
        r = await c.post("/api/runs", content=b'{"object": "egg"}', headers=text)
        assert r.status_code == 415
        assert (await c.get("/api/status")).json()["run"] is None  # nothing started
        r = await c.post("/api/runs/stop", headers={**text, "Origin": EVIL})
        assert r.status_code == 403
        r = await c.patch("/api/params", json={"k": 3}, headers={"Origin": EVIL})
        assert r.status_code == 403
        assert (await c.get("/api/params")).json()["k"] == 2.0

        # anyone may stop the hand; releasing it takes a request of this service's own page
        r = await c.post("/api/estop", headers={**text, "Origin": EVIL})
        assert r.status_code == 200 and r.json()["estopped"] is True
        r = await c.post("/api/estop/release", headers={**text, "Origin": EVIL})
        assert r.status_code == 403
        r = await c.post("/api/estop/release", json={}, headers={"Origin": EVIL})
        assert r.status_code == 403
        r = await c.post("/api/estop/release", json={}, headers={"Origin": svc.url})
        assert r.status_code == 200 and r.json() == {"estopped": False}
        # … or of a configured one
        r = await c.patch("/api/params", json={"k": 2.0}, headers={"Origin": ALLOWED_ORIGIN})
        assert r.status_code == 200

        # DNS rebinding: evil.example resolves to 127.0.0.1, the browser still says its name
        port = urlparse(svc.url).port
        r = await c.get("/api/status", headers={"Host": f"evil.example:{port}"})
        assert r.status_code == 400 and "host name" in r.json()["error"]
        # refused before the app, its body encoded as the app's own (compact, UTF-8 "…")
        compact = json.dumps(r.json(), ensure_ascii=False, separators=(",", ":")).encode()
        assert r.content == compact, r.content
        r = await c.post("/api/estop", headers={"Host": "evil.example"})
        assert r.status_code == 400
        for host in (f"lab-pc.local:{port}", f"localhost:{port}", "[::1]"):
            assert (await c.get("/api/status", headers={"Host": host})).status_code == 200


async def test_websocket_handshake_of_other_pages_refused(svc: LiveService) -> None:
    with pytest.raises(InvalidStatus) as refused:
        async with connect(svc.ws_url, origin=EVIL):  # type: ignore[arg-type]
            pass
    assert refused.value.response.status_code == 403
    async with connect(svc.ws_url, origin=svc.url) as ws:  # type: ignore[arg-type]
        assert json.loads(await ws.recv())["type"] == "hello"
    async with connect(svc.ws_url) as ws:  # no Origin: a script
        assert json.loads(await ws.recv())["type"] == "hello"
    # rebinding: a foreign Host in the handshake
    u = urlparse(svc.ws_url)
    with socket.create_connection((u.hostname, u.port), timeout=10) as sock:
        sock.sendall(
            f"GET {u.path} HTTP/1.1\r\nHost: evil.example:{u.port}\r\nUpgrade: websocket\r\n"
            "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
            "Sec-WebSocket-Version: 13\r\n\r\n".encode()
        )
        assert sock.recv(64).startswith(b"HTTP/1.1 400")


def _raw_request(url: str, head: str) -> bytes:
    """Send a request's head (no body), read the whole answer."""
    u = urlparse(url)
    with socket.create_connection((u.hostname, u.port), timeout=10) as sock:
        sock.sendall(head.encode())
        out = b""
        while chunk := sock.recv(65536):
            out += chunk
    return out


def test_huge_body_refused_before_it_is_read(svc: LiveService) -> None:
    u = urlparse(svc.url)
    answer = _raw_request(svc.url, f"PATCH /api/params HTTP/1.1\r\nHost: {u.netloc}\r\n"
                          "Content-Type: application/json\r\n"
                          f"Content-Length: {300 * 2**20}\r\n\r\n")  # fmt: skip
    head, _, body = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 413")
    assert f"at most {MAX_BODY_KB} kB".encode() in body


def test_a_body_a_little_too_large_gets_its_413(svc: LiveService) -> None:
    """The service reads (and drops) a body over the limit, up to 16 MiB, before it answers:
    closing with unread input makes the kernel reset the connection, and the client then saw
    no 413 but "connection reset" (sometimes at 1.1 MB on a busy machine; at 12 MB, always)."""
    with svc.sync_client() as c:
        for body in ({"k": "x" * (MAX_BODY_KB * 1024 + 100_000)},
                     {"k": "x" * (12 * 2**20)}):  # fmt: skip
            for _ in range(10):
                with pytest.raises(InvalidRequest) as big:
                    c.patch_params(body)
                assert big.value.status == 413, big.value


async def test_errors_never_echo_a_long_value(svc: LiveService) -> None:
    long = "x" * 300_000  # under the body limit, so that it reaches validation
    async with plain(svc) as c:  # hostile bodies, as sent
        for method, path, body in (
            ("PATCH", "/api/params", {"k": long}),
            ("PATCH", "/api/params", {long: 1}),
            ("POST", "/api/runs", {"params": {"cycles": long}}),
            ("POST", "/api/runs", {"object": long}),
            ("POST", "/api/runs", {long: 1}),
            ("PUT", "/api/sim/object", {"name": long}),
            ("PUT", "/api/sim/object", {"spec": {"kind": long, "depth_mm": 5}}),
            ("PUT", "/api/sim/object", {"spec": {"kind": "circle", "depth_mm": 5,
                                                 "diameter_mm": 30, "name": long}}),
            ("PUT", "/api/sim/object", {"spec": {"kind": "polygon", "depth_mm": 5,
                                                 "vertices_mm": [[0, 0]] * 20_000}}),
        ):  # fmt: skip
            r = await c.request(
                method, path, json=body, headers={"Content-Type": "application/json"}
            )
            assert r.status_code == 422, (method, path, r.text[:300])
            assert len(r.content) < 2000, (method, path, r.text[:300])
            assert "x" * 81 not in r.text
        r = await c.get("/api/runs/" + "9" * 5000)
        assert r.status_code == 422 and len(r.content) < 2000


async def test_ids_and_offsets_beyond_range_are_422_not_500(svc: LiveService) -> None:
    big = 9223372036854775808  # 2⁶³: beyond SQLite's integers
    async with svc.client() as c:
        for call in (c.run(big), c.run(2**64), c.run(0), c.run(-1), c.samples(big),
                     c.export_bytes(big, "csv")):  # fmt: skip
            with pytest.raises(InvalidRequest) as bad:
                await call
            assert bad.value.status == 422 and "run_id" in bad.value.details[0]
        with pytest.raises(NotFound, match="no run"):
            await c.run(big - 1)
        for offset in (2**63, 2**64, -1):
            with pytest.raises(InvalidRequest) as bad:
                await c.samples(1, offset=offset)
            assert bad.value.status == 422 and "offset" in bad.value.details[0]


async def test_booleans_are_no_numbers(svc: LiveService) -> None:
    async with svc.client() as c:
        with pytest.raises(InvalidRequest) as bad:
            await c.start_run({"cycles": True})
        assert bad.value.status == 422 and "cycles = true" in bad.value.details[0]
        with pytest.raises(InvalidRequest) as bad:
            await c.patch_params({"k": True})
        assert "k = true" in bad.value.details[0]
        spec = {"kind": "circle", "diameter_mm": True, "depth_mm": 10}
        with pytest.raises(InvalidRequest) as bad:
            await c.set_sim_object(spec=spec)
        assert "diameter_mm" in bad.value.details[0]
        async with plain(svc) as raw:  # a body the client would never send
            r = await raw.post("/api/runs", json={"params": {}, "paramz": {"cycles": 1}})
            assert r.status_code == 422 and "paramz" in r.json()["details"][0]
        assert (await c.status())["run"] is None


STAR = [[40.0 * c, 40.0 * s] for c, s in ((1, 0), (-0.809, 0.588), (0.309, -0.951),
                                          (0.309, 0.951), (-0.809, -0.588))]  # fmt: skip


@pytest.mark.parametrize(
    ("spec", "fragment"),
    [
        ({"kind": "polygon", "vertices_mm": STAR, "depth_mm": 10}, "must not cross"),
        ({"kind": "polygon", "vertices_mm": [[0, 0], [1e200, 0], [0, 30]], "depth_mm": 10},
         "vertices_mm.1.0 = 1e+200"),
        ({"kind": "polygon", "vertices_mm": [[0, 0], [1e-9, 0], [0, 1e-9]], "depth_mm": 10},
         "polygon"),
        ({"kind": "polygon", "vertices_mm": [[0, 0], [30, 0], [60, 0], [0, 30]], "depth_mm": 10},
         "convex"),
        ({"kind": "polygon", "vertices_mm": [[40 * __import__("math").cos(k / 500),
                                              40 * __import__("math").sin(k / 500)]
                                             for k in range(3000)], "depth_mm": 10},
         "at most 64"),
        ({"kind": "circle", "diameter_mm": 1e200, "depth_mm": 10}, "5.0 ≤ diameter_mm ≤ 150.0"),
        ({"kind": "box", "width_mm": 1e-9, "height_mm": 30, "depth_mm": 10}, "width_mm"),
        ({"kind": "ellipse", "axis_a_mm": 3, "axis_b_mm": 2, "depth_mm": 10}, "5 … 150 mm"),
        ({"kind": "stick", "length_mm": 500, "depth_mm": 10}, "length_mm ≤ 150.0"),
        ({"kind": "circle", "diameter_mm": 30, "depth_mm": 1e200}, "depth_mm"),
    ],
)  # fmt: skip
async def test_object_specs_the_hand_cannot_hold_are_422(
    svc: LiveService, spec: dict[str, Any], fragment: str
) -> None:
    async with svc.client() as c:
        with pytest.raises(InvalidRequest) as bad:
            await c.set_sim_object(spec=spec)
        assert bad.value.status == 422 and bad.value.error == "invalid object spec"
        assert any(fragment in d for d in bad.value.details), bad.value.details
        with pytest.raises(InvalidRequest):
            await c.start_run(object=spec)
        assert (await c.status())["run"] is None


async def test_a_fine_polygon_is_taken(svc: LiveService) -> None:
    import math

    ring = [[30 * math.cos(2 * math.pi * k / 64), 20 * math.sin(2 * math.pi * k / 64)]
            for k in range(64)]  # fmt: skip
    async with svc.client() as c:
        spec = {"kind": "polygon", "vertices_mm": ring, "depth_mm": 20, "name": "oval"}
        assert (await c.set_sim_object(spec=spec))["object"]["name"] == "oval"
        truth = (await c.status())["object"]
        assert truth["kind"] == "polygon" and len(truth["vertices_mm"]) == 64
        await c.set_sim_object(name="egg")


async def test_open_hand_route(svc: LiveService) -> None:
    async with svc.client() as c:
        try:
            assert (await c.open_hand()) == {"state": "opening"}
        except ApiError as refused:  # the route is there: refused for the hand's state only
            assert refused.status not in (404, 405, 415), refused
    async with plain(svc) as raw:
        assert (await raw.post("/api/hand/open")).status_code == 415  # JSON, as every command


async def test_head_answers_as_get_without_the_body(svc: LiveService) -> None:
    """Monitors and ``curl -I`` ask with HEAD: the GET's status and headers, no body."""
    async with plain(svc) as c:
        for path in ("/api/params", "/openapi.json", "/", "/api/runs", "/api/status"):
            got, head = await c.get(path), await c.head(path)
            assert head.status_code == got.status_code == 200, path
            assert head.content == b"", path
            assert head.headers["content-type"] == got.headers["content-type"], path
            if path in ("/api/params", "/openapi.json", "/"):  # (the others change as they go)
                assert int(head.headers["content-length"]) == len(got.content), path
        assert (await c.head("/api/runs/999999")).status_code == 404
        assert (await c.head("/api/params", headers={"Host": "evil.example"})).status_code == 400
        assert (await c.head("/api/estop")).status_code == 405  # GET's route only: no command


async def test_a_wrong_method_says_which_the_route_takes_and_an_unknown_route_says_so(
    svc: LiveService,
) -> None:
    """A 405 names the methods the route takes, in its ``Allow`` header too (RFC 9110); a 404
    of the router names the request and where the routes are listed."""
    async with plain(svc) as c:
        for method, path, allow in (("GET", "/api/estop", "POST"), ("PUT", "/api/params", None),
                                    ("DELETE", "/api/status", None)):  # fmt: skip
            r = await c.request(method, path, headers={"Content-Type": "application/json"})
            assert r.status_code == 405, (method, path, r.text)
            assert r.headers["allow"] and (allow is None or r.headers["allow"] == allow), r.headers
            said = r.json()["error"]
            assert said.startswith(f"{method} {path}: this route takes "), said
            assert said.endswith(r.headers["allow"]), said
        r = await c.get("/api/nope")
        assert r.status_code == 404
        assert r.json()["error"] == "GET /api/nope: no such route (the API's routes: /docs)"
        assert (await c.get("/api/runs/999999")).json()["error"] != r.json()["error"]


async def test_no_other_site_may_frame_the_dashboard(svc: LiveService) -> None:
    """A page that framed the dashboard would make its requests with the service's own Origin:
    a click it lured onto a button would drive the hand (clickjacking)."""
    async with plain(svc) as c:
        for r in (await c.get("/"), await c.get("/api/status"), await c.get("/nope"),
                  await c.post("/api/runs", headers={"Origin": EVIL})):  # fmt: skip
            assert r.headers["content-security-policy"] == "frame-ancestors 'self'", r
            assert r.headers["x-frame-options"] == "SAMEORIGIN", r


async def test_docs_are_served_from_the_package(svc: LiveService) -> None:
    async with plain(svc) as c:  # pages for a browser
        for page in ("/docs", "/redoc"):
            r = await c.get(page)
            assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
            urls = re.findall(r'(?:src|href)="([^"]+)"', r.text)
            assert urls and all(u.startswith("/") and not u.startswith("//") for u in urls), urls
            assert "http://" not in r.text and "https://" not in r.text, page
            for u in urls:
                got = await c.get(u)
                assert got.status_code == 200 and len(got.content) > 1000, u
        assert (await c.get("/openapi.json")).status_code == 200


async def test_openapi_lists_every_status_and_content_type(svc: LiveService) -> None:
    async with plain(svc) as c:
        paths = (await c.get("/openapi.json")).json()["paths"]
    error_schema = {"$ref": "#/components/schemas/ErrorBody"}
    expect = {
        ("get", "/api/status"): {200, 400, 422},  # 422: ?unknown=1 (every route but the e-stop)
        ("patch", "/api/params"): {200, 400, 401, 403, 413, 415, 422},
        ("post", "/api/runs"): {201, 400, 401, 403, 409, 413, 415, 422, 503},
        ("post", "/api/runs/stop"): {202, 400, 401, 403, 409, 413, 415, 422},
        # every read of the run database: 503 when it cannot be opened
        ("get", "/api/runs"): {200, 400, 422, 503},
        ("get", "/api/runs/{run_id}"): {200, 400, 404, 422, 503},
        ("get", "/api/runs/{run_id}/samples"): {200, 400, 404, 422, 503},
        ("get", "/api/runs/{run_id}/frames"): {200, 400, 404, 409, 422, 503},
        ("get", "/api/runs/{run_id}/truth"): {200, 400, 404, 422, 503},
        ("get", "/api/runs/{run_id}/export"): {200, 400, 404, 409, 422, 503},
        ("delete", "/api/runs/{run_id}"): {200, 400, 401, 403, 404, 409, 413, 415, 422, 503},
        ("put", "/api/viewer/replay"): {200, 400, 401, 403, 404, 409, 413, 415, 422, 503},
        ("delete", "/api/viewer/replay"): {200, 400, 401, 403, 409, 413, 415, 422},
        ("post", "/api/estop"): {200, 400, 413, 503},
        # 409: an e-stop came during the release (user audit)
        ("post", "/api/estop/release"): {200, 400, 401, 403, 409, 413, 415, 422, 503},
        ("post", "/api/hand/open"): {202, 400, 401, 403, 409, 413, 415, 422, 503},
        ("get", "/api/sim/object"): {200, 400, 404, 422},
        ("put", "/api/sim/object"): {200, 400, 401, 403, 404, 409, 413, 415, 422},
        ("post", "/api/sim/press"): {202, 400, 401, 403, 404, 413, 415, 422},
        ("delete", "/api/sim/press"): {200, 400, 401, 403, 404, 413, 415, 422},
    }
    for path in ("/api/params", "/api/params/schema", "/api/config", "/api/viewer"):
        expect[("get", path)] = {200, 400, 422}
    for (method, path), codes in expect.items():
        responses = paths[path][method]["responses"]
        assert {int(k) for k in responses} == codes, (method, path)
        for code, resp in responses.items():
            if int(code) >= 400:
                assert resp["content"]["application/json"]["schema"] == error_schema
    export = paths["/api/runs/{run_id}/export"]["get"]["responses"]["200"]["content"]
    assert set(export) == {"text/csv", "application/octet-stream"}
    run_id = paths["/api/runs/{run_id}"]["get"]["parameters"][0]["schema"]
    assert (run_id["minimum"], run_id["maximum"]) == (1, 2**63 - 1)


def test_docs_assets_are_in_the_installed_package() -> None:
    from sdh2svc.service.app import docs_assets_dir

    names = {p.name for p in Path(docs_assets_dir()).iterdir()}
    assert {"swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js"} <= names


NO_BODY = [("post", "/api/estop/release"), ("post", "/api/hand/open"),
           ("delete", "/api/sim/press"), ("delete", "/api/viewer/replay"),
           ("delete", "/api/runs/999999")]  # fmt: skip


async def test_a_command_without_a_body_refuses_one(svc: LiveService) -> None:
    """A mistaken body (a speed for Open hand, garbage for the release) is a 422, never silently
    ignored; nothing or {} is no body. The stops take any body: stopping is never refused."""
    async with plain(svc) as raw:
        for method, path in NO_BODY:
            for body in ("garbage", '{"speed": 1}', "[1, 2]", "null", '{"a"'):
                r = await raw.request(method, path, content=body, headers=JSON)
                assert r.status_code == 422, (method, path, body, r.text)
                assert "takes no body" in r.json()["details"][0]
            for body in ("", "{}", " { } "):
                r = await raw.request(method, path, content=body, headers=JSON)
                assert r.status_code != 422, (method, path, body, r.text)
        # the empty bodies opened the hand: the stop, garbage and all, stops that (202) or
        # finds nothing left to stop (409), whichever comes first
        r = await raw.post("/api/runs/stop", content="garbage", headers=JSON)
        assert r.status_code in (202, 409), r.text
        async with svc.client() as c:
            await c.wait_status(lambda st: not st["hand"]["opening"])
        r = await raw.post("/api/estop", content="garbage", headers=JSON)
        assert r.status_code == 200 and r.json()["estopped"] is True
        r = await raw.post("/api/estop/release", content="{}", headers=JSON)
        assert r.status_code == 200 and r.json() == {"estopped": False}


async def test_integers_are_written_in_digits_and_values_as_typed(svc: LiveService) -> None:
    async with plain(svc) as raw:
        for path in ("/api/runs/1_0", "/api/runs/+1", "/api/runs/1.0", "/api/runs/%20%201",
                     "/api/runs/1/samples?offset=1_0", "/api/runs/1/frames?from=+0"):  # fmt: skip
            r = await raw.get(path)
            assert r.status_code == 422, (path, r.text)
            assert "written in digits 0-9" in r.json()["details"][0], path
        for body in ({"cycles": "2"}, {"k": "3.5"}, {"route": 1}):
            r = await raw.patch("/api/params", json=body, headers=JSON)
            assert r.status_code == 422 and next(iter(body)) in r.json()["details"][0], r.text
        for at in ({"run_id": True, "iteration": 0}, {"run_id": "1", "iteration": 0},
                   {"run_id": 1, "iteration": "5"}):  # fmt: skip
            r = await raw.put("/api/viewer/replay", json=at, headers=JSON)
            assert r.status_code == 422, (at, r.text)
        for literal in ("NaN", "Infinity", "-Infinity"):  # named as such, not as out of range
            r = await raw.patch("/api/params", content=f'{{"k": {literal}}}', headers=JSON)
            assert r.status_code == 422 and "finite number" in r.json()["details"][0], r.text
        huge = '{"cycles": ' + "9" * 5000 + "}"  # beyond what json.loads reads
        r = await raw.patch("/api/params", content=huge, headers=JSON)
        assert r.status_code == 400 and "4300 digits" in r.json()["error"]
        r = await raw.patch("/api/params", content=b'{"k": "\xff"}', headers=JSON)
        assert r.status_code == 400 and "not UTF-8" in r.json()["error"], r.text
        assert (await raw.get("/api/params")).json()["cycles"] != "2"


async def test_a_body_that_cannot_be_read_says_why_and_where(svc: LiveService) -> None:
    """Not JSON: where it breaks (the details said "Expecting value", nowhere). JSON the decoder
    gives up on: which of its reasons (the error listed all three, whichever it was)."""
    unreadable = "the body is no JSON this service can read"
    async with plain(svc) as raw:
        r = await raw.patch("/api/params", content='{\n  "k": }', headers=JSON)
        assert r.status_code == 400, r.text
        assert r.json() == {
            "error": "the body is not JSON",
            "details": ["Expecting value at character 9 (line 2, column 8)"],
        }
        r = await raw.patch("/api/params", content='{"k": 3', headers=JSON)
        assert r.json()["details"] == [
            "Expecting ',' delimiter at character 7 (line 1, column 8)"
        ], r.text
        cases = [
            (b'{"k": "\xff"}', "not UTF-8", "byte 7 (0xff) is not UTF-8"),
            (b'{"cycles": ' + b"9" * 5000 + b"}", "a number of over 4300 digits",
             "a number of 5000 digits"),
            (b"[" * 100_000 + b"]" * 100_000, "nested too deep",
             "arrays and objects nested deeper than the decoder goes"),
        ]  # fmt: skip
        for body, why, detail in cases:
            r = await raw.patch("/api/params", content=body, headers=JSON)
            assert r.status_code == 400, r.text
            assert r.json() == {"error": f"{unreadable}: {why}", "details": [detail]}


async def test_a_bad_telemetry_query_refuses_the_handshake_with_422(svc: LiveService) -> None:
    # the last one a misspelt name: refused, as by a REST route, not ignored
    bad = ("decimate=0", "decimate=abc", "tactile=2", "max_queue=0", "decimate=1_0", "tactil=0")
    for query in bad:
        with pytest.raises(InvalidStatus) as refused:
            async with connect(f"{svc.ws_url}?{query}"):
                pass
        r = refused.value.response
        body = json.loads(r.body)
        assert r.status_code == 422 and body["error"] == "invalid request", query
        name, _, value = query.partition("=")
        assert body["details"][0].startswith(f"query.{name} = {value!r}: "), body
    assert "tactil = '0': no such query parameter here (this one takes: decimate, max_queue, " \
        "tactile)" in body["details"][0], body  # fmt: skip


async def _runs(raw: httpx.AsyncClient) -> tuple[str, Any]:
    """How many runs the database holds, and the status's run: both unchanged, none started."""
    listed = await raw.get("/api/runs", params={"limit": 1})
    return listed.headers["x-total-count"], (await raw.get("/api/status")).json()["run"]


async def test_null_for_a_body_or_an_optional_key_is_refused_naming_it(svc: LiveService) -> None:
    """FastAPI reads a body of null as no body, pydantic a key's null as the key left out: a
    client's null sent by mistake started a run with the defaults."""
    refused = [
        ("POST", "/api/runs", "null", "body: must be a JSON object, not null"),
        ("POST", "/api/runs", '{"params": null}', "body.params: must be an object, not null"),
        ("POST", "/api/runs", '{"object": null}',
         "body.object: must be a preset name or an object spec, not null"),
        ("PATCH", "/api/params", "null", "body: must be a JSON object, not null"),
        ("PUT", "/api/sim/object", "null", "body: must be a JSON object, not null"),
        ("PUT", "/api/sim/object", '{"name": "egg", "spec": null}',
         "body.spec: must be an object spec, not null"),
        ("POST", "/api/sim/press", "null", "body: must be a JSON object, not null"),
        ("PUT", "/api/viewer/replay", "null", "body: must be a JSON object, not null"),
        # a value of another type: one line, in JSON's words, not one per branch of a union
        ("POST", "/api/runs", '{"object": 5}',
         "body.object = 5: must be a preset name or an object spec, not a number"),
        ("POST", "/api/runs", '{"params": []}', "body.params: must be an object, not an array"),
        ("PUT", "/api/sim/object", '{"name": true}', "body.name = true: must be a preset name, "
         "not true"),
        ("PUT", "/api/sim/object", '{"spec": "egg"}', "body.spec = 'egg': must be an object spec, "
         "not a string"),
    ]  # fmt: skip
    async with plain(svc) as raw:
        before = await _runs(raw)
        for method, path, body, line in refused:
            r = await raw.request(method, path, content=body, headers=JSON)
            assert r.status_code == 422, (method, path, body, r.text)
            assert r.json()["error"] == "invalid request", r.text
            assert r.json()["details"][0].startswith(line), (body, r.text)
            assert len(r.json()["details"]) == 1, r.text
        assert await _runs(raw) == before  # no run started
        r = await raw.put("/api/sim/object", json={"name": "egg"}, headers=JSON)
        assert r.status_code == 200 and r.json()["object"]["name"] == "egg", r.text


async def test_a_key_given_twice_is_refused_naming_it(svc: LiveService) -> None:
    """JSON decoders keep the last of a repeated key silently: a grasp force of 1 could become
    40. Refused at any depth, on every route that takes a body, naming where."""
    bodies = [
        ("PATCH", "/api/params", '{"grasp_force": 1, "grasp_force": 40}', "body.grasp_force"),
        ("POST", "/api/runs", '{"params": {"cycles": 1, "grasp_force": 1, "grasp_force": 40}}',
         "body.params.grasp_force"),
        ("POST", "/api/runs", '{"params": {"cycles": 1}, "params": null}', "body.params"),
        ("PUT", "/api/sim/object",
         '{"spec": {"kind": "polygon", "depth_mm": 5, "vertices_mm": [[0, 0]], '
         '"kind": "circle", "diameter_mm": 30}}', "body.spec.kind"),
        ("POST", "/api/sim/press", '{"pad": 0, "x_mm": 1, "y_mm": 1, "force_n": 1, "pad": 5}',
         "body.pad"),
        ("PUT", "/api/viewer/replay", '{"run_id": 1, "iteration": 0, "run_id": 2}',
         "body.run_id"),
    ]  # fmt: skip
    async with plain(svc) as raw:
        params, before = (await raw.get("/api/params")).json(), await _runs(raw)
        for method, path, body, key in bodies:
            r = await raw.request(method, path, content=body, headers=JSON)
            assert r.status_code == 422, (method, path, body, r.text)
            assert r.json()["details"] == [f"{key}: the key is given more than once (JSON "
                                           "would silently keep the last)"], r.text  # fmt: skip
        assert (await raw.get("/api/params")).json() == params and await _runs(raw) == before
        r = await raw.patch("/api/params", content='[{"a": {"b": 1, "b": 2}}]', headers=JSON)
        assert r.json()["details"] == ["body.0.a.b: the key is given more than once (JSON would "
                                       "silently keep the last)"], r.text  # fmt: skip
        large = '{"k": "' + "x" * 100_000 + '", "k": 3}'  # (decoded on a worker thread)
        r = await raw.patch("/api/params", content=large, headers=JSON)
        assert r.status_code == 422 and r.json()["details"][0].startswith("body.k: "), r.text
        # the stops take any body, repeated keys too: stopping is never refused
        r = await raw.post("/api/runs/stop", content='{"a": 1, "a": 2}', headers=JSON)
        assert r.status_code == 409 and r.json()["error"] == "no run is running", r.text
        r = await raw.patch("/api/params", json={"k": params["k"]}, headers=JSON)  # once: taken
        assert r.status_code == 200 and r.json() == params, r.text


async def test_a_query_parameter_given_twice_is_refused(svc: LiveService) -> None:
    """FastAPI keeps the last of a repeated query parameter: ``?limit=5&limit=500`` read 500."""
    async with plain(svc) as raw:
        for path in ("/api/runs?limit=5&limit=500", "/api/runs/1/samples?every=2&offset=0&every=3",
                     "/api/runs/1/export?format=csv&format=mcap"):  # fmt: skip
            r = await raw.get(path)
            assert r.status_code == 422 and r.json()["error"] == "invalid request", (path, r.text)
            name = path.split("&")[-1].split("=")[0]
            said = [f"query.{name}: given 2 times; it takes one value"]  # as on the socket
            assert r.json()["details"] == said, r.text
        r = await raw.get("/api/runs?limit=5&before=9")  # each once: taken
        assert r.status_code == 200 and "x-total-count" in r.headers, r.text
    with pytest.raises(InvalidStatus) as refused:
        async with connect(f"{svc.ws_url}?decimate=1&decimate=1000"):
            pass
    body = json.loads(refused.value.response.body)
    assert refused.value.response.status_code == 422, body
    assert body["details"] == ["query.decimate: given 2 times; it takes one value"], body


async def test_a_run_starts_without_a_body_or_with_an_empty_one(svc: LiveService) -> None:
    """``POST /api/runs``' body is optional: nothing, or ``{}``, takes the parameters in force."""
    async with plain(svc) as raw, svc.client() as c:
        for body in ("", "{}"):
            for attempt in range(3):  # (as start_run: a starved service's stream may lag once)
                r = await raw.post("/api/runs", content=body, headers=JSON)
                if r.status_code != 503 or "sends no frames" not in r.text or attempt == 2:
                    break
                await c.wait_status(lambda st: st["hand"]["connected"]["tactile"], 30.0)
            assert r.status_code == 201, (body, r.text)
            run_id = r.json()["run_id"]
            await c.stop_run()
            await c.wait_run(run_id, timeout=60)
            meta = (await c.run(run_id))["meta"]
            assert meta["params"] == await c.params(), meta  # those in force


async def test_the_estop_stops_a_run_whatever_the_database_does(
    svc: LiveService, tmp_path: Path
) -> None:
    """Another program holds the run database locked (a DB browser, a sqlite3 shell) as the
    e-stop comes mid-run: the hand stops all the same and the run ends e-stopped; the answer
    says the latch is not on disk. The release cannot clear the record then, so it refuses and
    the e-stop stays latched; once the lock is gone, both work."""
    async with plain(svc) as raw:
        db = Path((await raw.get("/api/config")).json()["storage"]["db_path"])
    async with svc.client() as c:
        run_id = (await start_run(c, {"cycles": 1}))["run_id"]
        await c.wait_status(run_state("pre-shape", "grasping"))
        lock = sqlite3.connect(db, isolation_level=None)
        try:
            lock.execute("BEGIN IMMEDIATE")
            out = await c.estop()
            assert out["estopped"] is True and out["recorded"] is False, out
            # its write waits 0.5 s for the lock, the answer at most 1 s for the write: on a busy
            # machine the answer may come first
            assert re.search("(could not be|is still being) written to the run database",
                             out["detail"]), out  # fmt: skip
            end = await c.wait_run(run_id, timeout=60)
            assert end["status"] == "e-stopped" and "not recorded" in end["message"], end
            st = await c.wait_status(lambda st: st["estop"]["recorded"] == "no", 30)
            assert st["estopped"] is True
            with pytest.raises(Unavailable, match="e-stop stays latched"):
                await c.release_estop()
            assert (await c.status())["estopped"] is True
        finally:
            lock.execute("ROLLBACK")
            lock.close()
        assert (await c.estop())["recorded"] is True  # now on disk
        with contextlib.closing(sqlite3.connect(db)) as look:
            assert look.execute("SELECT reason FROM estop").fetchall() == [("e-stop requested",)]
        assert (await c.release_estop()) == {"estopped": False}
        assert (await c.status())["estop"] is None


async def test_a_latch_the_database_did_not_take_is_written_once_it_can_be(
    svc: LiveService,
) -> None:
    """The run database refused the e-stop's latch (another program held it locked past the
    busy timeout), and then a release too: once the lock is gone, the latch reaches the disk
    by itself — a restart keeps it — with the time the e-stop came."""
    async with plain(svc) as raw:
        db = Path((await raw.get("/api/config")).json()["storage"]["db_path"])
    async with svc.client() as c:
        lock = sqlite3.connect(db, isolation_level=None)
        try:
            lock.execute("BEGIN IMMEDIATE")
            assert (await c.estop())["recorded"] is False
            st = await c.wait_status(lambda st: st["estop"]["recorded"] == "no", 30)
            with pytest.raises(Unavailable, match="e-stop stays latched"):
                await c.release_estop()
            assert (await c.status())["estop"]["recorded"] == "no"
            with contextlib.closing(sqlite3.connect(db, timeout=0)) as look:
                assert look.execute("SELECT * FROM estop").fetchall() == []  # (read: no lock)
        finally:
            lock.execute("ROLLBACK")
            lock.close()
        on_disk = await c.wait_status(lambda st: "recorded" not in (st["estop"] or {}), 30)
        assert on_disk["estopped"] is True and on_disk["estop"]["since"] == st["estop"]["since"]
        with contextlib.closing(sqlite3.connect(db)) as look:
            assert look.execute("SELECT since FROM estop").fetchall() == [(st["estop"]["since"],)]
        assert (await c.release_estop()) == {"estopped": False}
        assert (await c.status())["estop"] is None


async def test_the_estop_answers_at_once_while_its_latch_waits_for_a_lock(tmp_path: Path) -> None:
    """The run database's writes wait 5 s for another program's lock: a run's start and the
    e-stop's answer do not (each waited the whole busy timeout before). The e-stop says the
    latch is not on disk yet, the status says it is pending, and once the lock goes the latch
    is on disk with the time the e-stop came, not the time the write got through."""
    s = start_service(tmp_path, viewer=False, extra=["--set", "storage.busy_timeout_s=5"])
    try:
        async with s.client() as c:
            lock = sqlite3.connect(tmp_path / "runs.sqlite", isolation_level=None)
            try:
                lock.execute("BEGIN IMMEDIATE")
                # a run's start, on the service's event loop, waits only a moment for it: a
                # 503 that names the lock (not a 500 after the whole busy timeout)
                with pytest.raises(Unavailable, match="locked by another program") as refused:
                    await c.start_run()
                assert "no run was started" in refused.value.error
                assert (await c.status())["run"] is None
                out = await c.estop()
                assert out["estopped"] is True and out["recorded"] is False, out
                assert "still being written" in out["detail"]
                pending = (await c.status())["estop"]
                assert pending["recorded"] == "pending", pending
            finally:
                lock.execute("ROLLBACK")
                lock.close()
            st = await c.wait_status(lambda st: "recorded" not in (st["estop"] or {}), 30)
            assert st["estopped"] is True and st["estop"]["since"] == pending["since"]
            with contextlib.closing(sqlite3.connect(tmp_path / "runs.sqlite")) as look:
                rows = look.execute("SELECT since FROM estop").fetchall()
            assert rows == [(pending["since"],)]
            assert (await c.release_estop()) == {"estopped": False}
    finally:
        assert s.stop() == 0, "".join(s.log)


def test_every_route_that_takes_a_body_reads_it_strictly() -> None:
    """A router made without ``route_class=JsonRoute`` would read a repeated key's last value and
    a null body as none, silently: every route that declares a body must read it through it."""
    from fastapi.routing import APIRoute

    from sdh2svc.service.api.body import JsonRoute
    from sdh2svc.service.app import ROUTERS

    with_body = [r for router in ROUTERS for r in router.routes
                 if isinstance(r, APIRoute) and r.body_field is not None]  # fmt: skip
    assert len(with_body) >= 5  # runs, params, the object, a press, the replay at least
    loose = [f"{sorted(r.methods)} {r.path}" for r in with_body if not isinstance(r, JsonRoute)]
    assert not loose, loose
