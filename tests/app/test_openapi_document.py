# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""The OpenAPI document says what a generated client needs (an integrator's review).

- how to authenticate: the Bearer scheme, on every API route but the login, so that a
  generated client sends the key;
- what a route really answers: the FHIR route's ``application/fhir+json`` (not an
  ``application/json`` of any shape), the visit report's ``409`` (docs/api.md: every
  status a route can answer is listed).
"""

from __future__ import annotations

from api_support import Api, api, make_api_key  # noqa: F401 - fixtures


def test_every_api_route_but_the_login_asks_for_the_bearer_key(api: Api) -> None:
    doc = api.client.get("/openapi.json").json()
    scheme = doc["components"]["securitySchemes"]["bearerAuth"]
    assert (scheme["type"], scheme["scheme"]) == ("http", "bearer")
    secured, public = [], []
    for path, operations in doc["paths"].items():
        for method, op in operations.items():
            (secured if op.get("security") else public).append(f"{method.upper()} {path}")
            if op.get("security"):
                assert op["security"] == [{"bearerAuth": []}]
                assert "401" in op["responses"], (method, path)
    assert sorted(public) == ["GET /health", "POST /api/v1/auth/login"]
    assert "GET /api/v1/audit" in secured and "POST /api/v1/sessions/{session_id}/trials" in secured
    # What the document says is what the routes do: without the key, 401; with it, 200.
    assert api.client.get("/api/v1/rigs").status_code == 401
    assert api.client.get("/api/v1/rigs", headers=api.headers).status_code == 200


def test_the_fhir_route_answers_fhir_json_only(api: Api) -> None:
    doc = api.client.get("/openapi.json").json()
    ok = doc["paths"]["/api/v1/trials/{trial_id}/fhir"]["get"]["responses"]["200"]
    assert list(ok["content"]) == ["application/fhir+json"]
    assert ok["content"]["application/fhir+json"]["schema"] == {"type": "object"}


def test_the_visit_report_lists_its_409(api: Api) -> None:
    doc = api.client.get("/openapi.json").json()
    pdf = doc["paths"]["/api/v1/sessions/{session_id}/report.pdf"]["get"]["responses"]
    assert "409" in pdf and "application/json" in pdf["409"]["content"]
