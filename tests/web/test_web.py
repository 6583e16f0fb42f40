"""The operator's page over HTTP: views and their JSON twins, errors, the actions' token and
CSRF checks, the refusal to serve another address than loopback without TLS and a token."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import subprocess
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path
from typing import Any

import pytest

from robid_link.config import load_daemon_config
from robid_link.exceptions import ConfigError
from robid_link.link.store import Store
from robid_link.web.server import WebServer, load_token

from .cell import TOKEN, Recorder, build_cell, serving, write_config


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    return build_cell(tmp_path_factory.mktemp("cell"))


def get(url: str, headers: dict[str, str] | None = None) -> tuple[int, str, Any]:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}),
                                    timeout=30) as r:
            return r.status, r.read().decode(), r.headers
    except urllib.error.HTTPError as err:
        return err.code, err.read().decode(), err.headers


def post(url: str, form: dict[str, str], headers: dict[str, str] | None = None
         ) -> tuple[int, str]:
    data = urllib.parse.urlencode(form).encode()
    req = urllib.request.Request(url, data=data, headers=headers or {}, method="POST")
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as err:
        return err.code, err.read().decode()


def test_runs_newest_first_with_state_progress_and_what_they_wait_for(cell):
    cfg = load_daemon_config(cell.config)
    with serving(WebServer(cfg, "127.0.0.1:0", cell.robot)) as url:
        status, text, _ = get(url + "api/runs")
        assert status == 200
        runs = json.loads(text)["runs"]
        assert [r["run_id"] for r in runs] == [cell.runs[k] for k in (
            "queued", "running", "failed", "reported", "older")]
        assert [r["state"] for r in runs] == ["queued", "running", "failed", "completed",
                                              "completed"]
        assert {r["robot"] for r in runs} == {"arm3"}
        assert [r["waiting_since"] is not None for r in runs] == [True, True, False, False,
                                                                   False]
        assert runs[1]["step"] == "experiment 1/2 a" and runs[1]["progress"]["total"] == 2
        assert [r["report"] for r in runs] == [False, False, False, True, False]
        status, page, headers = get(url)
        assert status == 200 and "default-src 'none'" in headers["Content-Security-Policy"]
        for r in runs:  # the page shows what the API returns
            assert r["run_id"] in page
        assert "controller did not answer" in page
        assert get(url + "api/runs?limit=2")[1].count('"run_id"') == 2
        status, text, _ = get(url + "api/runs?limit=all")
        assert status == 400 and "limit: expected a whole number, got 'all'" in text


def test_a_runs_page_is_its_report_with_the_tracking_that_came_after(cell):
    cfg = load_daemon_config(cell.config)
    run_id = cell.runs["reported"]
    with serving(WebServer(cfg, "127.0.0.1:0", cell.robot)) as url:
        status, text, _ = get(url + f"api/runs/{run_id}")
        view = json.loads(text)
        assert view["run"]["state"] == "completed"
        assert set(view["report"]["tracking"]["phases"]) == {"before", "after"}
        assert {r["kind"] for r in view["results"]} == {"identify", "verify_before",
                                                        "verify_after"}
        status, page, _ = get(url + f"runs/{run_id}")
        assert status == 200
        for name in ("measured-vs-model", "residual", "parameters", "tracking"):
            assert f'data-figure="{name}"' in page, name
        status, page, _ = get(url + f"runs/{cell.runs['failed']}")  # no report: the run
        assert status == 200 and "controller did not answer" in page and "No report yet" in page
        status, text, _ = get(url + "runs/nope")
        assert status == 404 and text.strip() == "run nope: not in the store"


def test_compare_trend_and_parameter_sets(cell):
    cfg = load_daemon_config(cell.config)
    with serving(WebServer(cfg, "127.0.0.1:0", cell.robot)) as url:
        q = urllib.parse.urlencode({"a": cell.runs["older"], "b": "robot:arm3"})
        view = json.loads(get(url + "api/compare?" + q)[1])
        assert [s["run_id"] for s in view["sides"]] == [cell.runs["older"], cell.runs["reported"]]
        rows = {p["name"]: p for p in view["parameters"]}
        assert rows["off_2"]["a"] is None and rows["off_2"]["delta"] is None
        assert rows["fv_1"]["delta"] is not None and rows["fv_1"]["sigmas"] is not None
        assert len(view["rmse_delta"]) == 3
        assert "compare-parameters" in get(url + "compare?" + q)[1]
        status, text, _ = get(url + "api/compare?a=" + cell.runs["failed"] + "&b=robot:arm3")
        assert status == 404 and "no identification stored" in text
        assert get(url + "api/compare")[0] == 400
        trend = json.loads(get(url + "api/trend")[1])
        assert [r["version"] for r in trend["runs"]] == [1, 2]
        assert trend["versions"][1][-1] == "offset@2" and trend["units"]["fv_1"] == "N·m·s/rad"
        assert 'data-parameter="zz_1"' in get(url + "trend")[1]
        sets = json.loads(get(url + "api/params")[1])["robots"][0]
        assert sets["robot"] == "arm3"
        assert [(s["version"], bool(s["approved"]), s["in_use"]) for s in sets["sets"]] == [
            (1, True, True), (2, False, False)]


def _runs(state: Path) -> int:
    with Store(state, readonly=True) as store:
        return len(store.runs(1000))


def test_actions_need_the_token_and_the_csrf_cookie(cell):
    cfg = load_daemon_config(cell.config)
    rec = Recorder()
    cfg = cfg.__class__(**{**cfg.__dict__, "web": cfg.web.__class__(token=TOKEN)})
    before = _runs(cell.state)
    with serving(WebServer(cfg, "127.0.0.1:0", cell.robot, actions=rec)) as url:
        start = url + "actions/start"
        assert post(start, {"campaign": "nightly"})[0] == 403
        assert post(start, {"campaign": "nightly", "token": "wrong" * 5})[0] == 403
        status, text = post(start, {"campaign": "nightly", "token": TOKEN})  # no CSRF cookie
        assert status == 403 and "CSRF check failed" in text
        _, _, headers = get(url)
        cookie = headers["Set-Cookie"].split(";")[0]
        assert "HttpOnly" in headers["Set-Cookie"] and "SameSite=Strict" in headers["Set-Cookie"]
        csrf = cookie.split("=", 1)[1]
        form = {"campaign": "nightly", "token": TOKEN, "csrf": csrf}
        assert post(start, {**form, "csrf": "forged"}, {"Cookie": cookie})[0] == 403
        assert post(start, form, {"Cookie": cookie, "Origin": "http://evil.example"})[0] == 403
        assert rec.calls == []  # nothing reached the daemon
        status, text = post(start, form, {"Cookie": cookie})
        assert status == 200 and "run r-new queued" in text
        status, text = post(url + "actions/cancel", {"run_id": "r1"},
                            {"Authorization": f"Bearer {TOKEN}"})
        assert status == 200 and json.loads(text)["ok"]
        status, text = post(url + "actions/resume", {"run_id": "r2"},
                            {"Authorization": f"Bearer {TOKEN}"})
        assert status == 200 and json.loads(text)["ok"]
        assert rec.calls == [{"cmd": "start", "campaign": "nightly", "by": "web",
                              "trigger": "web"},
                             {"cmd": "cancel", "run_id": "r1", "by": "web"},
                             {"cmd": "resume", "run_id": "r2", "by": "web"}]
        assert post(url + "actions/reboot", form, {"Cookie": cookie})[0] == 404
    assert _runs(cell.state) == before


def _status_for_host(cfg: Any, listen_host: str | None, host: str, post: bool = False
                     ) -> tuple[int, str]:
    """The page's answer to a request naming ``host`` in its Host header."""
    from aiohttp.test_utils import TestClient, TestServer

    from robid_link.web.server import make_app

    async def go() -> tuple[int, str]:
        app = make_app(cfg, "arm3", actions=Recorder(), token=TOKEN, listen_host=listen_host)
        async with TestClient(TestServer(app)) as client:
            if post:
                r = await client.post("/actions/start", data={"campaign": "nightly"},
                                      headers={"Host": host,
                                               "Authorization": f"Bearer {TOKEN}"})
            else:
                r = await client.get("/api/runs", headers={"Host": host})
            return r.status, await r.text()

    return asyncio.run(go())


@pytest.mark.parametrize("listen_host, host, served", [
    ("127.0.0.1", "127.0.0.1:8765", True),
    ("127.0.0.1", "localhost:8765", True),
    ("127.0.0.1", "LOCALHOST.", True),
    ("127.0.0.1", "[::1]:8765", True),
    ("127.0.0.1", "attacker.example:8765", False),  # DNS rebinding: a name that is not ours
    ("127.0.0.1", "10.1.2.3:8765", False),
    (None, "127.0.0.1", True),  # make_app alone: loopback names only
    (None, "attacker.example", False),
    ("10.1.2.3", "10.1.2.3:8765", True),
    ("10.1.2.3", "cell-12.plant.example", False),
    ("0.0.0.0", "10.9.8.7:8765", True),  # every address: any address, still no other name
    ("0.0.0.0", "[fe80::1]:8765", True),
    ("0.0.0.0", "attacker.example", False),
    ("cell-12.plant.example", "Cell-12.Plant.Example:8765", True),
    ("127.0.0.1", "cell-12.plant.example", True),  # web.hosts names it
])
def test_a_foreign_host_header_is_refused(cell, listen_host, host, served):
    """DNS rebinding: a page of another name that resolves to the page's address must get
    nothing (runs, parameter sets, actions): only the listen host, the loopback names and
    ``web.hosts`` are served, anything else is 421 with one line."""
    base = load_daemon_config(cell.config)
    cfg = base.__class__(**{**base.__dict__, "web": base.web.__class__(
        hosts=("cell-12.plant.example",) if listen_host == "127.0.0.1" else ())})
    for post in (False, True):
        status, text = _status_for_host(cfg, listen_host, host, post)
        if served:
            assert status == 200, (host, post, text)
        else:
            assert status == 421, (host, post, text)
            assert text.count("\n") == 1 and "not a name of this page" in text
            assert "web.hosts" in text


def test_web_hosts_names_hosts(tmp_path):
    cfg = load_daemon_config(write_config(tmp_path, hosts=["cell-12.plant.example", "10.0.0.7"]))
    assert cfg.web.hosts == ("cell-12.plant.example", "10.0.0.7")


def test_the_read_only_page_refuses_every_action(cell):
    cfg = load_daemon_config(cell.config)
    before = _runs(cell.state)
    with serving(WebServer(cfg, "127.0.0.1:0", cell.robot)) as url:
        status, text = post(url + "actions/start", {"campaign": "nightly", "token": TOKEN},
                            {"Authorization": f"Bearer {TOKEN}"})
        assert status == 403 and "read-only page (robid web)" in json.loads(text)["error"]
    assert _runs(cell.state) == before


def test_another_address_than_loopback_needs_tls_and_a_token(tmp_path):
    cfg = load_daemon_config(write_config(tmp_path))
    with pytest.raises(ConfigError, match=r"web.listen: 0.0.0.0:8765 is not a loopback "
                       r"address; serving it needs TLS and a token \(missing: tls_cert, "
                       r"tls_key, token\)"):
        WebServer(cfg, "0.0.0.0:8765", "arm3")
    cfg = load_daemon_config(write_config(tmp_path, token=TOKEN, tls_cert="c.pem"))
    with pytest.raises(ConfigError, match=r"\(missing: tls_key\)"):
        WebServer(cfg, "10.1.2.3:8765", "arm3")
    with pytest.raises(ConfigError, match="web.listen: expected HOST:PORT"):
        WebServer(cfg, "8765", "arm3")


def test_robid_web_refuses_in_one_line(tmp_path, capsys):
    from robid_link.cli import main

    cfg = write_config(tmp_path)
    assert main(["web", "--config", str(cfg)]) == 2  # no store yet
    assert capsys.readouterr().err.strip().endswith("holds no store yet")
    with Store(tmp_path / "state"):
        pass
    assert main(["web", "--config", str(cfg), "--listen", "0.0.0.0:8765"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "missing: tls_cert, tls_key, token" in err


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not found")
def test_tls_serves_https(cell, tmp_path):
    import ssl

    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
                    "-subj", "/CN=127.0.0.1", "-keyout", str(tmp_path / "k.pem"), "-out",
                    str(tmp_path / "c.pem")], check=True, capture_output=True)
    base = load_daemon_config(cell.config)
    cfg = base.__class__(**{**base.__dict__, "web": base.web.__class__(
        tls_cert=tmp_path / "c.pem", tls_key=tmp_path / "k.pem", token=TOKEN)})
    ctx = ssl.create_default_context(cafile=str(tmp_path / "c.pem"))
    ctx.check_hostname = False
    with serving(WebServer(cfg, "127.0.0.1:0", cell.robot)) as url:
        assert url.startswith("https://")
        with urllib.request.urlopen(url + "api/runs", context=ctx, timeout=30) as r:
            assert json.loads(r.read())["robot"] == "arm3"
    bad = cfg.__class__(**{**cfg.__dict__, "web": cfg.web.__class__(
        tls_cert=tmp_path / "k.pem", tls_key=tmp_path / "k.pem")})
    with pytest.raises(ConfigError, match="not a certificate and its key"):
        WebServer(bad, "127.0.0.1:0", "arm3")


def test_the_token_file_is_private(tmp_path):
    cfg = load_daemon_config(write_config(tmp_path))
    state = tmp_path / "state"
    state.mkdir()
    assert load_token(cfg.web, state, create=False) is None
    token = load_token(cfg.web, state, create=True)  # the daemon's first start
    path = state / "web.token"
    assert token and len(token) >= 32 and os.stat(path).st_mode & 0o777 == 0o600
    assert load_token(cfg.web, state, create=True) == token
    path.chmod(0o644)
    with pytest.raises(ConfigError, match=r"web.token_file: .*web.token is readable by others "
                       r"\(mode 0644; chmod 600 it\)"):
        load_token(cfg.web, state, create=False)


@pytest.mark.parametrize("web, message", [
    ({"listen": 8765}, "web.listen: expected text, got 8765"),
    ({"port": 1}, "web: unknown key 'port'"),
    ({"token": "short"}, "web.token: at least 16 characters"),
    ({"token": TOKEN, "token_file": "t"}, "web: give token or token_file, not both"),
    ({"hosts": "cell-12"}, "web.hosts: expected a list of host names, got 'cell-12'"),
    ({"hosts": ["http://cell-12"]}, r"web.hosts\[0\]: expected a host name or address "
     r"\(no scheme or port\), got 'http://cell-12'"),
])
def test_web_config_errors_name_the_key(tmp_path, web, message):
    with pytest.raises(ConfigError, match=message):
        load_daemon_config(write_config(tmp_path, **web))


def test_the_daemon_serves_its_page_with_actions(tmp_path):
    """``web: {listen}``: the daemon's page; a POST without the token is refused and starts
    nothing; with the token (the daemon made its file) the request reaches the daemon."""
    import aiohttp

    from robid_link.link.daemon import Daemon
    from robid_link.web.command import daemon_service

    cfg = load_daemon_config(write_config(tmp_path, listen="127.0.0.1:0"))

    async def go() -> tuple[int, int, dict[str, Any], int]:
        async with Daemon(cfg, env={}) as d, daemon_service(cfg)(d) as srv, \
                aiohttp.ClientSession() as http:
            async with http.post(srv.url + "actions/start", data={"campaign": "nightly"}) as r:
                refused = r.status
            token = (tmp_path / "state" / "web.token").read_text().strip()
            async with http.post(srv.url + "actions/cancel", data={"run_id": "nope"},
                                 headers={"Authorization": f"Bearer {token}"}) as r:
                status, answer = r.status, await r.json()
            assert d.store is not None
            return refused, status, answer, len(await d.store.runs())

    refused, status, answer, runs = asyncio.run(go())
    assert refused == 403 and runs == 0
    assert status == 400 and answer["error"] == "run nope: not in the store"


def test_the_daemons_page_starts_only_approved_programs(tmp_path):
    """A start from the page is unattended (the page may be far from the cell): with the
    token and programs nobody approved, it is refused in one line and nothing is queued."""
    import aiohttp

    from robid_link.link.daemon import Daemon
    from robid_link.web.command import daemon_service

    cfg = load_daemon_config(write_config(tmp_path, listen="127.0.0.1:0"))

    async def go() -> tuple[int, dict[str, Any], int]:
        async with Daemon(cfg, env={}) as d, daemon_service(cfg)(d) as srv, \
                aiohttp.ClientSession() as http:
            token = (tmp_path / "state" / "web.token").read_text().strip()
            async with http.post(srv.url + "actions/start", data={"campaign": "nightly"},
                                 headers={"Authorization": f"Bearer {token}"}) as r:
                status, answer = r.status, await r.json()
            assert d.store is not None
            return status, answer, len(await d.store.runs())

    status, answer, runs = asyncio.run(go())
    assert status == 400 and runs == 0
    assert answer["error"].startswith("web start refused: the program of experiment ")
    assert "robid campaign approve nightly --config" in answer["error"]
    assert "\n" not in answer["error"]


def _named(path: Path, robot_name: str | None = None, robot: str | None = None) -> Path:
    """The config at ``path`` with ``robot_name`` (and another robot description) set."""
    import yaml

    doc = yaml.safe_load(path.read_text())
    doc.update({k: v for k, v in (("robot_name", robot_name), ("robot", robot)) if v})
    path.write_text(yaml.safe_dump(doc))
    return path


def test_the_daemons_page_names_the_robot_as_its_store_does(tmp_path):
    """``robot_name: cell-a``: the daemon's page shows cell-a's runs, trend and parameter
    sets (it showed the description's name, arm3, and none of them)."""
    import aiohttp

    from robid_link.link.daemon import Daemon
    from robid_link.web.command import daemon_service

    cfg = load_daemon_config(_named(write_config(tmp_path, listen="127.0.0.1:0"), "cell-a"))
    record = {"robot": "arm3", "parameters": [{"name": "m_1", "value": 1.0, "std": 0.1}],
              "effects": [], "rmse": [1.0]}

    async def go() -> tuple[str | None, dict[str, Any], dict[str, Any], dict[str, Any]]:
        async with Daemon(cfg, env={}) as d, daemon_service(cfg)(d) as srv, \
                aiohttp.ClientSession() as http:
            assert d.store is not None
            run_id = await d.store.create_run("nightly", "operator", {}, [("a", "rigid_body")])
            await d.store.add_result(run_id, "cell-a", "identify", record)
            await d.store.add_param_set({"sha256": "ab" * 32, "robot": "cell-a",
                                         "run_id": run_id}, b"{}")
            got = []
            for page in ("runs", "trend", "params"):
                async with http.get(srv.url + "api/" + page) as r:
                    got.append(await r.json())
            return d.robot_name, *got

    name, runs, trend, params = asyncio.run(go())
    assert name == runs["robot"] == trend["robot"] == "cell-a"
    assert len(runs["runs"]) == 1 and [r["version"] for r in trend["runs"]] == [1]
    assert [r["robot"] for r in params["robots"]] == ["cell-a"]


@pytest.mark.parametrize("robot_name, robot, expected", [
    ("cell-a", None, "cell-a"),  # the config's name first
    (None, None, "arm3"),  # else the description's
    (None, "broken.yaml", "broken"),  # else the file's stem (read-only commands still open)
])
def test_one_rule_names_the_robot(tmp_path, robot_name, robot, expected):
    """``config.robot_name``: what the daemon, its page, ``robid web`` and the operator's
    commands call the robot."""
    from robid_link.config import robot_name as rule
    from robid_link.ident.model.robot import description_name

    (tmp_path / "broken.yaml").write_text("joints: 3\n")
    path = _named(write_config(tmp_path), robot_name, robot and str(tmp_path / robot))
    cfg = load_daemon_config(path)
    assert rule(cfg, description_name(cfg.robot, cfg.lock)) == expected


def test_status_and_results_print_the_report_of_a_finished_run(cell, capsys):
    from robid_link.cli import main

    page = cell.state / "reports" / cell.runs["reported"] / "report.html"
    for cmd in ("status", "results"):
        assert main([cmd, "--config", str(cell.config)]) == 0
        out = capsys.readouterr().out
        assert f"report {cell.runs['reported']}: {page}" in out, cmd
        assert cell.runs["older"] not in out.split("report ")[-1]  # it has no report.html


def test_the_fleet_page_shows_every_robot_of_the_store(cell, tmp_path):
    """/fleet: robid fleet's report of the store (per robot and model version: runs, drift
    flags; outliers per type), JSON at /api/fleet; an empty store is said, not an error."""
    cfg = load_daemon_config(cell.config)
    with serving(WebServer(cfg, "127.0.0.1:0", cell.robot)) as url:
        view = json.loads(get(url + "api/fleet")[1])
        assert [r["robot"] for r in view["robots"]] == ["arm3"]
        versions = view["robots"][0]["versions"]
        assert len(versions) == 2 and any("offset@2" in label for label in versions)
        assert [len(v["runs"]) for v in versions.values()] == [1, 1]
        status, page, _ = get(url + "fleet")
        assert status == 200 and 'data-figure="fleet-robots"' in page
        assert "/trend?robot=arm3" in page and f"/runs/{cell.runs['reported']}" in page
        assert '<a href="/fleet">Fleet</a>' in get(url)[1]
    empty = load_daemon_config(write_config(tmp_path))
    Store(empty.state_dir).close()  # a store without a robot yet
    with serving(WebServer(empty, "127.0.0.1:0", cell.robot)) as url:
        status, page, _ = get(url + "fleet")
        assert status == 200 and "No robot in" in page
        assert json.loads(get(url + "api/fleet")[1])["robots"] == []
