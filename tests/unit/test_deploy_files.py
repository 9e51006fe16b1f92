"""docker-compose.yml and the Dockerfiles match the project's real entry points (there is
no Docker engine here to build them)."""

import re
from pathlib import Path

import yaml

from fleetmap.services.cli import build_parser
from fleetmap.services.place_db.config import Settings as PlaceSettings

ROOT = Path(__file__).resolve().parents[2]


def test_compose_structure():
    c = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    assert set(c["services"]) == {"place-db", "aligner"}
    assert "place-db-data" in c["volumes"]
    for name, svc in c["services"].items():
        assert (ROOT / svc["build"]["dockerfile"]).is_file()
        assert svc["healthcheck"]["test"][0] == "CMD"
        assert any("/healthz" in part for part in svc["healthcheck"]["test"])
        for var in svc.get("environment", {}):
            prefix = "FLEETMAP_PLACE_DB_" if name == "place-db" else "FLEETMAP_ALIGNER_"
            assert var.startswith(prefix)
            if name == "place-db":
                assert var.removeprefix(prefix).lower() in PlaceSettings.model_fields
    assert "place-db-data:/data" in c["services"]["place-db"]["volumes"]


def test_dockerfile_commands_are_real_cli_commands():
    parser = build_parser()
    for name in ("place_db", "aligner"):
        text = (ROOT / "docker" / f"{name}.Dockerfile").read_text()
        cmd = re.search(r"^CMD (\[.*\])$", text, re.M).group(1)
        argv = yaml.safe_load(cmd)
        assert argv[0] == "fleetmap"
        args = parser.parse_args(argv[1:])  # exits on an unknown command or option
        assert args.command == "serve" and args.host == "0.0.0.0"
        assert f"EXPOSE {args.port}" in text
        # sources from the build context (not COPY --from=<stage>)
        for src in re.findall(r"^COPY (?!--from)(\S+)", text, re.M):
            assert (ROOT / src).exists(), src


def test_deployment_conventions():
    """Issue 14 item 7: ports bindable beyond loopback, a start period, a stop grace period
    longer than the 30 s drain, no root, base image and torch source as build arguments."""
    c = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    for svc in c["services"].values():
        assert svc["ports"][0].startswith("${FLEETMAP_BIND:-127.0.0.1}:")
        assert svc["healthcheck"]["start_period"] == "30s"
        assert int(svc["stop_grace_period"].rstrip("s")) > 30
    for name in ("place_db", "aligner"):
        text = (ROOT / "docker" / f"{name}.Dockerfile").read_text()
        assert re.search(r"^USER fleetmap$", text, re.M)
        assert "ARG BASE_IMAGE=" in text and "FROM ${BASE_IMAGE}" in text
        assert "--extra-index-url ${TORCH_INDEX}" in text


def _lock() -> dict[str, tuple[str, list[str]]]:
    """docker/requirements.lock: name -> (version, hashes)."""
    text = (ROOT / "docker" / "requirements.lock").read_text()
    pins = {}
    for block in re.split(r"\n(?=\S)", text):
        if block.startswith("#"):
            continue
        m = re.match(r"([A-Za-z0-9._-]+)==(\S+)", block)
        assert m, f"not pinned with ==: {block.splitlines()[0]}"
        pins[m.group(1).lower()] = (m.group(2), re.findall(r"--hash=sha256:([0-9a-f]{64})", block))
    return pins


def test_images_install_the_hashed_lock_only():
    for name in ("place_db", "aligner"):
        text = (ROOT / "docker" / f"{name}.Dockerfile").read_text()
        assert "pip install --no-cache-dir --require-hashes -r /tmp/requirements.lock" in text
        assert "COPY docker/requirements.lock /tmp/requirements.lock" in text
        # the project itself built with the locked build backend into a wheel, installed
        # alone on the locked venv (no index reached): no other requirement
        assert re.findall(r"pip (?:install|wheel) [^\n]*", text) == [
            "pip install --no-cache-dir --require-hashes -r /tmp/requirements.lock \\",
            "pip wheel --no-cache-dir --no-deps --no-build-isolation --wheel-dir /wheels /src",
            "pip install --no-cache-dir --no-deps --no-index /tmp/wheels/*.whl"
            " && rm -rf /tmp/wheels",
        ]
        # the venv of the dependencies is copied from the stage before the project's
        assert "COPY --from=deps /opt/venv /opt/venv" in text
    pins = _lock()
    assert all(hashes for _, hashes in pins.values())
    assert pins["torch"][0] == "2.13.0+cpu" and "open3d-cpu" in pins and "open3d" not in pins
    assert {"setuptools", "wheel"} <= set(pins)


def test_the_lock_satisfies_pyproject():
    """scripts/lock.sh makes the lock again after a dependency changes in pyproject.toml."""
    import tomllib

    from packaging.requirements import Requirement

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    pins = _lock()
    for line in project["dependencies"] + project["optional-dependencies"]["server"]:
        req = Requirement(line)
        name = "open3d-cpu" if req.name == "open3d" else req.name.lower()
        assert name in pins, f"{name} is not in docker/requirements.lock: run scripts/lock.sh"
        version = pins[name][0]
        assert req.specifier.contains(version, prereleases=True), (
            f"docker/requirements.lock pins {name}=={version}, pyproject.toml asks {line}: "
            "run scripts/lock.sh"
        )
    build = tomllib.loads((ROOT / "pyproject.toml").read_text())["build-system"]["requires"]
    for line in build:
        req = Requirement(line)
        assert req.specifier.contains(pins[req.name][0]), line
