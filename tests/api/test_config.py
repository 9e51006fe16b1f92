"""`GET /config` of both services (in-process): the parameters in force as the service
resolved them, never a secret, behind the service's own access rules."""

from __future__ import annotations

import dataclasses

import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr
from pydantic_settings import BaseSettings

from fleetmap.services.aligner.config import Settings as AlignerSettings
from fleetmap.services.aligner.main import create_app as create_aligner
from fleetmap.services.place_db.config import Settings
from fleetmap.services.place_db.main import create_app
from fleetmap.services.schemas import ConfigView, redact_url

OP, TOK_A, AL_TOK = "op-secret-4711", "robot-a-secret-4712", "aligner-secret-4713"
PG_PASS, QUERY_PASS, URL_PASS = "pg-pass-4714", "query-pass-4715", "url-pass-4716"
SECRETS = (OP, TOK_A, AL_TOK, PG_PASS, QUERY_PASS, URL_PASS)
PG_URL = (
    f"postgresql://fleet:{PG_PASS}@db.example:5433/fleetmap?sslmode=require&password={QUERY_PASS}"
)


def _auth(tok: str) -> dict:
    return {"authorization": f"Bearer {tok}"}


@pytest.fixture
def tuned(tmp_path, monkeypatch):
    """A secured place database whose cascade and live map are set from the environment,
    with every kind of secret configured. Its lifespan is not run (PostgreSQL is named but
    absent): `/config` reads the settings only."""
    monkeypatch.setenv("FLEETMAP_PLACE_DB_CASCADE__MAX_VERIFY", "7")
    monkeypatch.setenv("FLEETMAP_PLACE_DB_CASCADE__MATCH__RATIO", "0.8")
    monkeypatch.setenv("FLEETMAP_PLACE_DB_LIVE__POLL_S", "0.5")
    monkeypatch.setenv("FLEETMAP_PLACE_DB_AUTO_RETRAIN", "false")
    st = Settings(
        data_dir=tmp_path,
        database=PG_URL,
        operator_token=OP,
        robot_tokens={"A": TOK_A},
        aligner=f"http://fleet:{URL_PASS}@aligner:8200,http://aligner2:8200",
        aligner_token=AL_TOK,
    )
    return TestClient(create_app(st, announce=False)), st


@pytest.fixture
def aligner(monkeypatch):
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__MIN_INLIERS", "21")
    monkeypatch.setenv("FLEETMAP_ALIGNER_MAX_PAIRS", "100")
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__GEOMETRIC__SEEDS", "8")
    monkeypatch.setenv("FLEETMAP_ALIGNER_ALIGN__SECOND__PER_VIEW", "200")
    st = AlignerSettings(operator_token=OP, robot_tokens={"A": TOK_A})
    with TestClient(create_aligner(st, announce=False)) as c:
        yield c, st


def test_place_db_config_answers_the_settings_in_force(tuned):
    client, st = tuned
    r = client.get("/config", headers=_auth(OP))
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["cascade"]["max_verify"] == 7 and body["cascade"]["match"]["ratio"] == 0.8
    assert body["cascade"] == dataclasses.asdict(st.cascade)  # every knob, nested
    assert body["live"]["poll_s"] == 0.5 and body["live"] == dataclasses.asdict(st.live)
    assert body["auto_retrain"] is False and body["background_overlaps"] is True
    assert body["data_dir"] == str(st.data_dir) and body["db_file"] == st.db_file
    assert body["max_body_bytes"] == st.max_body_bytes and body["vocabulary"] is None


def test_place_db_config_never_shows_a_secret(tuned):
    client, _ = tuned
    r = client.get("/config", headers=_auth(OP))
    assert not [s for s in SECRETS if s in r.text]
    body = r.json()
    assert not {"operator_token", "robot_tokens", "aligner_token"} & set(body)
    assert body["database"] == (
        "postgresql://fleet:***@db.example:5433/fleetmap?sslmode=require&password=***"
    )
    assert body["aligner"] == "http://fleet:***@aligner:8200,http://aligner2:8200"
    schema = client.get("/openapi.json").text
    assert "operator_token" not in schema and not [s for s in SECRETS if s in schema]


def test_place_db_config_is_the_operators(tuned):
    client, _ = tuned
    assert client.get("/config").status_code == 401
    assert client.get("/config", headers=_auth("nope")).status_code == 401
    r = client.get("/config", headers=_auth(TOK_A))  # a robot's token: not its business
    assert r.status_code == 403 and r.json()["error"] == "Forbidden"
    assert not [s for s in SECRETS if s in r.text]


def test_open_place_db_answers_anyone_from_a_running_service(tmp_path):
    with TestClient(create_app(Settings(data_dir=tmp_path), announce=False)) as c:
        r = c.get("/config")
        assert r.status_code == 200
        assert r.json()["database"] is None and r.json()["aligner"] is None


def test_aligner_config_answers_the_settings_in_force(aligner):
    client, st = aligner
    r = client.get("/config", headers=_auth(TOK_A))  # any valid token, as /align
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["align"]["min_inliers"] == 21 and body["max_pairs"] == 100
    assert body["align"]["geometric"]["seeds"] == 8  # the third look's, nested in its turn
    assert body["align"]["second"]["per_view"] == 200 and st.align.second.per_view == 200
    assert body["align"] == dataclasses.asdict(st.align)
    assert not {"operator_token", "robot_tokens"} & set(body)
    assert not [s for s in SECRETS if s in r.text]
    assert client.get("/config").status_code == 401
    assert client.get("/config", headers=_auth("nope")).status_code == 401


@pytest.mark.parametrize(
    "name, value, named",
    [
        ("GEOMETRIC__SEEDS", "0", "seeds >= 1"),
        ("SECOND__PER_VIEW", "0", "per_view >= 1"),
        ("SECOND__RATIO", "1.5", "ratio must lie in"),
        ("SECOND__VIEWS", "six", "views"),
    ],
)
def test_aligner_refuses_a_look_it_cannot_run(monkeypatch, name, value, named):
    """A setting the second or third look could not run with is refused at start-up,
    named."""
    from pydantic import ValidationError

    monkeypatch.setenv(f"FLEETMAP_ALIGNER_ALIGN__{name}", value)
    with pytest.raises(ValidationError, match=named):
        AlignerSettings()


@pytest.mark.parametrize(
    "settings, variable, value, named",
    [
        (Settings, "FLEETMAP_PLACE_DB_OPERATOR_TOKEN", "", "OPERATOR_TOKEN: Value error, is empty"),
        (AlignerSettings, "FLEETMAP_ALIGNER_OPERATOR_TOKEN", "", "OPERATOR_TOKEN: Value error"),
        (Settings, "FLEETMAP_PLACE_DB_ALIGNER", "notaurl", "ALIGNER: Value error, must be an http"),
        (Settings, "FLEETMAP_PLACE_DB_DATA_DIR", "/etc/hostname", "DATA_DIR: Value error, is not"),
        (Settings, "FLEETMAP_PLACE_DB_ROBOT_TOKENS", '{"a": "x"', 'parsing value for field "robot'),
        (AlignerSettings, "FLEETMAP_ALIGNER_MAX_PAIRS", "-1", "MAX_PAIRS: Input should be greater"),
        (AlignerSettings, "FLEETMAP_ALIGNER_CLOUD_CACHE", "0", "CLOUD_CACHE: Input should be"),
    ],
)
def test_a_setting_that_cannot_work_is_one_line_at_start(
    monkeypatch, settings, variable, value, named
):
    """Each was accepted, or a traceback, before an outside tester's review (session 51): an
    empty token locked every operator route, an aligner that is not a URL failed on every
    pair once robots streamed, a file as the data folder, a JSON typo, a negative limit."""
    from fleetmap.errors import BadInput
    from fleetmap.services.commands import _settings

    monkeypatch.setenv(variable, value)
    with pytest.raises(BadInput, match=named) as caught:
        _settings(settings)
    assert 'x"' not in str(caught.value)  # a token's value is never in the line


@pytest.mark.parametrize("service", ["place-db", "aligner"])
def test_config_refuses_other_methods_and_ignores_query_strings(service, tuned, aligner):
    client = tuned[0] if service == "place-db" else aligner[0]
    good = client.get("/config", headers=_auth(OP)).json()
    for method in ("post", "put", "patch", "delete"):
        r = client.request(method, "/config", headers=_auth(OP), content=b"{}")
        assert r.status_code == 405 and r.headers["allow"] == "GET", method
    for query in ("?cascade__max_verify=1", "?align=x&align=y", "?%00=%ff", "?" + "a=1&" * 500):
        r = client.get(f"/config{query}", headers=_auth(OP))
        assert r.status_code == 200 and r.json() == good, query
    r = client.get("/config/", headers=_auth(OP), follow_redirects=False)
    assert r.status_code == 307 and r.headers["location"].endswith("/config")  # as every route
    op = client.get("/openapi.json").json()["paths"]["/config"]
    assert list(op) == ["get"] and op["get"]["security"] == [{"HTTPBearer": []}]
    ref = op["get"]["responses"]["200"]["content"]["application/json"]["schema"]["$ref"]
    assert ref.endswith("PlaceDBConfig" if service == "place-db" else "AlignerConfig")


def test_new_settings_named_or_typed_as_secrets_stay_out():
    """The answer is built from the settings class: a setting added later shows up by
    itself, unless it holds a SecretStr or is named like a secret."""

    class Later(BaseSettings):
        threshold: float = 0.5
        webhook_password: str = "pw-later"
        api_key: str = "key-later"
        signing: SecretStr = SecretStr("signing-later")
        keys: dict[str, SecretStr] = {"a": SecretStr("nested-later")}
        keyframes: int = 3

    view = ConfigView(Later, "LaterConfig")
    assert set(view.model.model_fields) == {"threshold", "keyframes"}
    assert view.answer(Later()).model_dump() == {"threshold": 0.5, "keyframes": 3}


@pytest.mark.parametrize(
    ("url", "shown"),
    [
        ("http://aligner:8200", "http://aligner:8200"),
        ("http://user@host:1/x", "http://user@host:1/x"),
        ("http://user:pw@host:1/x#frag", "http://user:***@host:1/x"),
        ("http://:pw@host", "http://:***@host"),
        ("http://a:p1@h1, http://b:p2@h2", "http://a:***@h1,http://b:***@h2"),
        (
            "postgresql://u:p@h/db?sslpassword=s&sslmode=x",
            "postgresql://u:***@h/db?sslpassword=***&sslmode=x",
        ),
        ("postgresql://u:p%40ss@h/db", "postgresql://u:***@h/db"),
        ("not a url", "not a url"),
    ],
)
def test_redact_url(url, shown):
    assert redact_url(url) == shown
