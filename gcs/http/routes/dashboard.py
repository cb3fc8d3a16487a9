"""What the dashboard loads: health, its config, map tiles, its static files (``/ui``) and ``/docs``.

The static files (gcs/web/) and Swagger UI are mounted by :func:`mount_dashboard`, served locally:
no CDN, works offline.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sqlite3
import time
from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import RedirectResponse, Response
from fastapi.staticfiles import StaticFiles

from gcs.http.deps import Agents, ApiProblem, Missions, Ports
from gcs.http.models import Health, UiConfig

log = logging.getLogger("gcs.api")
WEB_DIR = Path(__file__).parents[2] / "web"
router = APIRouter()


@router.get("/api/v1/health")
async def health(agents: Agents, missions: Missions) -> Health:
    return Health(
        ok=True,
        agents_connected=len(agents.connected()),
        missions=len(missions.active),
        server_time=time.time(),
    )


@router.get("/api/v1/ui-config")
async def ui_config(ports: Ports) -> UiConfig:
    config = ports.config()
    tile_url = "/api/v1/tiles/{z}/{x}/{y}" if config.tile_mbtiles is not None else config.tile_url
    return UiConfig(tile_url=tile_url, status_period_s=config.status_period_s, cluster=bool(config.cluster))


@router.get("/api/v1/tiles/{z}/{x}/{y}", include_in_schema=False)
async def tile(z: int, x: int, y: int, ports: Ports) -> Response:
    """One map tile from the configured MBTiles file (XYZ numbering; MBTiles rows are TMS)."""
    mbtiles = ports.config().tile_mbtiles
    if mbtiles is None:
        raise ApiProblem(404, "no tiles", "no tile_mbtiles file is configured")
    data = await asyncio.to_thread(read_tile, mbtiles, z, x, y)
    if data is None:
        raise ApiProblem(404, "no such tile", f"{z}/{x}/{y} is not in {Path(mbtiles).name}")
    kind = "image/png" if data[:4] == b"\x89PNG" else "image/jpeg"
    if data[:4] == b"RIFF":
        kind = "image/webp"
    return Response(data, media_type=kind, headers={"Cache-Control": "max-age=86400"})


def read_tile(path: Path | str, z: int, x: int, y: int) -> bytes | None:
    """The tile z/x/y (XYZ, as the dashboard asks) of an MBTiles file, or None."""
    if not (0 <= z <= 24 and 0 <= x < 2**z and 0 <= y < 2**z):
        return None
    uri = f"{Path(path).resolve().as_uri()}?mode=ro"
    with contextlib.closing(sqlite3.connect(uri, uri=True)) as db:
        row = db.execute(
            "SELECT tile_data FROM tiles WHERE zoom_level=? AND tile_column=? AND tile_row=?",
            (z, x, (1 << z) - 1 - y),
        ).fetchone()
    return None if row is None else bytes(row[0])


@router.get("/", include_in_schema=False)
async def root() -> RedirectResponse:
    return RedirectResponse("/ui/")


def mount_dashboard(app: FastAPI) -> None:
    """The dashboard's files at /ui and Swagger UI at /docs (a 503 / a hint if not installed)."""
    if WEB_DIR.is_dir():
        app.mount("/ui", StaticFiles(directory=WEB_DIR, html=True), name="ui")
    else:  # an install without package data: say so instead of a silent 404
        log.warning("dashboard files missing (%s): / will answer 503", WEB_DIR)

        @app.get("/ui/", include_in_schema=False)
        async def no_dashboard() -> Response:
            raise ApiProblem(503, "dashboard not installed", f"{WEB_DIR} is missing from this install")

    _mount_docs(app)


def _mount_docs(app: FastAPI) -> None:
    """Swagger UI at /docs from the swagger-ui-bundle package's files, so it works offline."""
    try:
        from swagger_ui_bundle import swagger_ui_path
    except ImportError:
        swagger_ui_path = None
    if swagger_ui_path is None or not Path(str(swagger_ui_path)).is_dir():

        @app.get("/docs", include_in_schema=False)
        async def docs_missing() -> Response:
            return Response(
                "Swagger UI is not installed (pip install swagger-ui-bundle-v2); "
                "the API description is at /openapi.json",
                media_type="text/plain",
            )

        return
    app.mount("/docs-assets", StaticFiles(directory=str(swagger_ui_path)), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    async def docs() -> Response:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title="fleetgcs API",
            swagger_js_url="/docs-assets/swagger-ui-bundle.js",
            swagger_css_url="/docs-assets/swagger-ui.css",
            swagger_favicon_url="/docs-assets/favicon-32x32.png",
        )
