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
        assert "torch==2.13.0" in text and f"EXPOSE {args.port}" in text
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
        assert "--index-url ${TORCH_INDEX}" in text
