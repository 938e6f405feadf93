"""The pages the server serves to browsers: the dashboard and the API docs, every asset from this server."""

from __future__ import annotations

import re

from server.dashboard.pages import STATIC
from tests.server.conftest import Api


def test_the_root_leads_to_the_dashboard(sqlite_api: Api) -> None:
    for path in ("/", "/dashboard"):
        r = sqlite_api.client.get(path, follow_redirects=False)
        assert r.status_code == 307
        assert r.headers["location"] == "/dashboard/"
    page = sqlite_api.client.get("/dashboard/")
    assert page.status_code == 200
    assert page.headers["content-type"].startswith("text/html")
    assert 'id="app" data-building="" data-users="0" data-updated-ms="0"' in page.text
    # its own scripts only, talking only to this server, never framed, never leaking the URL
    csp = page.headers["content-security-policy"]
    assert "default-src 'self'" in csp
    assert "frame-ancestors 'none'" in csp
    assert "unsafe-inline" not in csp
    assert page.headers["referrer-policy"] == "no-referrer"
    assert page.headers["x-frame-options"] == "DENY"
    # nothing about the pages in the API's spec
    paths = sqlite_api.client.get("/openapi.json").json()["paths"]
    assert not any(p.startswith(("/dashboard", "/docs")) or p == "/" for p in paths)


def test_every_asset_the_page_names_is_served_and_none_is_remote(sqlite_api: Api) -> None:
    index = (STATIC / "index.html").read_text()
    named = set(re.findall(r'(?:src|href)="(/[^"]+)"', index))
    for source in STATIC.glob("*.js"):
        text = source.read_text()
        named |= {f"/dashboard/assets/{m}" for m in re.findall(r'from "\./([^"]+)"', text)}
        assert not re.search(r"https?://", text), f"{source.name} names a remote URL"
    assert {
        "/dashboard/assets/main.js",
        "/dashboard/assets/map.js",
        "/dashboard/assets/dashboard.css",
    } <= named
    for path in named:
        r = sqlite_api.client.get(path)
        assert r.status_code == 200, path
    assert (
        sqlite_api.client.get("/dashboard/assets/main.js")
        .headers["content-type"]
        .startswith("text/javascript")
    )
    assert sqlite_api.client.get("/dashboard/assets/nothing.js").status_code == 404
    assert sqlite_api.client.get("/favicon.ico").status_code == 200


def test_the_api_docs_load_their_assets_from_this_server(sqlite_api: Api) -> None:
    for page in ("/docs", "/redoc"):
        html = sqlite_api.client.get(page).text
        remote = re.findall(r'(?:src|href)=["\'](https?://[^"\']+)', html)
        assert remote == [], f"{page} loads {remote}"
        for asset in re.findall(r'(?:src|href)=["\'](/[^"\']+)', html):
            assert sqlite_api.client.get(asset).status_code == 200, asset
    redoc = sqlite_api.client.get("/docs-assets/redoc.standalone.js")
    assert redoc.status_code == 200
    assert b"cdn.redoc.ly" not in redoc.content
    assert len(redoc.content) > 500_000  # ReDoc itself, not a stand-in
