"""Property-based test of the REST API against its own OpenAPI document (schemathesis).

For every operation, schemathesis generates requests from the schema (valid
and invalid ones), sends them with a full-scope API key to the ASGI app over a
real migrated SQLite database that holds one patient, rig, session, trial and
result (so small ids hit real rows), and checks that:

- no answer is a 5xx (``not_a_server_error``);
- every status is documented for the operation (``status_code_conformance``);
- the body matches the documented schema and content type.

Bounded: a few examples per operation (the whole module takes well under 40 s).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
import schemathesis
from api_support import make_api_key, seed_recording_target, trial_files, write_video
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from app.main import create_app

MAX_EXAMPLES = 6  # per operation and mode; ~30 operations


@pytest.fixture
def fuzz_app(app_settings, db_sessionmaker, tmp_path) -> Iterator[tuple[Any, str]]:
    from api_support import Api, add_result

    app = create_app(app_settings)
    key = make_api_key(db_sessionmaker)
    with TestClient(app) as client:
        api = Api(app, client, app_settings, db_sessionmaker, key)
        seeded = seed_recording_target(api)
        left = write_video(tmp_path / "l.mp4")
        right = write_video(tmp_path / "r.mp4", shift_px=2)
        r = client.post(
            f"/api/v1/sessions/{seeded.session_id}/trials",
            data={"hand": "left"},
            files=trial_files(left, right),
            headers=api.headers,
        )
        assert r.status_code == 201, r.text
        add_result(api, r.json()["id"])
        yield app, key


OPERATIONS_MIN = 25  # the API has about 30 operations; fewer means the schema lost some


@pytest.mark.parametrize("mode", ["positive", "negative"])
def test_api_conforms_to_its_openapi_document(fuzz_app, mode: str) -> None:
    app, key = fuzz_app
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= OPERATIONS_MIN
    failures: list[str] = []
    for operation in operations:
        if operation.path.endswith(("/report.pdf", "/fhir")) and mode == "positive":
            # rendering a PDF takes seconds; both are exercised in test_api_results
            continue
        strategy = operation.as_strategy(GenerationMode(mode))

        @given(case=strategy)
        @settings(
            max_examples=MAX_EXAMPLES,
            deadline=None,
            derandomize=True,  # the same examples on every run
            suppress_health_check=list(HealthCheck),
            database=None,
        )
        def check(case: Any) -> None:
            case.call_and_validate(
                headers={"Authorization": f"Bearer {key}"},
                checks=[
                    not_a_server_error,
                    status_code_conformance,
                    content_type_conformance,
                    response_schema_conformance,
                ],
            )

        try:
            check()
        except Unsatisfiable:
            assert mode == "negative"  # no parameter or body to get wrong (e.g. /health)
        except Exception as exc:  # collect every failing operation, then fail once
            failures.append(f"{operation.method.upper()} {operation.path}: {exc}")
    assert not failures, "\n\n".join(failures)
