"""The console's web application (Starlette, served by uvicorn): one page, a JSON API and one event stream.

Starlette is a small, well-kept ASGI toolkit; the live state goes to every page by server-sent events (one
`text/event-stream` response per page, plain HTTP, reconnected by the browser by itself), which is all a
page that only listens needs (its buttons are ordinary POSTs). With a token (any bind off loopback needs one)
every request must carry it (`?token=` once, then the cookie it sets, or `Authorization: Bearer`).

The page draws its plots with plotly.js, the file that plotly's Python package ships (package_data/plotly.min.js):
the console serves it itself, so a page needs nothing beyond the console (a cell's network often has no
internet, and the tests have none).
"""

from __future__ import annotations

import asyncio
import hmac
import json
import secrets
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager, suppress
from dataclasses import asdict, dataclass, replace
from importlib import resources
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path
from typing import Any

import anyio
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.requests import Request
from starlette.responses import FileResponse, HTMLResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Route
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from hil.console.live import Answer
from hil.console.station import RequestRefusedError, RunRequest, Station
from hil.console.views import (
    COMPENSATED_SUFFIX,
    MODEL_SUFFIX,
    REPORT_SUFFIX,
    form,
    history,
    plan_view,
    point_deviations,
)
from hil.runner.registry import load, registered

CLIENT_COOKIE = "hil_console_client"  # which browser this is (control is given to one)
TOKEN_COOKIE = "hil_console_token"
PLOTLY_JS = "plotly/package_data/plotly.min.js"  # in plotly's wheel
PLOTLY_CACHE = "public, max-age=86400"  # 4.8 MB a page loads once a day, not on every reload
STREAM_KEEPALIVE_S = 10.0  # a page's stream sends the state at least this often


LOOPBACK_NAMES = ("127.0.0.1", "localhost")


@dataclass(frozen=True)
class ConsoleOptions:
    """How the console serves: its token (None: loopback only, no token asked) and the host names a request
    may address it by. On loopback without a token only the loopback names: a web page elsewhere that points
    a name of its own at 127.0.0.1 (DNS rebinding) is refused before it could take control of the cell."""

    token: str | None = None
    allowed_hosts: tuple[str, ...] = LOOPBACK_NAMES


def build_app(station: Station, options: ConsoleOptions) -> ASGIApp:
    """The console's ASGI application on `station`."""
    api = _Api(station)
    routes = [
        Route("/", api.page),
        Route("/assets/plotly.min.js", api.plotly_js),
        Route("/api/procedures", api.procedures),
        Route("/api/state", api.state),
        Route("/api/stream", api.stream),
        Route("/api/control", api.claim, methods=["POST"]),
        Route("/api/control/release", api.release, methods=["POST"]),
        Route("/api/plan", api.plan, methods=["POST"]),
        Route("/api/start", api.start, methods=["POST"]),
        Route("/api/pause", api.pause, methods=["POST"]),
        Route("/api/resume", api.resume, methods=["POST"]),
        Route("/api/abort", api.abort, methods=["POST"]),
        Route("/api/prompt/{prompt_id:int}", api.answer, methods=["POST"]),
        Route("/api/points/{campaign}", api.points),
        Route("/api/history", api.history),
        Route("/api/diagnose/{campaign}", api.diagnose, methods=["POST"]),
        Route("/api/compensate/{campaign}", api.compensate, methods=["POST"]),
        Route("/reports/{campaign}", api.report),
        Route("/compensated/{campaign}", api.compensated),
    ]
    middleware = [Middleware(TrustedHostMiddleware, allowed_hosts=list(options.allowed_hosts))]
    app = Starlette(routes=routes, lifespan=api.lifespan, middleware=middleware)
    return app if options.token is None else TokenGate(app, options.token)


class TokenGate:
    """Refuses every request that does not carry the token (401), whatever its path."""

    def __init__(self, app: ASGIApp, token: str) -> None:
        self.app, self.token = app, token

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        request = Request(scope)
        given = request.query_params.get("token")
        carried = request.cookies.get(TOKEN_COOKIE) or _bearer(request.headers.get("authorization", ""))
        if not any(self._matches(t) for t in (given, carried)):
            await Response(
                "this console asks for its token: open it with ?token=... (hil serve --token, or [console] "
                "token in the cell config)\n",
                status_code=401,
                media_type="text/plain",
            )(scope, receive, send)
            return
        if not self._matches(given):
            await self.app(scope, receive, send)
            return

        async def send_with_cookie(message: Message) -> None:  # ?token= once: the cookie carries it on
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                cookie = f"{TOKEN_COOKIE}={self.token}; Path=/; HttpOnly; SameSite=Strict"
                headers.append((b"set-cookie", cookie.encode("latin-1")))
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_cookie)

    def _matches(self, given: str | None) -> bool:
        return given is not None and hmac.compare_digest(given.encode(), self.token.encode())


def _bearer(header: str) -> str | None:
    kind, _, value = header.partition(" ")
    return value.strip() if kind.lower() == "bearer" else None


class _Api:
    """The routes' handlers on one station."""

    def __init__(self, station: Station) -> None:
        self.station = station
        self.closing = False

    # ------------------------------------------------------------------ page and state
    async def page(self, request: Request) -> Response:
        html = resources.files("hil.console").joinpath("page.html").read_text(encoding="utf-8")
        response = HTMLResponse(html)
        if CLIENT_COOKIE not in request.cookies:
            response.set_cookie(CLIENT_COOKIE, secrets.token_hex(16), httponly=True, samesite="strict")
        return response

    async def plotly_js(self, request: Request) -> Response:
        path = plotly_js_path()
        if path is None:
            return Response(
                "plotly.min.js is missing: the console's plots need the plotly package (pip install plotly)\n",
                status_code=404,
                media_type="text/plain",
            )
        return FileResponse(path, media_type="text/javascript", headers={"Cache-Control": PLOTLY_CACHE})

    async def procedures(self, request: Request) -> Response:
        forms = []
        for name in registered():
            try:
                forms.append(asdict(form(load(name))))
            except Exception as exc:  # noqa: BLE001 - a broken plug-in must not hide the others
                forms.append(
                    {"name": name, "purpose": f"(cannot load: {exc})", "instruction": "", "fields": []}
                )
        return JSONResponse({"procedures": forms, "cell": self.station.config.source})

    def _view(self, request: Request) -> dict:
        view = self.station.live.view()
        client = request.cookies.get(CLIENT_COOKIE)
        return {
            **replace(view, controller=self.station.controls(client)).as_json(),
            "controlled_elsewhere": self.station.controlled_by_another(client),
        }

    async def state(self, request: Request) -> Response:
        return JSONResponse(self._view(request))

    async def stream(self, request: Request) -> Response:
        """The state now, then after every change (and at least every STREAM_KEEPALIVE_S, for the ETA)."""
        loop = asyncio.get_running_loop()
        changed = asyncio.Event()
        client = request.cookies.get(CLIENT_COOKIE)

        async def events() -> AsyncIterator[str]:
            def wake() -> None:  # on the run's thread
                loop.call_soon_threadsafe(changed.set)

            stop = self.station.live.listen(wake)
            try:
                while not self.closing:
                    changed.clear()
                    self.station.seen(client)
                    yield f"data: {json.dumps(self._view(request))}\n\n"
                    with suppress(TimeoutError):
                        await asyncio.wait_for(changed.wait(), STREAM_KEEPALIVE_S)
            finally:
                stop()
                # a page that goes (a reload, a closed tab) was there until now: a controller's lapse counts
                # from here, not from its stream's last state, so a reloaded page finds its control again
                self.station.seen(client)

        return StreamingResponse(
            events(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
        )

    @asynccontextmanager
    async def lifespan(self, app: Starlette) -> AsyncIterator[None]:
        yield
        await self.shutdown()

    async def shutdown(self) -> None:
        """The server stops: abort a run (Ctrl-C's path), let the streams end."""
        self.closing = True
        if self.station.running:
            self.station.abort("the console was stopped")
            await anyio.to_thread.run_sync(self.station.join, 15.0)
        self.station.live.wake()

    # ------------------------------------------------------------------ control
    async def claim(self, request: Request) -> Response:
        client = request.cookies.get(CLIENT_COOKIE)
        if client is None or not self.station.claim(client):
            return _refused(
                RequestRefusedError(
                    "another browser controls this console; this one watches", "ask there to release it"
                ),
                403,
            )
        self.station.live.wake()
        return JSONResponse({"controller": True})

    async def release(self, request: Request) -> Response:
        client = request.cookies.get(CLIENT_COOKIE)
        if client is not None:
            self.station.release(client)
        self.station.live.wake()
        return JSONResponse({"controller": False})

    def _require_control(self, request: Request) -> None:
        client = request.cookies.get(CLIENT_COOKIE)
        if not self.station.controls(client):
            raise RequestRefusedError(
                "this browser watches: another one controls the console", "take control when it is free"
            )

    # ------------------------------------------------------------------ runs
    async def plan(self, request: Request) -> Response:
        try:
            checked = self.station.check(_run_request(await request.json()))
        except RequestRefusedError as exc:
            return _refused(exc, 400)
        return JSONResponse(asdict(plan_view(checked, self.station.config)))

    async def start(self, request: Request) -> Response:
        try:
            self._require_control(request)
        except RequestRefusedError as exc:
            return _refused(exc, 403)
        try:
            checked = self.station.start(_run_request(await request.json()))
        except RequestRefusedError as exc:
            return _refused(exc, 409 if "driven by" in exc.message or "already" in exc.message else 400)
        return JSONResponse(asdict(plan_view(checked, self.station.config)))

    async def pause(self, request: Request) -> Response:
        return self._button(request, self.station.pause)

    async def resume(self, request: Request) -> Response:
        return self._button(request, self.station.resume)

    async def abort(self, request: Request) -> Response:
        return self._button(request, self.station.abort)

    async def answer(self, request: Request) -> Response:
        body = await request.json()
        prompt_id = int(request.path_params["prompt_id"])
        answer = Answer.STOP if body.get("answer") == Answer.STOP else Answer.DONE
        return self._button(request, lambda: self.station.answer(prompt_id, answer))

    def _button(self, request: Request, press: Any) -> Response:
        try:
            self._require_control(request)
        except RequestRefusedError as exc:
            return _refused(exc, 403)
        try:
            press()
        except RequestRefusedError as exc:
            return _refused(exc, 409)
        return JSONResponse(self._view(request))

    # ------------------------------------------------------------------ campaigns
    async def points(self, request: Request) -> Response:
        try:
            path = self.station.campaign_path(request.path_params["campaign"])
        except RequestRefusedError as exc:
            return _refused(exc, 404)
        found = await anyio.to_thread.run_sync(point_deviations, path, self.station.config)
        return JSONResponse(asdict(found))

    async def history(self, request: Request) -> Response:
        entries = await anyio.to_thread.run_sync(history, self.station.campaigns)
        return JSONResponse(
            {"folder": str(self.station.campaigns), "campaigns": [asdict(e) for e in entries]}
        )

    async def report(self, request: Request) -> Response:
        found = self._beside_campaign(request, REPORT_SUFFIX, "report", "diagnose it first")
        return found if isinstance(found, Response) else FileResponse(found, media_type="text/html")

    async def diagnose(self, request: Request) -> Response:
        """`hil diagnose CAMPAIGN --html REPORT -o MODEL` on a campaign nobody drives: the report `--html`
        writes, and the model a compensation from the page then uses."""
        path = self._finished_campaign(request)
        if isinstance(path, Response):
            return path
        report = path.with_name(path.name + REPORT_SUFFIX)
        model = path.with_name(path.name + MODEL_SUFFIX)
        command = [
            "diagnose", str(path), "--robot", self.station.config.robot_model,
            "--html", str(report), "-o", str(model), "--force",
        ]  # fmt: skip
        return await _hil_writing(command, f"the diagnosis of {path.name}", "report", report)

    async def compensate(self, request: Request) -> Response:
        """`hil compensate MODEL CAMPAIGN --step validation --interval 0.95` with the model the page's diagnosis
        wrote: the joints that reach the campaign's validation targets, each with its predicted remaining
        error and interval, in a CSV beside the campaign (nothing moves)."""
        path = self._finished_campaign(request)
        if isinstance(path, Response):
            return path
        model = path.with_name(path.name + MODEL_SUFFIX)
        if not model.is_file():
            return _refused(RequestRefusedError(f"{path.name} has no model yet", "diagnose it first"), 409)
        out = path.with_name(path.name + COMPENSATED_SUFFIX)
        command = [
            "compensate", str(model), str(path), "--step", "validation", "--interval", "0.95",
            "-o", str(out), "--force",
        ]  # fmt: skip
        return await _hil_writing(command, f"the compensation of {path.name}", "compensated", out)

    async def compensated(self, request: Request) -> Response:
        found = self._beside_campaign(request, COMPENSATED_SUFFIX, "compensation", "compensate it first")
        if isinstance(found, Response):
            return found
        return FileResponse(found, media_type="text/csv", filename=found.name)

    def _beside_campaign(self, request: Request, suffix: str, what: str, remedy: str) -> Path | Response:
        """A result written beside the campaign the request names (its report, its compensated joints), or
        the refusal (404) when there is no such campaign or no such result yet."""
        name = request.path_params["campaign"]
        try:
            path = self.station.campaign_path(name)
        except RequestRefusedError as exc:
            return _refused(exc, 404)
        result = path.with_name(path.name + suffix)
        if not result.is_file():
            return _refused(RequestRefusedError(f"{name} has no {what} yet", remedy), 404)
        return result

    def _finished_campaign(self, request: Request) -> Path | Response:
        """The campaign a result is asked for, or the refusal: this browser must control the console (403),
        the campaign must exist (404)."""
        try:
            self._require_control(request)
            path = self.station.campaign_path(request.path_params["campaign"])
        except RequestRefusedError as exc:
            return _refused(exc, 403)
        if not path.is_file():
            return _refused(RequestRefusedError(f"no campaign {path.name} in {path.parent}"), 404)
        return path


def plotly_js_path() -> Path | None:
    """plotly.js as plotly's Python package installs it (found through the package's metadata, without
    importing it), or None when it is not there."""
    try:
        path = Path(str(distribution("plotly").locate_file(PLOTLY_JS)))
    except PackageNotFoundError:
        return None
    return path if path.is_file() else None


async def _hil(args: list[str]) -> tuple[bool, str]:
    """A hil command in its own process (the console's run and the analysis never share one): whether it
    succeeded, and what it printed."""
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "hil", *args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT
    )
    out, _ = await process.communicate()
    return process.returncode == 0, out.decode("utf-8", "replace").strip()


async def _hil_writing(args: list[str], what: str, key: str, written: Path) -> Response:
    """Run a hil command that writes `written` beside a campaign: the file's name (under `key`) and the last
    lines it printed, or `what` refused as failed with the lines that say why."""
    ok, text = await _hil(args)
    if not ok:
        return _refused(RequestRefusedError(f"{what} failed", _last_lines(text)), 422)
    return JSONResponse({key: written.name, "output": _last_lines(text, 12)})


def _run_request(body: Any) -> RunRequest:
    if not isinstance(body, dict):
        raise RequestRefusedError("the request is not a form")
    values = body.get("values") or {}
    return RunRequest(str(body.get("procedure", "")), str(body.get("campaign", "")), dict(values))


def _refused(exc: RequestRefusedError, status: int) -> Response:
    return JSONResponse({"message": exc.message, "remedy": exc.remedy}, status_code=status)


def _last_lines(text: str, n: int = 6) -> str:
    return "\n".join(text.splitlines()[-n:])
