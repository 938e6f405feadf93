"""The phone page at ``/phone/``: every asset from this server, opened as
``/phone/#key=<device key>&building=<id>`` (the fragment never reaches the server). It draws with the
dashboard's map and talks to the same public API as any other phone."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from server.dashboard.pages import PAGE_HEADERS

STATIC = Path(__file__).parent / "static"
PHONE = "/phone/"
ASSETS = "/phone/assets"

# Motion sensors and the camera (a tag's QR code) for this page's own origin only; nothing else.
PHONE_HEADERS = {
    **PAGE_HEADERS,
    "Permissions-Policy": (
        "accelerometer=(self), gyroscope=(self), magnetometer=(self), camera=(self), "
        "geolocation=(), microphone=(), payment=(), usb=()"
    ),
}


def install_phone_page(app: FastAPI) -> None:
    app.mount(ASSETS, StaticFiles(directory=STATIC), name="phone-assets")

    @app.get("/phone", include_in_schema=False)
    async def phone_without_slash() -> RedirectResponse:
        return RedirectResponse(PHONE, status_code=307)

    @app.get(PHONE, include_in_schema=False)
    async def phone() -> FileResponse:
        return FileResponse(STATIC / "index.html", media_type="text/html", headers=PHONE_HEADERS)
