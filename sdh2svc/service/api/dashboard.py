"""The dashboard's page and files, and the API's own docs (``/docs``, ``/redoc``), all packaged:
nothing loads from elsewhere (the lab PC may be offline)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles

from sdh2svc.service.hand_service import ServiceError

DOCS_ASSETS = "/docs-assets"  # Swagger UI and ReDoc, served from the fastapi-offline package
_FAVICON = f"{DOCS_ASSETS}/favicon.png"

router = APIRouter(include_in_schema=False)


def docs_assets_dir() -> Path:
    """Swagger UI's and ReDoc's files, packaged (no CDN: the lab PC may be offline)."""
    return Path(str(resources.files("fastapi_offline") / "static"))


def web_dir() -> Path:
    """The dashboard's files: packaged (wheel) or the repository's ``web/``."""
    packaged = resources.files("sdh2svc") / "_web"
    if packaged.is_dir():
        return Path(str(packaged))
    return Path(__file__).resolve().parents[3] / "web"


def mount_files(app: FastAPI) -> None:
    """The docs' assets and the dashboard's files (when installed) as static mounts."""
    app.mount(DOCS_ASSETS, StaticFiles(directory=docs_assets_dir()), name="docs-assets")
    static = web_dir()
    if static.is_dir():
        app.mount("/web", StaticFiles(directory=static), name="web")


@router.get("/")
def index() -> FileResponse:
    page = web_dir() / "index.html"
    if not page.is_file():
        raise ServiceError(404, f"the dashboard is not installed ({page} missing)")
    return FileResponse(page)


@router.get("/docs")
def swagger() -> HTMLResponse:
    return get_swagger_ui_html(
        openapi_url="/openapi.json", title="sdh2svc API",
        swagger_js_url=f"{DOCS_ASSETS}/swagger-ui-bundle.js",
        swagger_css_url=f"{DOCS_ASSETS}/swagger-ui.css", swagger_favicon_url=_FAVICON,
        swagger_ui_parameters={"validatorUrl": None},  # no badge from validator.swagger.io
    )  # fmt: skip


@router.get("/redoc")
def redoc() -> HTMLResponse:
    return get_redoc_html(openapi_url="/openapi.json", title="sdh2svc API",
                          redoc_js_url=f"{DOCS_ASSETS}/redoc.standalone.js",
                          redoc_favicon_url=_FAVICON, with_google_fonts=False)  # fmt: skip
