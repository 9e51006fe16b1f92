"""Property-based fuzzing of both services from their OpenAPI schemas (schemathesis
strategies driven by hypothesis): whatever the input, no 5xx and no hang."""

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings

from tests.servers import Service


def _fuzz(schema, examples: int) -> list[str]:
    """Every operation with `examples` generated requests; returns the ones that hit 5xx."""
    failures: list[str] = []
    for result in schema.get_all_operations():
        _fuzz_operation(result.ok(), examples, failures)
    return failures


def _fuzz_operation(op, examples: int, failures: list[str]) -> None:
    @settings(
        max_examples=examples,
        deadline=None,
        database=None,
        derandomize=True,
        suppress_health_check=list(HealthCheck),
    )
    @given(case=op.as_strategy())
    def run(case):
        response = case.call(timeout=60)
        if response.status_code >= 500:
            failures.append(
                f"{op.method.upper()} {op.path} -> {response.status_code}: {response.text[:200]}"
            )

    run()


@pytest.mark.parametrize("kind", ["place-db", "aligner"])
def test_no_5xx_and_no_hang(kind, tmp_path):
    svc = Service(kind, tmp_path / "db" if kind == "place-db" else None).start()
    try:
        schema = schemathesis.openapi.from_url(svc.url + "/openapi.json")
        assert _fuzz(schema, examples=60) == []
        assert svc.proc.poll() is None  # still alive
    finally:
        svc.stop()
